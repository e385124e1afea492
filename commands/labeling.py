"""Labeling with an exported model version, no torch: `detmatch label` (offline), `serve` (the
gRPC service) and `health` (its health check)."""

from __future__ import annotations

import argparse
import os
import socket
import sys
from pathlib import Path

from commands.common import (
    add_frame_selection,
    add_overwrite_option,
    add_store_options,
    frame_selection,
    prepare_output,
    store_location,
)

# What `detmatch label --out` writes (removed first by --overwrite).
LABEL_OUTPUTS = ("3d", "2d", "labels", "labeling.json")

# `detmatch serve --host` when not given: the Docker image sets 0.0.0.0 (all interfaces).
HOST_ENV = "DETMATCH_HOST"


def label(args: argparse.Namespace) -> int:
    from serving.errors import StoreError
    from serving.labeler import Labeler
    from serving.offline import label_split
    from serving.ray_labeling import label_with_ray
    from serving.store import LabelStore, validate_namespace

    if not args.out and not args.store:
        raise ValueError("give --out DIR (result files), --store DIR (the label store) or both")
    validate_namespace(args.namespace)
    engine = _ray_engine(args)
    if args.out and (engine is None or args.overwrite):  # the Ray engine resumes into --out
        prepare_output(Path(args.out), args.overwrite, LABEL_OUTPUTS)
    frames = frame_selection(args)
    labeler = None if engine else Labeler.from_repository(Path(args.repository), args.version)
    try:
        store = LabelStore(store_location(args), args.shard) if args.store else None
    except StoreError as error:  # the shard is held by a server or another `label`
        raise ValueError(f"--shard {args.shard}: {error}") from None
    try:
        if engine is None:
            summary = label_split(
                labeler, Path(args.data), frames, Path(args.out) if args.out else None,
                args.tau_hung, store=store, namespace=args.namespace,
            )  # fmt: skip
        else:
            labeling = label_with_ray(
                Path(args.repository), args.data, frames, Path(args.out) if args.out else None,
                args.version, args.tau_hung, store=store, namespace=args.namespace,
                engine=engine,
            )  # fmt: skip
            summary = labeling.summary
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
    return 0 if engine is None else _report_ray_labeling(labeling, args.out)


def _ray_engine(args: argparse.Namespace):
    """`--engine ray`'s settings (serving.ray_labeling.RayEngine); None for the in-process
    engine, which takes none of them."""
    given = {"address": args.address, "actors": args.actors, "batch_size": args.batch_size}
    given = {name: value for name, value in given.items() if value is not None}
    if args.engine != "ray":
        if given:
            raise ValueError(f"--{next(iter(given)).replace('_', '-')} goes with --engine ray")
        return None
    from serving.ray_labeling import RayEngine

    return RayEngine(**given)


def _report_ray_labeling(labeling, out: str | None) -> int:
    """The Ray engine's resumed and failed frames; exit status 1 when frames failed."""
    if labeling.resumed:
        print(f"skipped {labeling.resumed} frames labeled by this model version already")
    if not labeling.failed:
        return 0
    listed = f" (listed in {out}/labeling.json)" if out else ""
    print(
        f"{len(labeling.failed)} frames could not be read or labeled and were skipped{listed}:",
        file=sys.stderr,
    )
    for failure in labeling.failed:
        print(f"  {failure.frame_id}: {failure.reason}", file=sys.stderr)
    return 1


def _bearer_token(args: argparse.Namespace) -> str | None:
    """The token clients must send, from $--token-env; None with --no-auth. Authentication is
    never silently off: an unset or empty variable without --no-auth is an error."""
    token = os.environ.get(args.token_env, "")
    if args.no_auth and token:
        raise ValueError(
            f"--no-auth, but ${args.token_env} holds a token: unset it, or drop --no-auth"
        )
    if args.no_auth:
        return None
    if not token.strip():
        state = "is empty" if args.token_env in os.environ else "is not set"
        raise ValueError(
            f"${args.token_env} (--token-env) {state}, and authentication is never silently "
            f"off: put the bearer token clients must send in ${args.token_env}, or pass "
            "--no-auth to run without authentication"
        )
    if not token.isascii() or not token.isprintable() or token != token.strip():
        raise ValueError(f"${args.token_env}: a token is printable ASCII without spaces")
    return token


def serve(args: argparse.Namespace) -> int:
    from serving.config import ServerConfig
    from serving.errors import StoreError
    from serving.logs import configure_logging
    from serving.server import format_address
    from serving.server import serve as run_server

    token = _bearer_token(args)
    _check_serve_paths(args)
    configure_logging()
    config = ServerConfig(
        address=format_address(args.host, args.port),
        workers=args.workers,
        max_batch_size=args.max_batch_size,
        max_queue_delay_us=args.max_queue_delay_us,
        threads=args.threads,
        max_message_bytes=args.max_message_mb * 1024 * 1024,
        max_image_pixels=args.max_image_pixels,
        max_points=args.max_points,
        max_concurrent_rpcs=args.max_concurrent_rpcs,
        max_inflight_bytes=args.max_inflight_mb * 1024 * 1024,
        budget_wait_s=args.budget_wait_s,
        max_uploads_per_peer=args.max_uploads_per_peer,
        receive_timeout_s=args.receive_timeout_s,
        tls_cert=Path(args.tls_cert) if args.tls_cert else None,
        tls_key=Path(args.tls_key) if args.tls_key else None,
        token=token,
        metrics_port=args.metrics_port,
        metrics_address=args.metrics_host or args.host,
        poll_s=args.poll_s,
        grace_s=args.grace_s,
    )
    try:
        run_server(Path(args.repository), store_location(args), config, shard=args.shard)
    except (OSError, StoreError) as error:  # a port in use, a shard held by another server
        raise ValueError(str(error)) from None
    return 0


def _check_serve_paths(args: argparse.Namespace) -> None:
    """Before anything is created: the repository exists (an empty one is fine: the server
    answers NOT_SERVING until a version is promoted there) and the TLS files can be read."""
    if not Path(args.repository).is_dir():
        raise FileNotFoundError(
            f"--repository {args.repository}: no such directory (detmatch-export --repository "
            "DIR creates a model repository)"
        )
    for flag, path in (("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key)):
        if path and not Path(path).is_file():
            raise FileNotFoundError(f"{flag} {path}: no such file")


def health(args: argparse.Namespace) -> int:
    from serving.health_check import wait_until_serving

    _check_target(args.target)
    status = wait_until_serving(
        args.target,
        args.wait_s,
        service=args.service,
        timeout_s=args.timeout_s,
        root_certificates=Path(args.ca_cert).read_bytes() if args.ca_cert else None,
        server_name=args.server_name,
    )
    print(status)
    if status == "UNREACHABLE":
        print(
            f"no gRPC server answered at {args.target} within {args.wait_s:g} s (is it "
            "running, on that port; with TLS, pass --ca-cert)",
            file=sys.stderr,
        )
    return 0 if status == "SERVING" else 1


def _check_target(target: str) -> None:
    """--target is HOST:PORT ([v6 address]:PORT too), the port 1-65535."""
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--target {target!r}: expected HOST:PORT, e.g. 127.0.0.1:50051")


def add_parsers(commands: argparse._SubParsersAction) -> None:
    _add_label_parser(commands)
    _add_serve_parser(commands)
    _add_health_parser(commands)


def _add_label_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "label", help="label a data set with an exported model version (onnxruntime, no torch)"
    )
    parser.add_argument("--repository", required=True, help="model repository (detmatch-export)")
    parser.add_argument("--version", help="model version (default: the newest promoted one)")
    parser.add_argument("--data", required=True, help="KITTI-layout data set root")
    add_frame_selection(parser)
    parser.add_argument("--out", help="output directory (gets 3d/, 2d/, labels/)")
    add_store_options(
        parser,
        False,
        "store every frame and its labels as the service does (what `detmatch "
        "retrain` reads), with or without --out, into this label store",
    )
    parser.add_argument("--shard", default="offline", help="the label store shard written")
    parser.add_argument("--namespace", default="default",
                        help="the data set's namespace in the label store (keys are namespace + "
                        "frame id, so two data sets' 000000 do not collide)")  # fmt: skip
    parser.add_argument("--tau-hung", type=float, help="matching threshold (default: manifest's)")
    parser.add_argument("--engine", choices=("inprocess", "ray"), default="inprocess",
                        help="inprocess: this process labels the frames; ray: a pool of Ray "
                        "actors on this machine or a cluster (the ray extra, docs/scale.md), "
                        "--data may be a URL (s3://, file://), frames already labeled by the "
                        "version are skipped")  # fmt: skip
    parser.add_argument("--address",
                        help="--engine ray: the cluster to join (auto: this node's; "
                        "HOST:PORT: its head's GCS; default: $RAY_ADDRESS, else a local Ray "
                        "instance)")  # fmt: skip
    parser.add_argument("--actors", type=int,
                        help="--engine ray: labeling actors, each loading the model once "
                        "(default: 2)")  # fmt: skip
    parser.add_argument(
        "--batch-size", type=int, help="--engine ray: frames an actor labels per call (default: 8)"
    )
    add_overwrite_option(parser)
    parser.set_defaults(handler=label)


def _add_serve_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "serve",
        help="run the gRPC auto-labeling service (no torch)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--repository", required=True, help="model repository (detmatch-export)")
    add_store_options(parser, True, "label store")
    parser.add_argument("--port", type=int, default=50051, help="0 picks a free port")
    parser.add_argument("--host", default=os.environ.get(HOST_ENV) or "127.0.0.1",
                        help=f"address to bind: 0.0.0.0 (or ::) listens on every interface, as a "
                        f"container must (default: ${HOST_ENV}, else 127.0.0.1)")  # fmt: skip
    parser.add_argument("--workers", type=int, default=4,
                        help="inference threads: frames decoded and labeled at once")  # fmt: skip
    parser.add_argument("--threads", type=int, default=0,
                        help="onnxruntime threads per model run; 0: the CPUs this process may "
                        "use (its CPU set and its cgroup's CPU quota)")  # fmt: skip
    parser.add_argument("--max-batch-size", type=int, default=1,
                        help="dynamic batching: frames of concurrent calls labeled in one call "
                        "of each graph, at most --workers; 1: off (on a 2-core CPU a batch "
                        "makes no frame cheaper: docs/service.md)")  # fmt: skip
    parser.add_argument("--max-queue-delay-us", type=int, default=2000,
                        help="dynamic batching: how long a frame waits for others to join its "
                        "batch, microseconds")  # fmt: skip
    parser.add_argument("--shard", default=socket.gethostname().split(".")[0] or "default",
                        help="this replica's label store shard (default: host name)")  # fmt: skip
    parser.add_argument("--max-message-mb", type=int, default=48,
                        help="largest request, MiB (refused as its first bytes arrive; the "
                        "default holds --max-points points and a 4K image)")  # fmt: skip
    parser.add_argument("--max-image-pixels", type=int, default=3840 * 2160,
                        help="largest image (width x height), checked before decoding")  # fmt: skip
    parser.add_argument("--max-points", type=int, default=2_000_000,
                        help="LiDAR points per frame; INVALID_ARGUMENT beyond")  # fmt: skip
    parser.add_argument("--max-concurrent-rpcs", type=int, default=64,
                        help="LabelFrame calls at once, counted once their message has arrived; "
                        "RESOURCE_EXHAUSTED beyond (GetModelInfo, health and reflection "
                        "always answer)")  # fmt: skip
    parser.add_argument("--max-inflight-mb", type=int, default=512,
                        help="memory budget of the frames being labeled (3x their messages); a "
                        "call that does not fit waits --budget-wait-s, then gets "
                        "RESOURCE_EXHAUSTED")  # fmt: skip
    parser.add_argument("--budget-wait-s", type=float, default=5.0,
                        help="how long a call may wait for room in the budget")  # fmt: skip
    parser.add_argument("--max-uploads-per-peer", type=int, default=16,
                        help="LabelFrame requests one connection may have uploading")  # fmt: skip
    parser.add_argument("--receive-timeout-s", type=float, default=30.0,
                        help="a request message must arrive within this; slower clients get "
                        "DEADLINE_EXCEEDED")  # fmt: skip
    parser.add_argument("--tls-cert", help="PEM server certificate (with --tls-key)")
    parser.add_argument("--tls-key", help="PEM server private key")
    parser.add_argument("--token-env", default="DETMATCH_TOKEN",
                        help="variable holding the bearer token clients must send; the server "
                        "refuses to start when it is unset or empty, unless --no-auth")  # fmt: skip
    parser.add_argument("--no-auth", action="store_true",
                        help="run without authentication (any client reaching the port may "
                        "label and store)")  # fmt: skip
    parser.add_argument("--metrics-port", type=int, help="Prometheus /metrics port (off if unset)")
    parser.add_argument("--metrics-host",
                        help="address the metrics endpoint binds (default: --host's; 0.0.0.0: "
                        "scrapable from other hosts)")  # fmt: skip
    parser.add_argument("--poll-s", type=float, default=2.0, help="model repository poll period")
    parser.add_argument("--grace-s", type=float, default=30.0, help="drain time after SIGTERM")
    parser.set_defaults(handler=serve)


def _add_health_parser(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "health", help="ask a server's gRPC health service: exit 0 if SERVING, else 1"
    )
    parser.add_argument("--target", default="127.0.0.1:50051", help="server host:port")
    parser.add_argument("--service", default="", help="service name ('': the whole server)")
    parser.add_argument("--timeout-s", type=float, default=5.0, help="deadline of each check")
    parser.add_argument(
        "--wait-s",
        type=float,
        default=0.0,
        help="keep asking until SERVING or this many seconds have passed",
    )
    parser.add_argument("--ca-cert", help="PEM certificate to verify a TLS server")
    parser.add_argument("--server-name", help="the name the TLS certificate holds")
    parser.set_defaults(handler=health)
