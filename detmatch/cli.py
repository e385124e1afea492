"""The `detmatch` command: one thin function per subcommand, delegating to the library."""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from detmatch.config import DEVICES, METHODS, PRESETS, packaged_configs
from detmatch.data.kitti import SUBSETS

# `detmatch serve --host` when not given: the Docker image sets 0.0.0.0 (all interfaces).
HOST_ENV = "DETMATCH_HOST"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's default in --help, except where there is none (None, False, "", []) or
    the help text already states it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        help_text = action.help or ""
        default = action.default
        if (
            default is None
            or default is False
            or default is argparse.SUPPRESS
            or (isinstance(default, str | list) and not default)
            or "default" in help_text
        ):
            return help_text
        return super()._get_help_string(action)


def package_version() -> str:
    """The installed distribution's version (the source tree's when not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("detmatch")
    except PackageNotFoundError:
        from detmatch import __version__

        return __version__


def show_defaults(parser: argparse.ArgumentParser) -> None:
    """HelpFormatter for the parser and all its subcommands, however deeply nested."""
    parser.formatter_class = HelpFormatter
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                show_defaults(subparser)


def add_version_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--version", action="version", version=f"{parser.prog} {package_version()}")


def _synth(args: argparse.Namespace) -> int:
    from detmatch.data.synth import generate_dataset

    generate_dataset(
        out_dir=Path(args.out),
        num_frames=args.frames,
        seed=args.seed,
        resolution=args.resolution,
        workers=args.workers,
        val_fraction=args.val_fraction,
        progress=not args.quiet,
    )
    print(f"wrote {args.frames} frames to {args.out}")
    return 0


def _split(args: argparse.Namespace) -> int:
    from detmatch.data.splits import make_split

    result = make_split(
        Path(args.data), args.fraction, args.seed, args.source, dev_fraction=args.dev_fraction
    )
    if result.dev_path is not None:
        print(f"dev:       {result.num_dev:6d} frames -> {result.dev_path}")
    print(
        f"labeled:   {result.num_labeled:6d} frames -> {result.labeled_path}\n"
        f"unlabeled: {result.num_unlabeled:6d} frames -> {result.unlabeled_path}"
    )
    return 0


def _show(args: argparse.Namespace) -> int:
    from detmatch.data.kitti import KittiDataset, read_objects
    from detmatch.data.visualize import save_frame_picture

    dataset = KittiDataset(Path(args.data), args.subset)
    frame = dataset.load_frame(args.frame)
    predictions = None
    if args.predictions:
        predictions = read_objects(Path(args.predictions) / f"{args.frame}.txt")
    save_frame_picture(frame, Path(args.out), predictions=predictions)
    print(f"wrote {args.out}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from detmatch.data.kitti import read_image_set
    from detmatch.eval.kitti import evaluate_dirs, format_table

    if args.all:
        ids = sorted(path.stem for path in Path(args.gt_dir).glob("*.txt"))
        if not ids:
            raise FileNotFoundError(f"no label files (ID.txt) in {args.gt_dir}")
    else:
        ids = read_image_set(args.ids_file)
    classes = [c.strip() for c in args.classes.split(",") if c.strip()]
    results = evaluate_dirs(Path(args.gt_dir), Path(args.pred_dir), ids, classes)
    print(format_table(results))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


def refuse_existing_run(out: Path, resume: bool) -> None:
    """A run directory that exists and is not empty is another run: training into it would
    append to its metrics.jsonl and overwrite its checkpoints. Only --resume may continue it."""
    if resume or not out.exists():
        return
    if not out.is_dir():
        raise FileExistsError(f"--out {out} exists and is not a directory")
    if any(out.iterdir()):
        raise FileExistsError(
            f"--out {out} already holds a run (it is not empty): pass --resume to continue it, "
            "or choose a new run directory"
        )


def _train(args: argparse.Namespace) -> int:
    from detmatch.config import (
        apply_overrides,
        apply_preset,
        load_config,
        refuse_pretraining_overrides,
        teacher_student_config,
    )

    # Before any process of a torchrun job writes (init_distributed is their rendezvous).
    refuse_existing_run(Path(args.out), args.resume)
    config = apply_overrides(load_config(args.config), args.set)
    if args.preset:
        config = apply_preset(config, args.preset)
    if args.data:
        config = config.replace("data", root=args.data)
    if args.method:
        config = config.replace("ssl", method=args.method)
    if args.pretrained:
        config = config.replace("ssl", pretrained=args.pretrained)
    refuse_pretraining_overrides(config, args.set)
    if args.steps is not None:  # the run's length: the stage's for a teacher-student method
        section = "train" if config.ssl.method == "labeled-only" else "ssl"
        config = config.replace(section, steps=args.steps)
    config = teacher_student_config(config)
    if config.ssl.method != "labeled-only" and not config.ssl.pretrained and not args.resume:
        raise ValueError(
            f"--method {config.ssl.method} starts from pre-trained weights: pass --pretrained "
            "CKPT (a labeled-only run) or set [ssl] pretrained"
        )
    from detmatch.training.distributed import init_distributed, shutdown_distributed
    from detmatch.training.semi_supervised import trainer_type

    context = init_distributed(args.device)
    try:
        trainer = trainer_type(config.ssl.method)(config, Path(args.out), context)
        if args.resume and trainer.resume() and context.is_main:
            print(f"resumed {args.out} at step {trainer.state.step}")
        state = trainer.run()
        if context.is_main:
            print(json.dumps({"step": state.step, "metrics": _headline(state.metrics)}, indent=2))
    finally:
        shutdown_distributed()
    return 0


def _headline(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if not k.startswith("full_")}


def _frames(args: argparse.Namespace):
    from detmatch.data.selection import FrameSelection

    ids_file = Path(args.ids_file) if args.ids_file else None
    return FrameSelection(args.split, ids_file, args.all, args.subset)


def _predict(args: argparse.Namespace) -> int:
    from detmatch.inference import predict_split

    count = predict_split(Path(args.checkpoint), Path(args.data), _frames(args), Path(args.out))
    print(f"wrote predictions for {count} frames to {args.out}/3d and {args.out}/2d")
    return 0


def _label(args: argparse.Namespace) -> int:
    from serving.labeler import Labeler
    from serving.offline import label_split
    from serving.store import LabelStore

    if not args.out and not args.store:
        raise ValueError("give --out DIR (result files), --store DIR (the label store) or both")
    frames = _frames(args)
    labeler = Labeler.from_repository(Path(args.repository), args.version)
    store = LabelStore(Path(args.store), args.shard) if args.store else None
    try:
        summary = label_split(
            labeler, Path(args.data), frames, Path(args.out) if args.out else None,
            args.tau_hung, store=store, namespace=args.namespace,
        )  # fmt: skip
    finally:
        if store is not None:
            store.close()
    where = []
    if args.out:
        where.append(f"{args.out}/3d, {args.out}/2d, {args.out}/labels")
    if store is not None:
        where.append(
            f"label store {args.store} shard {store.shard} ({summary.stored} frames stored, "
            f"{summary.already_stored} already there)"
        )
    print(
        f"labeled {summary.frames} frames with model version {summary.model_version}: "
        f"{summary.labels} labels ({summary.matched} matched 2D-3D, {summary.lidar_only} "
        f"LiDAR-only) -> {'; '.join(where)}"
    )
    return 0


def _serve(args: argparse.Namespace) -> int:
    import os

    from serving.errors import StoreError
    from serving.logs import configure_logging
    from serving.server import ServerConfig, format_address, serve

    token = os.environ.get(args.token_env, "")
    if args.no_auth and token:
        raise ValueError(
            f"--no-auth, but ${args.token_env} holds a token: unset it, or drop --no-auth"
        )
    if not args.no_auth:
        if not token.strip():
            state = "is empty" if args.token_env in os.environ else "is not set"
            raise ValueError(
                f"${args.token_env} (--token-env) {state}, and authentication is never silently "
                f"off: put the bearer token clients must send in ${args.token_env}, or pass "
                "--no-auth to run without authentication"
            )
        if not token.isascii() or not token.isprintable() or token != token.strip():
            raise ValueError(f"${args.token_env}: a token is printable ASCII without spaces")
    configure_logging()
    config = ServerConfig(
        address=format_address(args.host, args.port),
        workers=args.workers,
        threads=args.threads,
        max_message_bytes=args.max_message_mb * 1024 * 1024,
        max_image_pixels=args.max_image_pixels,
        max_concurrent_rpcs=args.max_concurrent_rpcs,
        receive_timeout_s=args.receive_timeout_s,
        tls_cert=Path(args.tls_cert) if args.tls_cert else None,
        tls_key=Path(args.tls_key) if args.tls_key else None,
        token=None if args.no_auth else token,
        metrics_port=args.metrics_port,
        metrics_address=args.metrics_host or args.host,
        poll_s=args.poll_s,
        grace_s=args.grace_s,
    )
    try:
        serve(Path(args.repository), Path(args.store), config, shard=args.shard)
    except (OSError, StoreError) as error:  # a port in use, a shard held by another server
        raise ValueError(str(error)) from None
    return 0


def _health(args: argparse.Namespace) -> int:
    from serving.health_check import wait_until_serving

    status = wait_until_serving(
        args.target,
        args.wait_s,
        service=args.service,
        timeout_s=args.timeout_s,
        root_certificates=Path(args.ca_cert).read_bytes() if args.ca_cert else None,
        server_name=args.server_name,
    )
    print(status)
    return 0 if status == "SERVING" else 1


def _retrain(args: argparse.Namespace) -> int:
    from detmatch.training.distributed import init_distributed, shutdown_distributed
    from export.graphs import ExportCheckError
    from retrain.round import RoundOutcome, RoundRequest
    from retrain.schedule import LockHeld, parse_period, run_scheduled

    every = parse_period(args.every) if args.every else None
    if args.times is not None and (every is None or args.times < 1):
        raise ValueError("--times N (N >= 1) goes with --every")
    for name in ("store", "data", "repository"):
        if not Path(getattr(args, name)).is_dir():
            raise FileNotFoundError(f"--{name} {getattr(args, name)}: no such directory")
    repository = Path(args.repository)
    request = RoundRequest(
        store=Path(args.store),
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
        return 3
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


def _demo(args: argparse.Namespace) -> int:
    from retrain.demo import run_demo

    started = time.monotonic()
    report = run_demo(args.out, args.size, args.seed, args.workers, args.device)
    print(f"demo finished in {time.monotonic() - started:.0f} s")
    print(f"report: {report}")
    return 0


def _store_export(args: argparse.Namespace) -> int:
    from serving.store import export_store

    summary = export_store(
        Path(args.store), Path(args.out), args.val_fraction, args.seed, args.namespace or None
    )
    print(
        f"exported {summary.frames} stored frames of namespace(s) {', '.join(summary.namespaces)}"
        f" to {args.out} (KITTI layout, labels in label_2): ImageSets/train.txt {summary.train},"
        f" val.txt {summary.val} frames"
    )
    return 0


def _add_frame_selection(parser: argparse.ArgumentParser) -> None:
    """--split | --ids-file | --all, and --subset: which frames of --data to read."""
    frames = parser.add_mutually_exclusive_group(required=True)
    frames.add_argument("--split", help="ImageSets split: the ids in DATA/ImageSets/SPLIT.txt")
    frames.add_argument("--ids-file", help="a file of frame ids, one a line (no ImageSets needed)")
    frames.add_argument(
        "--all", action="store_true", help="every frame with an image (PNG or JPEG) in image_2/"
    )
    parser.add_argument(
        "--subset",
        choices=SUBSETS,
        help="DATA's subset directory to read (default: training/ if DATA has one, else testing/)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="detmatch", description="Joint 2D-3D semi-supervised detection (DetMatch)."
    )
    add_version_option(parser)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    synth = commands.add_parser("synth", help="generate a synthetic paired camera + LiDAR data set")
    synth.add_argument("--out", required=True, help="output directory (KITTI layout)")
    synth.add_argument("--frames", type=int, required=True, help="number of frames")
    synth.add_argument("--seed", type=int, default=0, help="random seed (same seed, same bytes)")
    synth.add_argument("--resolution", choices=("full", "half"), default="half",
                       help="full = 1242x375 (KITTI), half = 621x188")  # fmt: skip
    synth.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    synth.add_argument("--val-fraction", type=float, default=0.25,
                       help="fraction of frames in ImageSets/val.txt")  # fmt: skip
    synth.add_argument("--quiet", action="store_true", help="no progress bar")
    synth.set_defaults(handler=_synth)

    split = commands.add_parser(
        "split", help="write a labeled / unlabeled split of the train frames"
    )
    split.add_argument("--data", required=True, help="KITTI-layout data set root")
    split.add_argument("--fraction", type=float, required=True, help="labeled fraction in (0, 1)")
    split.add_argument("--seed", type=int, default=0, help="random seed of the labeled subset")
    split.add_argument("--source", default="train", help="ImageSets split to divide")
    split.add_argument(
        "--dev-fraction",
        type=float,
        default=0.0,
        help="first hold out this fraction of the source as a labeled dev split for tuning "
        "(the same frames for every seed); 0: no dev split",
    )
    split.set_defaults(handler=_split)

    show = commands.add_parser("show", help="render a frame: image with 2D boxes + bird's-eye view")
    show.add_argument("--data", required=True, help="KITTI-layout data set root")
    show.add_argument("--subset", choices=SUBSETS, default="training",
                      help="DATA's subset directory")  # fmt: skip
    show.add_argument("--frame", required=True, help="frame id, e.g. 000001")
    show.add_argument("--out", required=True, help="output PNG")
    show.add_argument("--predictions", help="directory of KITTI result files to overlay (dashed)")
    show.set_defaults(handler=_show)

    train = commands.add_parser("train", help="train the 2D and 3D detectors")
    train.add_argument(
        "--config",
        required=True,
        help=f"TOML config file, or a packaged config's name: {', '.join(packaged_configs())}",
    )
    train.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override any config key, e.g. train.steps=100, data.image_size=[320,96], "
        "ssl.tau_hung=-2 (repeatable; values are TOML literals, bare words are strings; "
        "--preset, --data, --steps, --method and --pretrained apply after them)",
    )
    train.add_argument("--data", help="data set root; overrides [data] root")
    train.add_argument(
        "--out",
        required=True,
        help="run directory: checkpoints, metrics.jsonl; must be new or empty unless --resume",
    )
    train.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its latest checkpoint (a new run if it has none)",
    )
    train.add_argument(
        "--steps",
        type=int,
        help="override the run's steps ([train] steps; a teacher-student method's [ssl] steps)",
    )
    train.add_argument(
        "--method",
        choices=METHODS,
        help="override [ssl] method: labeled-only (pre-training, [train]'s schedule), "
        "labeled-only-control (the pre-trained model continued with an EMA teacher, no "
        "unlabeled data), confidence thresholding or DetMatch; the teacher-student methods "
        "train [ssl] steps at [ssl] lr_2d / lr_3d, constant after [ssl] warmup_steps",
    )
    train.add_argument("--pretrained", help="override [ssl] pretrained: the labeled-only run")
    train.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        help="named DetMatch settings, applied after --set (paper: the paper's constants and "
        "loss as published; the defaults are what won on dev, BENCHMARKS.md)",
    )
    train.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where to train: auto (a CUDA GPU when there is one), cpu or cuda",
    )
    train.set_defaults(handler=_train)

    predict = commands.add_parser("predict", help="write KITTI result files of both detectors")
    predict.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    predict.add_argument("--data", required=True, help="KITTI-layout data set root")
    _add_frame_selection(predict)
    predict.add_argument("--out", required=True, help="output directory (gets 3d/ and 2d/)")
    predict.set_defaults(handler=_predict)

    label = commands.add_parser(
        "label", help="label a data set with an exported model version (onnxruntime, no torch)"
    )
    label.add_argument("--repository", required=True, help="model repository (detmatch-export)")
    label.add_argument("--version", help="model version (default: the newest promoted one)")
    label.add_argument("--data", required=True, help="KITTI-layout data set root")
    _add_frame_selection(label)
    label.add_argument("--out", help="output directory (gets 3d/, 2d/, labels/)")
    label.add_argument(
        "--store",
        help="label store directory: store every frame and its labels as the service does "
        "(what `detmatch retrain` reads); with or without --out",
    )
    label.add_argument("--shard", default="offline", help="the label store shard written")
    label.add_argument("--namespace", default="default",
                       help="the data set's namespace in the label store (keys are namespace + "
                       "frame id, so two data sets' 000000 do not collide)")  # fmt: skip
    label.add_argument("--tau-hung", type=float, help="matching threshold (default: manifest's)")
    label.set_defaults(handler=_label)

    serve = commands.add_parser(
        "serve",
        help="run the gRPC auto-labeling service (no torch)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    serve.add_argument("--repository", required=True, help="model repository (detmatch-export)")
    serve.add_argument("--store", required=True, help="label store directory")
    serve.add_argument("--port", type=int, default=50051, help="0 picks a free port")
    serve.add_argument("--host", default=os.environ.get(HOST_ENV) or "127.0.0.1",
                       help=f"address to bind: 0.0.0.0 (or ::) listens on every interface, as a "
                       f"container must (default: ${HOST_ENV}, else 127.0.0.1)")  # fmt: skip
    serve.add_argument("--workers", type=int, default=4,
                       help="inference threads: frames decoded and labeled at once")  # fmt: skip
    serve.add_argument("--threads", type=int, default=0,
                       help="onnxruntime threads per model run; 0: the CPUs this process may "
                       "use (its CPU set and its cgroup's CPU quota)")  # fmt: skip
    serve.add_argument("--shard", default=socket.gethostname().split(".")[0] or "default",
                       help="this replica's label store shard (default: host name)")  # fmt: skip
    serve.add_argument("--max-message-mb", type=int, default=64, help="largest request, MiB")
    serve.add_argument("--max-image-pixels", type=int, default=3840 * 2160,
                       help="largest image (width x height), checked before decoding")  # fmt: skip
    serve.add_argument("--max-concurrent-rpcs", type=int, default=64,
                       help="labeling calls at once; RESOURCE_EXHAUSTED beyond (health and "
                       "reflection always answer)")  # fmt: skip
    serve.add_argument("--receive-timeout-s", type=float, default=30.0,
                       help="a request message must arrive within this; slower clients get "
                       "DEADLINE_EXCEEDED")  # fmt: skip
    serve.add_argument("--tls-cert", help="PEM server certificate (with --tls-key)")
    serve.add_argument("--tls-key", help="PEM server private key")
    serve.add_argument("--token-env", default="DETMATCH_TOKEN",
                       help="variable holding the bearer token clients must send; the server "
                       "refuses to start when it is unset or empty, unless --no-auth")  # fmt: skip
    serve.add_argument("--no-auth", action="store_true",
                       help="run without authentication (any client reaching the port may "
                       "label and store)")  # fmt: skip
    serve.add_argument("--metrics-port", type=int, help="Prometheus /metrics port (off if unset)")
    serve.add_argument("--metrics-host",
                       help="address the metrics endpoint binds (default: --host's; 0.0.0.0: "
                       "scrapable from other hosts)")  # fmt: skip
    serve.add_argument("--poll-s", type=float, default=2.0, help="model repository poll period")
    serve.add_argument("--grace-s", type=float, default=30.0, help="drain time after SIGTERM")
    serve.set_defaults(handler=_serve)

    health = commands.add_parser(
        "health", help="ask a server's gRPC health service: exit 0 if SERVING, else 1"
    )
    health.add_argument("--target", default="127.0.0.1:50051", help="server host:port")
    health.add_argument("--service", default="", help="service name ('': the whole server)")
    health.add_argument("--timeout-s", type=float, default=5.0, help="deadline of each check")
    health.add_argument(
        "--wait-s",
        type=float,
        default=0.0,
        help="keep asking until SERVING or this many seconds have passed",
    )
    health.add_argument("--ca-cert", help="PEM certificate to verify a TLS server")
    health.add_argument("--server-name", help="the name the TLS certificate holds")
    health.set_defaults(handler=_health)

    retrain = commands.add_parser(
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
    retrain.add_argument("--store", required=True, help="label store directory (every shard)")
    retrain.add_argument(
        "--data", required=True, help="the original data set: labeled frames, pool and gate split"
    )
    retrain.add_argument("--repository", required=True, help="model repository")
    retrain.add_argument(
        "--config",
        help="TOML config file or packaged config name (default: the served version's config, "
        "kept in its manifest); it must describe the same detectors",
    )
    retrain.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a config key, e.g. retrain.steps=500, retrain.max_map_drop=0.5, "
        "retrain.stored_labels=labeled, data.val_split=gate (repeatable)",
    )
    retrain.add_argument(
        "--work",
        help="working directory: the round in progress and past rounds' reports (default: "
        "REPOSITORY/.retrain)",
    )
    retrain.add_argument(
        "--every",
        metavar="PERIOD",
        help="run in the foreground, a round every PERIOD (90s, 15m, 24h, 7d)",
    )
    retrain.add_argument("--times", type=int, help="with --every: stop after N periods")
    retrain.add_argument(
        "--force", action="store_true", help="train even if the store holds nothing new"
    )
    retrain.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where to train: auto (a CUDA GPU when there is one), cpu or cuda",
    )
    retrain.set_defaults(handler=_retrain)

    from retrain.demo import DEFAULT_OUT, DEFAULT_SIZE, SIZES, describe_sizes

    demo = commands.add_parser(
        "demo",
        help="the whole product in one command: synthetic data, pre-training, DetMatch, "
        "export, the service, labeling through gRPC, a retraining round, a report",
        description="Generate a synthetic data set, pre-train both detectors, run DetMatch, "
        "compare them on val, export, start `detmatch serve`, label unseen frames through gRPC "
        "into the label store, run one retraining round from the stored labels (promoted if "
        "it passes) and write a report directory; its path is printed at the end. Sizes: "
        + describe_sizes(),
    )
    demo.add_argument("--size", choices=tuple(SIZES), default=DEFAULT_SIZE,
                      help="how big a run (see above)")  # fmt: skip
    demo.add_argument("--out", default=DEFAULT_OUT, help="output directory (new or empty)")
    demo.add_argument("--seed", type=int, default=0, help="seed of the synthetic data")
    demo.add_argument("--workers", type=int, default=2, help="processes rendering frames")
    demo.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where to train: auto (a CUDA GPU when there is one), cpu or cuda",
    )
    demo.set_defaults(handler=_demo)

    store = commands.add_parser("store", help="the label store of `detmatch serve`")
    store_commands = store.add_subparsers(dest="store_command", required=True, metavar="ACTION")
    store_export = store_commands.add_parser(
        "export",
        help="a KITTI-layout data set of the stored frames and their labels, with train and "
        "val ImageSets (`detmatch train --data OUT` runs on it)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    store_export.add_argument("--store", required=True, help="label store directory")
    store_export.add_argument("--out", required=True, help="output directory (KITTI layout)")
    store_export.add_argument(
        "--val-fraction",
        type=float,
        default=0.1,
        help="share of frames held out in ImageSets/val.txt, chosen by a hash of each key (a "
        "frame keeps its side as the store grows)",
    )
    store_export.add_argument("--seed", type=int, default=0, help="salt of that hash")
    store_export.add_argument(
        "--namespace",
        action="append",
        help="export only this namespace (repeatable); frame ids stay bare when one namespace "
        "is exported, else NAMESPACE__ID",
    )
    store_export.set_defaults(handler=_store_export)

    evaluate = commands.add_parser("eval", help="KITTI object-benchmark evaluation")
    evaluate.add_argument("--gt-dir", required=True, help="directory of KITTI label files")
    evaluate.add_argument("--pred-dir", required=True, help="directory of KITTI result files")
    frames = evaluate.add_mutually_exclusive_group(required=True)
    frames.add_argument("--ids-file", help="ImageSets file of frame ids")
    frames.add_argument("--all", action="store_true",
                        help="every frame with a label file in --gt-dir")  # fmt: skip
    evaluate.add_argument("--classes", default="Car,Pedestrian,Cyclist", help="classes to score")
    evaluate.add_argument("--json", help="write the results as JSON here")
    evaluate.set_defaults(handler=_eval)
    show_defaults(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.handler(args)
    except (FileNotFoundError, FileExistsError, ValueError) as error:
        print(f"detmatch {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
