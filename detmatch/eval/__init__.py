"""Evaluation: KITTI object-benchmark AP and pseudo-label quality."""
