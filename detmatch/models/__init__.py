"""Detectors. `pillars` is numpy-only (serving imports it); the detectors need torch."""
