"""Run under torchrun by tests/training/test_training.py: trains the tiny config with DDP and
saves this rank's weights so the test can compare ranks."""

import sys
from pathlib import Path

import torch

from detmatch.config import load_config
from detmatch.training.distributed import init_distributed, shutdown_distributed
from detmatch.training.trainer import SupervisedTrainer


def main() -> None:
    config_path, data_root, run_dir = sys.argv[1:4]
    config = load_config(config_path).replace("data", root=data_root)
    context = init_distributed()
    trainer = SupervisedTrainer(config, Path(run_dir), context)
    state = trainer.run()
    weights = {"model_2d": state.model_2d.state_dict(), "model_3d": state.model_3d.state_dict()}
    torch.save(weights, Path(run_dir) / f"rank{context.rank}_of_{context.world_size}.pt")
    shutdown_distributed()


if __name__ == "__main__":
    main()
