"""Training: checkpoints, distributed set-up, the train loop and inference helpers."""
