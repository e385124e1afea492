"""onnxruntime against PyTorch eager, and the labeler's overhead, on CPU at full KITTI resolution.

    python -m benchmarks.onnx_latency [--configs configs/tiny.toml configs/synth_cpu.toml]
                                      [--threads 1 2] [--repeats 20]

Per config, both detectors with random weights (torch.manual_seed(0); latency does not depend on
the weights) are saved as a checkpoint and exported by `export_checkpoint`, parity check
included. The frame is synthetic frame 0 at full resolution: a 1242x375 image and a 64-beam
sweep. Each engine runs in a process of its own, so its memory (VmHWM, the peak resident
set; also after loading the models) is its own:
- torch: each exported graph's module in eager mode (2D: the uint8 image -> resize ->
  CenterNet2D -> decode -> boxes in image pixels; 3D: pillars -> PointPillars3D -> decode);
- onnxruntime, in a process where `import torch` fails: the same graphs with the labeler's
  session options, then `Labeler.label` on the frame (input checks, both graphs, pillarize,
  thresholds, projection and matching). Its overhead ratio is the median labeler time over
  the median of the two graphs' own time inside the same calls (target: at most 1.25), and
  over the two graphs' standalone medians.
Median and 90th percentile over --repeats runs after 3 warm-up runs; the same thread count
for both engines.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

from benchmarks.harness import benchmark_parser, rerun

WARM_UP = 3
# onnxruntime settings compared with the labeler's (graph optimisation "all", no spinning).
SESSION_VARIANTS = (("all", False), ("extended", False), ("basic", False), ("all", True))


def _peak_rss_mib() -> float:
    """This process's peak resident set (VmHWM). Not ru_maxrss: Linux carries that across
    exec, so a worker would report its parent's peak."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed(function, repeats: int) -> list[float]:
    for _ in range(WARM_UP):
        function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return times


def _stats(times: list[float]) -> dict[str, float]:
    return {
        "median_ms": 1000 * float(np.median(times)),
        "p90_ms": 1000 * float(np.percentile(times, 90)),
    }


def _load_frame(path: str):
    from detmatch.structures import Calibration

    data = np.load(path)
    calib = Calibration(data["P2"], data["R0_rect"], data["Tr_velo_to_cam"])
    return data["image"], data["points"], calib


# --- workers (separate processes) --------------------------------------------------------------


def torch_worker(args: argparse.Namespace) -> dict:
    import torch

    from detmatch.models.build import load_detectors
    from detmatch.models.pillars import pillarize
    from export.graphs import ImageDetector2DGraph, PillarDetector3DGraph

    torch.set_num_threads(args.threads)
    image, points, _ = _load_frame(args.frame)
    loaded = load_detectors(Path(args.checkpoint))
    config, model_2d, model_3d = loaded.config, loaded.model_2d, loaded.model_3d
    baseline = _peak_rss_mib()
    graph_2d = ImageDetector2DGraph(model_2d, config.data.image_size).eval()
    graph_3d = PillarDetector3DGraph(model_3d).eval()
    image_tensor = torch.from_numpy(image.copy())
    pillars = tuple(torch.from_numpy(a) for a in pillarize(points, model_3d.grid).arrays)
    with torch.inference_mode():
        detector_2d = _timed(lambda: graph_2d(image_tensor), args.repeats)
        detector_3d = _timed(lambda: graph_3d(*pillars), args.repeats)
    return {
        "detector2d": _stats(detector_2d),
        "detector3d": _stats(detector_3d),
        "pillars": len(pillars[0]),
        "rss_after_load_mib": baseline,
        "peak_rss_mib": _peak_rss_mib(),
    }


def ort_worker(args: argparse.Namespace) -> dict:
    sys.modules["torch"] = None  # the labeler's side must not need it
    from serving.labeler import Labeler
    from serving.repository import DECODED_OUTPUTS, INPUTS_3D, MODEL_2D_FILE, MODEL_3D_FILE
    from serving.sessions import SessionSettings, make_session

    image, points, calib = _load_frame(args.frame)
    labeler = Labeler(Path(args.version_dir), SessionSettings(intra_op_threads=args.threads))
    baseline = _peak_rss_mib()
    from detmatch.models.pillars import pillarize

    feed_3d = dict(zip(INPUTS_3D, pillarize(points, labeler.grid).arrays, strict=True))
    outputs = list(DECODED_OUTPUTS)
    feed_2d = {"image": image}
    detector_2d = _timed(partial(labeler.session_2d.run, outputs, feed_2d), args.repeats)
    detector_3d = _timed(partial(labeler.session_3d.run, outputs, feed_3d), args.repeats)
    recorded: list[dict[str, float]] = []

    def label() -> None:
        recorded.append(labeler.label(image, points, calib).timings)

    total = _timed(label, args.repeats)
    calls = recorded[WARM_UP:]
    peak = _peak_rss_mib()  # before the sessions of the variants below
    variants = {}
    for optimization, spinning in SESSION_VARIANTS:
        settings = SessionSettings(args.threads, optimization, spinning)
        session_2d = make_session(labeler.path / MODEL_2D_FILE, settings)
        session_3d = make_session(labeler.path / MODEL_3D_FILE, settings)
        name = f"{optimization}, spinning {'on' if spinning else 'off'}"
        variants[name] = {
            "detector2d": _stats(_timed(partial(session_2d.run, outputs, feed_2d), args.repeats)),
            "detector3d": _stats(_timed(partial(session_3d.run, outputs, feed_3d), args.repeats)),
        }
    models = [c["detector2d"] + c["detector3d"] for c in calls]
    standalone = np.median(detector_2d) + np.median(detector_3d)
    return {
        "detector2d": _stats(detector_2d),
        "detector3d": _stats(detector_3d),
        "labeler_total": _stats(total),
        "labeler_models": _stats(models),
        "labeler_pillarize": _stats([c["pillarize"] for c in calls]),
        "labeler_matching": _stats([c["matching"] for c in calls]),
        "labeler_ratio": float(np.median(total) / np.median(models)),
        "labeler_ratio_standalone": float(np.median(total) / standalone),
        "session_variants": variants,
        "labels": len(labeler.label(image, points, calib)),
        "rss_after_load_mib": baseline,
        "peak_rss_mib": peak,
    }


# --- the driver -----------------------------------------------------------------------------------


def prepare(config_path: Path, work: Path, frame_path: Path) -> tuple[Path, Path]:
    """Random-weight checkpoint of a config, exported; returns (checkpoint, version dir)."""
    import torch

    from detmatch.config import config_to_dict, load_config
    from detmatch.models.build import build_detectors
    from export.onnx_export import export_checkpoint

    config = load_config(config_path)
    torch.manual_seed(0)
    model_2d, model_3d = build_detectors(config)
    checkpoint = work / f"{config_path.stem}.pt"
    torch.save(
        {
            "format": 1,
            "step": 0,
            "config": config_to_dict(config),
            "model_2d": model_2d.state_dict(),
            "model_3d": model_3d.state_dict(),
            "metrics": {},
        },
        checkpoint,
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the parity reference; see BENCHMARKS.md on contended pools
    try:
        result = export_checkpoint(checkpoint, work / f"repository_{config_path.stem}",
                                   synthetic_frames=1)  # fmt: skip
    finally:
        torch.set_num_threads(threads)
    return checkpoint, result.path


def run_worker(kind: str, **options: object) -> dict:
    command = [sys.executable, __file__, "--worker", kind]
    for key, value in options.items():
        command += [f"--{key.replace('_', '-')}", str(value)]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{kind} worker failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument(
        "--configs", nargs="+", default=["configs/tiny.toml", "configs/synth_cpu.toml"]
    )
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--json", help="write all figures here")
    parser.add_argument("--worker", choices=("torch", "ort"), help=argparse.SUPPRESS)
    parser.add_argument("--checkpoint", help=argparse.SUPPRESS)
    parser.add_argument("--version-dir", help=argparse.SUPPRESS)
    parser.add_argument("--frame", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        args.threads = args.threads[0]
        result = torch_worker(args) if args.worker == "torch" else ort_worker(args)
        print(json.dumps(result))
        return

    from detmatch.data.synth.dataset import generate_frame

    work = Path(tempfile.mkdtemp(prefix="onnx_latency_"))
    frame = generate_frame(0, 0, "full").frame
    frame_path = work / "frame.npz"
    np.savez(frame_path, image=frame.image, points=frame.points, P2=frame.calib.P2,
             R0_rect=frame.calib.R0_rect, Tr_velo_to_cam=frame.calib.Tr_velo_to_cam)  # fmt: skip
    print(f"frame: synthetic seed 0 frame 0, image {frame.image_size[0]}x{frame.image_size[1]}, "
          f"{len(frame.points)} points; {args.repeats} runs after {WARM_UP} warm-up")  # fmt: skip
    rows = []
    for config_path in map(Path, args.configs):
        checkpoint, version_dir = prepare(config_path, work, frame_path)
        for threads in args.threads:
            common = {"frame": frame_path, "threads": threads, "repeats": args.repeats}
            torch_result = run_worker("torch", checkpoint=checkpoint, **common)
            ort_result = run_worker("ort", version_dir=version_dir, **common)
            rows.append({"config": config_path.stem, "threads": threads,
                         "torch": torch_result, "ort": ort_result})  # fmt: skip

    print("\n| config | threads | model | PyTorch eager ms | onnxruntime ms | ORT / PyTorch |")
    print("| --- | ---: | --- | ---: | ---: | ---: |")
    for row in rows:
        for model in ("detector2d", "detector3d"):
            eager = row["torch"][model]["median_ms"]
            ort = row["ort"][model]["median_ms"]
            print(f"| {row['config']} | {row['threads']} | {model} | {eager:.1f} | {ort:.1f} | "
                  f"{ort / eager:.2f} |")  # fmt: skip
    header = (
        "config",
        "threads",
        "labeler ms (p90)",
        "models ms",
        "pillarize ms",
        "matching ms",
        "labeler / models (same calls)",
        "labeler / standalone models",
        "RSS MiB after load / peak: PyTorch, labeler",
    )
    print("\n| " + " | ".join(header) + " |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for row in rows:
        ort = row["ort"]
        total, models = ort["labeler_total"], ort["labeler_models"]
        print(f"| {row['config']} | {row['threads']} | {total['median_ms']:.1f} "
              f"({total['p90_ms']:.1f}) | {models['median_ms']:.1f} | "
              f"{ort['labeler_pillarize']['median_ms']:.1f} | "
              f"{ort['labeler_matching']['median_ms']:.1f} | {ort['labeler_ratio']:.2f} | "
              f"{ort['labeler_ratio_standalone']:.2f} | "
              f"{row['torch']['rss_after_load_mib']:.0f} / {row['torch']['peak_rss_mib']:.0f}, "
              f"{ort['rss_after_load_mib']:.0f} / {ort['peak_rss_mib']:.0f} |")  # fmt: skip
    print("\n| config | threads | session options | detector2d ms | detector3d ms |")
    print("| --- | ---: | --- | ---: | ---: |")
    for row in rows:
        for name, figures in row["ort"]["session_variants"].items():
            print(f"| {row['config']} | {row['threads']} | {name} | "
                  f"{figures['detector2d']['median_ms']:.1f} | "
                  f"{figures['detector3d']['median_ms']:.1f} |")  # fmt: skip
    for row in rows[:: max(len(args.threads), 1)]:
        print(f"{row['config']}: {row['torch']['pillars']} pillars")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    print(f"\nrerun: {rerun('onnx_latency')}")


if __name__ == "__main__":
    main()
