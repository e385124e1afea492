"""Human review of the auto-labels: `detmatch review export` and `detmatch review import` (no
torch; CVAT's formats need the review extra, datumaro)."""

from __future__ import annotations

import argparse
from pathlib import Path

from commands.common import (
    add_overwrite_option,
    add_store_options,
    class_names,
    prepare_output,
    store_location,
)
from detmatch.constants import (
    LABEL_STUDIO_LOCAL_FILES,
    REVIEW_CLASSES,
    REVIEW_FORMATS,
    REVIEW_SELECTIONS,
)

# What `detmatch review export` writes into --out (removed first by --overwrite).
REVIEW_OUTPUTS = (
    "ds0", "meta.json", "key_id_map.json", "tracklet_labels.xml", "frame_list.txt",
    "annotations", "point_clouds", "velodyne_points", "image_00", "images", "tasks.json",
    "label_config.xml", "review.json", "cvat_labels.json",
)  # fmt: skip


def review_export(args: argparse.Namespace) -> int:
    from serving.review import export_review, select_frames

    store = store_location(args)
    selected = select_frames(store, args.select, args.budget, args.seed, args.namespace,
                             args.version)  # fmt: skip
    prepare_output(Path(args.out), args.overwrite, REVIEW_OUTPUTS)
    summary = export_review(store, Path(args.out), args.format, selected, args.image_url_prefix)
    print(
        f"exported {summary.frames} frames ({summary.labels} labels) for review as "
        f"{summary.format} to {summary.out}; why each frame: {summary.out}/review.json"
    )
    return 0


def review_import(args: argparse.Namespace) -> int:
    from serving.reviews import import_review

    summary = import_review(store_location(args), Path(args.source), args.format,
                            class_names(args.classes))  # fmt: skip
    print(
        f"imported human labels of {len(summary.created) + len(summary.replaced)} frames from "
        f"{args.source}: {len(summary.created)} created, {len(summary.unchanged)} unchanged, "
        f"{len(summary.replaced)} replaced"
        + (f" ({', '.join(summary.replaced[:10])})" if summary.replaced else "")
    )
    return 0


def review_backend(args: argparse.Namespace) -> int:
    from serving.review_backend import Backend, RetrainQueue, retrain_command, serve

    repository = Path(args.repository)
    if not repository.is_dir():
        raise FileNotFoundError(f"--repository {repository}: no such directory")
    store = store_location(args) if args.store else None
    queue = None
    if args.data is not None:
        if store is None:
            raise ValueError("--data (retraining) goes with --store: a round trains on the "
                             "label store's frames")  # fmt: skip
        if not Path(args.data).is_dir():
            raise FileNotFoundError(f"--data {args.data}: no such directory")
        queue = RetrainQueue(retrain_command(args.store, args.store_root, args.data,
                                             str(repository), args.set),
                             lock_retry_s=args.lock_retry_s)  # fmt: skip
    elif args.train_after is not None:
        raise ValueError("--train-after needs --data and --store (what a round trains on)")
    backend = Backend(repository, store, queue, args.train_after, args.label_studio_url,
                      tuple(class_names(args.classes)))  # fmt: skip
    try:
        serve(backend, args.host, args.port)
    except KeyboardInterrupt:
        return 130
    return 0


def _add_classes_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--classes", default=",".join(REVIEW_CLASSES),
                        help="the class names a reviewer may use")  # fmt: skip


def add_parsers(commands: argparse._SubParsersAction) -> None:
    review = commands.add_parser("review", help="the auto-labels in front of human reviewers")
    actions = review.add_subparsers(dest="review_command", required=True, metavar="ACTION")
    parser = actions.add_parser(
        "export",
        help="stored frames and their labels for review: CVAT 3D (Sly Point Cloud with the "
        "camera image and calibration; KITTI Raw) or Label Studio tasks with pre-annotations",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    add_store_options(parser, True, "label store")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--format", required=True, choices=REVIEW_FORMATS,
                        help="cvat-3d: Sly Point Cloud 1.0 (CVAT's 3D import with the camera's "
                        "calibration); kitti-raw: Kitti Raw Format 1.0; datumaro-3d: Datumaro "
                        "3D 1.0 (the camera image, no calibration); label-studio: tasks.json "
                        "and label_config.xml")  # fmt: skip
    parser.add_argument("--select", default="all", choices=REVIEW_SELECTIONS,
                        help="all frames of the filters; a random audit sample; the frames "
                        "whose labels have the lowest 3D scores; or the frames where the camera "
                        "and the LiDAR disagree most (labels the camera did not confirm, class "
                        "disagreements, weak matches; camera-only detections break ties); all "
                        "but the first need --budget")  # fmt: skip
    parser.add_argument("--budget", type=int, help="frames to select")
    parser.add_argument("--seed", type=int, default=0, help="the random sample's seed")
    parser.add_argument("--namespace", help="only this namespace's frames")
    parser.add_argument("--version", help="only frames labeled by this model version")
    parser.add_argument("--image-url-prefix", default=LABEL_STUDIO_LOCAL_FILES,
                        help="label-studio: what the tasks' image URLs start with (Label "
                        "Studio's local files, or your bucket's URL)")  # fmt: skip
    add_overwrite_option(parser)
    parser.set_defaults(handler=review_export)

    parser = actions.add_parser(
        "import",
        help="a reviewed export back into the label store as human labels, beside the "
        "machine labels: all of it or nothing; says created / unchanged / replaced",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    add_store_options(parser, True, "label store")
    parser.add_argument("--from", dest="source", required=True,
                        help="CVAT's export directory (cvat-3d: Sly Point Cloud; kitti-raw; "
                        "datumaro-3d), or "
                        "Label Studio's JSON export file")  # fmt: skip
    parser.add_argument("--format", required=True, choices=REVIEW_FORMATS)
    _add_classes_option(parser)
    parser.set_defaults(handler=review_import)

    parser = actions.add_parser(
        "backend",
        help="a Label Studio ML backend: the served 2D detector pre-annotates tasks, "
        "annotations of exported tasks come back as human labels, training requests queue "
        "retraining rounds (one at a time, under the repository's lock)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--repository", required=True, help="model repository (the served "
                        "version predicts; a newly promoted one is picked up)")  # fmt: skip
    add_store_options(parser, False, "label store where annotations of `detmatch review "
                      "export` tasks are kept as human labels (none: not kept)")  # fmt: skip
    parser.add_argument("--data", help="the original data set, for retraining rounds "
                        "(none: training requests are refused)")  # fmt: skip
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="a config override for the retraining rounds (repeatable)",
    )
    parser.add_argument("--train-after", type=int, metavar="N",
                        help="queue a round after every N new annotations (besides Label "
                        "Studio's START_TRAINING)")  # fmt: skip
    parser.add_argument("--lock-retry-s", type=float, default=30.0,
                        help="when another retraining holds the repository: seconds between "
                        "tries")  # fmt: skip
    parser.add_argument("--label-studio-url", help="where task images on the Label Studio "
                        "server are fetched from, if /setup sent no hostname")  # fmt: skip
    _add_classes_option(parser)
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on")
    parser.add_argument("--port", type=int, default=9090, help="port (0: a free one)")
    parser.set_defaults(handler=review_backend)
