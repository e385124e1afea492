"""Data: KITTI layout I/O, the synthetic paired data set, splits and pictures."""
