"""Batch labeling on Ray (`detmatch label --engine ray`) against in-process `detmatch label`,
on the same frames, in one run.

    python -m benchmarks.ray_labeling [--frames 200] [--data DIR] [--config configs/synth_cpu.toml]
        [--repository DIR] [--batch-size 8] [--store] [--work DIR] [--json FILE]

The frames: a synthetic set of --frames frames (half resolution, seed 0, made in --work), or
every frame of --data (a KITTI-layout directory). The model: --repository's promoted version,
else --config's two detectors with random weights (benchmarks.service_common.prepare_repository;
throughput does not depend on the weights). Four runs, each into a fresh output directory
(and, with --store, a fresh label store):
  in-process, 1 thread   serving.offline.label_split with onnxruntime on one thread: the
                         baseline of the overhead, as each Ray actor runs one thread;
  in-process             label_split as `detmatch label` runs it (threads: this process's CPUs);
  ray, 1 actor           serving.ray_labeling.label_with_ray with one actor;
  ray, 2 actors          the same with two.
Ray is a local instance started once beforehand and warmed up by an untimed run (its
start-up is not counted); each Ray run's actor start-up and model loading are. Each run labels
every frame and, before, the first 2 x --batch-size frames: the difference gives its seconds
per frame after start-up, and the start-up (model loading; for Ray, also planning and starting
the actors).
Prints each run's seconds, frames/s, start-up and frames/s after start-up; after start-up the
ratios ray 2 actors / ray 1 actor and ray 1 actor / in-process 1 thread, and the overhead per
frame: ray 1 actor's seconds per frame minus in-process 1 thread's. On a 2-core machine 2
actors should approach 2x one actor, less that overhead.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from pathlib import Path

from benchmarks.harness import benchmark_parser, rerun

RUNS = ("in-process, 1 thread", "in-process", "ray, 1 actor", "ray, 2 actors")


def timed_runs(repository: Path, data: Path, work: Path, batch_size: int, store: bool) -> dict:
    """Seconds of each of RUNS over every frame of data ("all") and over its first
    2 x batch_size frames ("start"), and the frames each labeled."""
    from detmatch.data.kitti import KittiDataset, find_subset, write_image_set
    from detmatch.data.selection import FrameSelection

    ids = KittiDataset(data, find_subset(data)).ids()
    first = work / "first_frames.txt"
    write_image_set(first, ids[: 2 * batch_size])
    selections = {"start": FrameSelection(ids_file=first), "all": FrameSelection(all_frames=True)}
    seconds: dict = {name: {} for name in RUNS}
    counts: dict = {name: {} for name in RUNS}
    # Not timed: a session's first Ray Data run also starts its worker processes.
    timed_run("ray, 2 actors", repository, data, selections["start"], work / "run", batch_size,
              store)  # fmt: skip
    for name in RUNS:
        for part, frames in selections.items():
            seconds[name][part], counts[name][part] = timed_run(
                name, repository, data, frames, work / "run", batch_size, store
            )
    return {"seconds": seconds, "frames": counts}


def timed_run(
    name: str,
    repository: Path,
    data: Path,
    frames,
    out: Path,
    batch_size: int,
    store: bool,
) -> tuple[float, int]:
    """One of RUNS into a fresh output directory (and store): seconds, frames labeled."""
    from serving.labeler import Labeler
    from serving.offline import label_split
    from serving.ray_labeling import RayEngine, label_with_ray
    from serving.sessions import SessionSettings
    from serving.store import LabelStore

    shutil.rmtree(out, ignore_errors=True)
    label_store = LabelStore(out / "store", "bench") if store else None
    try:
        start = time.perf_counter()
        if name.startswith("in-process"):
            threads = 1 if name.endswith("1 thread") else 0
            labeler = Labeler.from_repository(repository, settings=SessionSettings(threads))
            summary = label_split(labeler, data, frames, out / "labels", progress=False,
                                  store=label_store)  # fmt: skip
        else:
            engine = RayEngine(actors=1 if name.endswith("1 actor") else 2, batch_size=batch_size)
            summary = label_with_ray(repository, data, frames, out / "labels", progress=False,
                                     store=label_store, engine=engine).summary  # fmt: skip
        return time.perf_counter() - start, summary.frames
    finally:
        if label_store is not None:
            label_store.close()


def run_figures(seconds: dict[str, float], counts: dict[str, int]) -> dict[str, float]:
    """A run's frames/s over all frames, and apart from its start-up: the marginal seconds per
    frame between the "start" and "all" runs, and the start-up that leaves of "start"."""
    per_frame = (seconds["all"] - seconds["start"]) / (counts["all"] - counts["start"])
    return {
        "frames_per_s": counts["all"] / seconds["all"],
        "start_up_s": seconds["start"] - counts["start"] * per_frame,
        "frames_per_s_after_start_up": 1 / per_frame,
    }


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--frames", type=int, default=200, help="synthetic frames to make")
    parser.add_argument("--data", help="label this KITTI-layout directory's frames instead")
    parser.add_argument("--config", default="configs/synth_cpu.toml")
    parser.add_argument("--repository", help="use this model repository's promoted version")
    parser.add_argument("--batch-size", type=int, default=8, help="frames per actor call")
    parser.add_argument("--store", action="store_true", help="also store every frame")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="ray_labeling_"))
    work.mkdir(parents=True, exist_ok=True)
    if args.repository:
        repository = Path(args.repository)
    else:
        from benchmarks.service_common import prepare_repository

        repository = prepare_repository(work, args.config)
    data = Path(args.data) if args.data else work / f"synth_{args.frames}"
    if not args.data and not (data / "synth.json").is_file():
        from detmatch.data.synth import generate_dataset

        generate_dataset(data, args.frames, seed=0, progress=False)

    import ray

    from serving.sessions import available_cpus

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    ray.init(num_cpus=available_cpus(), include_dashboard=False, _node_ip_address="127.0.0.1",
             _temp_dir=str(work / "ray"), log_to_driver=False)  # fmt: skip
    try:
        result = timed_runs(repository, data, work, args.batch_size, args.store)
    finally:
        ray.shutdown()
    seconds, counts = result["seconds"], result["frames"]
    figures = {name: run_figures(seconds[name], counts[name]) for name in RUNS}
    steady = {name: figures[name]["frames_per_s_after_start_up"] for name in RUNS}
    result.update(
        data=str(data),
        repository=str(repository),
        batch_size=args.batch_size,
        store=args.store,
        cpus=available_cpus(),
        figures=figures,
        ratio_2_actors_to_1=steady["ray, 2 actors"] / steady["ray, 1 actor"],
        ratio_1_actor_to_in_process_1_thread=steady["ray, 1 actor"]
        / steady["in-process, 1 thread"],
        overhead_ms_per_frame=1000
        * (1 / steady["ray, 1 actor"] - 1 / steady["in-process, 1 thread"]),
    )
    frames = counts["in-process"]["all"]
    print(f"{frames} frames of {data}; model {repository}; batch size {args.batch_size}; "
          f"store {'on' if args.store else 'off'}; {available_cpus()} CPUs")  # fmt: skip
    print("\n| run | frames | seconds | frames/s | start-up s | frames/s after start-up |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for name in RUNS:
        f = figures[name]
        print(f"| {name} | {counts[name]['all']} | {seconds[name]['all']:.2f} | "
              f"{f['frames_per_s']:.1f} | {f['start_up_s']:.2f} | "
              f"{f['frames_per_s_after_start_up']:.1f} |")  # fmt: skip
    print("\nafter start-up:")
    print(f"  ray 2 actors / ray 1 actor: {result['ratio_2_actors_to_1']:.2f}x")
    print(f"  ray 1 actor / in-process 1 thread: "
          f"{result['ratio_1_actor_to_in_process_1_thread']:.2f}x")  # fmt: skip
    print(f"  overhead per frame (ray 1 actor - in-process 1 thread): "
          f"{result['overhead_ms_per_frame']:.1f} ms")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nrerun: {rerun('ray_labeling')}")


if __name__ == "__main__":
    main()
