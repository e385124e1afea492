"""Retraining: `detmatch retrain` (a round, or rounds on a schedule) and `detmatch demo` (the
whole product in one command)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from commands.common import add_device_option, add_store_options, store_location
from detmatch.constants import RETRAIN_LOCK_HELD_EXIT
from retrain.demo_results import DEFAULT_OUT, DEFAULT_SIZE, SIZES, describe_sizes


def retrain(args: argparse.Namespace) -> int:
    from detmatch.training.distributed import init_distributed, shutdown_distributed
    from export.graphs import ExportCheckError
    from retrain.round import RoundOutcome, RoundRequest
    from retrain.schedule import LockHeld, parse_period, run_scheduled

    every = parse_period(args.every) if args.every else None
    if args.times is not None and (every is None or args.times < 1):
        raise ValueError("--times N (N >= 1) goes with --every")
    store = store_location(args)
    for name in ("store", "data", "repository"):
        if name == "store" and not isinstance(store, Path):
            continue
        if not Path(getattr(args, name)).is_dir():
            raise FileNotFoundError(f"--{name} {getattr(args, name)}: no such directory")
    repository = Path(args.repository)
    request = RoundRequest(
        store=store,
        data=Path(args.data),
        repository=repository,
        work=Path(args.work) if args.work else repository / ".retrain",
        config=args.config,
        overrides=tuple(args.set),
        force=args.force,
    )
    context = init_distributed(args.device)

    def report(outcome: RoundOutcome) -> None:
        if context.is_main:
            print(outcome.message, flush=True)
            if outcome.report is not None:
                print(f"report: {outcome.report}", flush=True)

    try:
        run_scheduled(request, context, every, args.times, report=report)
    except LockHeld as error:
        print(f"detmatch retrain: {error}", file=sys.stderr)
        return RETRAIN_LOCK_HELD_EXIT
    except ExportCheckError as error:
        print(f"detmatch retrain: the candidate failed its export checks, nothing was "
              f"published: {error}", file=sys.stderr)  # fmt: skip
        return 1
    except KeyboardInterrupt:
        print("detmatch retrain: interrupted; the next run resumes the round", file=sys.stderr)
        return 130
    finally:
        shutdown_distributed()
    return 0


def demo(args: argparse.Namespace) -> int:
    from retrain.demo import run_demo

    started = time.monotonic()
    report = run_demo(args.out, args.size, args.seed, args.workers, args.device)
    print(f"demo finished in {time.monotonic() - started:.0f} s")
    print(f"report: {report}")
    return 0


def add_parsers(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "retrain",
        help="a retraining round: the label store's frames -> a new version, promoted only if "
        "it does not regress",
        description="Continue teacher-student training from the served version with the "
        "original labeled frames and every stored frame (all shards) in the unlabeled pool; "
        "score the candidate and the served version on the held-out gate split ([data] "
        "val_split of --data); export the candidate and promote it only if neither its 2D nor "
        "its 3D moderate mAP drops more than [retrain] max_map_drop. Skips when the store "
        "holds nothing new since the last round. Exit status: 0 done (promoted, not promoted "
        "or skipped), 1 the export checks failed, 2 bad input, 3 another retraining holds the "
        "repository's lock.",
    )
    add_store_options(parser, True, "label store (every shard)")
    parser.add_argument(
        "--data", required=True, help="the original data set: labeled frames, pool and gate split"
    )
    parser.add_argument("--repository", required=True, help="model repository")
    parser.add_argument(
        "--config",
        help="TOML config file or packaged config name (default: the served version's config, "
        "kept in its manifest); it must describe the same detectors",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a config key, e.g. retrain.steps=500, retrain.max_map_drop=0.5, "
        "retrain.stored_labels=labeled, data.val_split=gate (repeatable)",
    )
    parser.add_argument(
        "--work",
        help="working directory: the round in progress and past rounds' reports (default: "
        "REPOSITORY/.retrain)",
    )
    parser.add_argument(
        "--every",
        metavar="PERIOD",
        help="run in the foreground, a round every PERIOD (90s, 15m, 24h, 7d)",
    )
    parser.add_argument("--times", type=int, help="with --every: stop after N periods")
    parser.add_argument(
        "--force", action="store_true", help="train even if the store holds nothing new"
    )
    add_device_option(parser)
    parser.set_defaults(handler=retrain)

    parser = commands.add_parser(
        "demo",
        help="the whole product in one command: synthetic data, pre-training, DetMatch, "
        "export, the service, labeling through gRPC, a retraining round, a report",
        description="Generate a synthetic data set, pre-train both detectors, run DetMatch, "
        "compare them on val, export, start `detmatch serve`, label unseen frames through gRPC "
        "into the label store, run one retraining round from the stored labels (promoted if "
        "it passes) and write a report directory; its path is printed at the end. Sizes: "
        + describe_sizes(),
    )
    parser.add_argument("--size", choices=tuple(SIZES), default=DEFAULT_SIZE,
                        help="how big a run (see above)")  # fmt: skip
    parser.add_argument("--out", default=DEFAULT_OUT, help="output directory (new or empty)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic data")
    parser.add_argument("--workers", type=int, default=2, help="processes rendering frames")
    add_device_option(parser)
    parser.set_defaults(handler=demo)
