"""A fuzzer for LabelFrame: malformed requests derived from valid ones, and raw bytes at the
method, against `detmatch serve` with its label store on.

    python -m benchmarks.service_fuzz [--cases 1200] [--seed 0] [--config configs/tiny.toml]

Cases (see `fuzz_cases`): bytes that are no request (random, truncated and bit-flipped
serialisations, lying length prefixes); point buffers of odd and truncated lengths, NaN and
Inf, absurd counts and coordinates; images truncated, corrupted, of the wrong format, 16-bit,
palette, grey, alpha, 1 x 1, one pixel high and very wide, and decompression bombs (PNG and
JPEG headers of 8192 x 8192 and more); degenerate calibrations (zero, rank-deficient, 1e308,
NaN, tiny, wrong lengths); hostile frame ids and namespaces (16 KB, traversal, NUL, Unicode);
out-of-range options. Each case is one call. Figures: the count of each status code (target:
0 INTERNAL, 0 UNKNOWN), whether the server is alive and SERVING afterwards and still labels a
valid frame, whether the store changed other than by the calls that succeeded (target: no),
error lines in its log (target: 0), and its RSS (peak and at the end, target: bounded).
`tests/grpc_service/test_fuzz.py` runs a slice of the same cases against an in-process server.
"""

from __future__ import annotations

import io
import json
import random
import tempfile
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
from PIL import Image

from benchmarks.harness import benchmark_parser, rerun
from benchmarks.service_common import RssSampler, prepare_repository, serve

LABEL_FRAME = "/detmatch.v1.AutoLabeler/LabelFrame"


@dataclass(frozen=True)
class Case:
    """One call: a request message, or raw bytes sent as the request."""

    kind: str
    request: object | None = None
    raw: bytes | None = None


def _image(mode: str, size: tuple[int, int], kind: str = "PNG", **save) -> bytes:
    buffer = io.BytesIO()
    Image.new(mode, size).save(buffer, format=kind, **save)
    return buffer.getvalue()


def _jpeg_with_size(jpeg: bytes, width: int, height: int) -> bytes:
    """A JPEG whose start-of-frame header claims width x height (the data stays small)."""
    data = bytearray(jpeg)
    for marker in (b"\xff\xc0", b"\xff\xc2"):
        at = data.find(marker)
        if at >= 0:
            data[at + 5 : at + 7] = height.to_bytes(2, "big")
            data[at + 7 : at + 9] = width.to_bytes(2, "big")
    return bytes(data)


def _images(valid_png: bytes, valid_jpeg: bytes) -> list[tuple[str, bytes]]:
    return [
        ("image: truncated PNG", valid_png[: len(valid_png) // 2]),
        ("image: PNG header only", valid_png[:40]),
        ("image: truncated JPEG", valid_jpeg[: len(valid_jpeg) // 3]),
        ("image: PNG magic then junk", valid_png[:8] + b"\x00" * 200),
        ("image: JPEG magic then junk", b"\xff\xd8\xff" + bytes(range(256)) * 4),
        ("image: GIF", b"GIF89a" + b"\x00" * 100),
        ("image: BMP", b"BM" + b"\x00" * 100),
        ("image: empty", b""),
        ("image: 16-bit grey PNG", _image("I;16", (64, 32))),
        ("image: palette PNG", _image("P", (64, 32))),
        ("image: grey PNG", _image("L", (64, 32))),
        ("image: RGBA PNG", _image("RGBA", (64, 32))),
        ("image: 1-bit PNG", _image("1", (64, 32))),
        ("image: 1 x 1 PNG", _image("RGB", (1, 1))),
        ("image: 1 x 4000 PNG", _image("RGB", (4000, 1))),
        ("image: CMYK JPEG", _image("CMYK", (64, 32), "JPEG")),
        ("image: progressive JPEG", _image("RGB", (64, 32), "JPEG", progressive=True)),
        ("image: PNG bomb 8192 x 8192", _image("L", (8192, 8192))),
        ("image: PNG bomb 20000 x 20000", _image("1", (20000, 20000))),
        ("image: JPEG claiming 65535 x 65535", _jpeg_with_size(valid_jpeg, 65535, 65535)),
        ("image: JPEG claiming 8192 x 8192", _jpeg_with_size(valid_jpeg, 8192, 8192)),
    ]


def _calibrations() -> list[tuple[str, dict]]:
    eye = np.eye(4)[:3].ravel().tolist()
    p2 = [721.5, 0.0, 609.6, 44.9, 0.0, 721.5, 172.9, 0.2, 0.0, 0.0, 1.0, 0.003]
    return [
        ("calibration: zero P2", {"p2": [0.0] * 12}),
        ("calibration: zero R0", {"r0_rect": [0.0] * 9}),
        ("calibration: zero Tr", {"tr_velo_to_cam": [0.0] * 12}),
        ("calibration: rank-2 P2", {"p2": p2[:8] + p2[:4]}),
        ("calibration: 1e308", {"p2": [1e308] * 12}),
        ("calibration: -1e308", {"tr_velo_to_cam": [-1e308] * 12}),
        ("calibration: tiny P2", {"p2": [1e-300] * 12}),
        ("calibration: NaN", {"r0_rect": [float("nan")] * 9}),
        ("calibration: Inf", {"p2": [float("inf")] + p2[1:]}),
        ("calibration: short P2", {"p2": p2[:11]}),
        ("calibration: long Tr", {"tr_velo_to_cam": eye + [1.0]}),
        ("calibration: empty", {"p2": [], "r0_rect": [], "tr_velo_to_cam": []}),
        ("calibration: scaled R0", {"r0_rect": (np.eye(3) * 7).ravel().tolist()}),
        ("calibration: reflecting Tr", {"tr_velo_to_cam": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0]}),
    ]


def _ids() -> list[tuple[str, str, str]]:
    """(kind, field, value)."""
    values = ["", "../../etc/passwd", "a/b", "x" * 16384, "x" * 65, "a\0b", "frame id",
              "caf\u00e9", "\u202e", "..", ".", "-" * 64, "\ud7ff" * 10]  # fmt: skip
    return [(f"{field}: {value[:12]!r}", field, value) for field in ("frame_id", "namespace")
            for value in values if not (field == "namespace" and value == "")]  # fmt: skip


def _options() -> list[tuple[str, str, float]]:
    return [(f"options: {name} = {value}", name, value)
            for name in ("score_threshold_2d", "score_threshold_3d", "tau_hung")
            for value in (float("nan"), float("inf"), -1.0, 1.5, 1e308)]  # fmt: skip


def fuzz_cases(valid: list, count: int, seed: int = 0, large: bool = True) -> list[Case]:
    """count cases derived from the valid requests (deterministic for a seed). The fixed
    cases of every kind come first, random variations fill the rest; large=False leaves out
    the cases of tens of MB (absurd point counts)."""
    from serving.client import pb2

    rng = random.Random(seed)
    cases: list[Case] = []

    def derived(kind: str, change) -> Case:
        request = pb2.LabelFrameRequest()
        request.CopyFrom(rng.choice(valid))
        request.frame_id = f"fuzz{len(cases):05d}"
        change(request)
        return Case(kind, request=request)

    base = valid[0]
    jpeg = io.BytesIO()
    Image.open(io.BytesIO(base.image)).convert("RGB").save(jpeg, format="JPEG", quality=80)
    for kind, data in _images(base.image, jpeg.getvalue()):
        cases.append(derived(kind, lambda r, d=data: setattr(r, "image", d)))
    for kind, change in _calibrations():

        def calibrate(r, change=change):
            for name, values in change.items():
                getattr(r.calibration, name)[:] = values

        cases.append(derived(kind, calibrate))  # fmt: skip
    for kind, field, value in _ids():
        cases.append(derived(kind, lambda r, f=field, v=value: setattr(r, f, v)))
    for kind, name, value in _options():
        cases.append(derived(kind, lambda r, n=name, v=value: setattr(r.options, n, v)))
    points = np.frombuffer(base.points, "<f4").reshape(-1, 4)
    fixed_points = [
        ("points: empty", b""),
        ("points: 20 bytes", b"\0" * 20),
        ("points: one float short", base.points[:-4]),
        ("points: NaN", _with(points, (3, 1), np.nan)),
        ("points: Inf", _with(points, (0, 0), np.inf)),
        ("points: -Inf intensity", _with(points, (5, 3), -np.inf)),
        ("points: 3e38 coordinates", np.full((1000, 4), 3e38, "<f4").tobytes()),
        ("points: one point", np.zeros((1, 4), "<f4").tobytes()),
        ("points: 200k points at one spot", np.zeros((200_000, 4), "<f4").tobytes()),
    ]
    if large:
        fixed_points += [
            ("points: 4M points (64 MB, over the message limit)",
             np.zeros((4_200_000, 4), "<f4").tobytes()),
            ("points: 3M points (48 MB)", np.ones((3_000_000, 4), "<f4").tobytes()),
        ]  # fmt: skip
    for kind, data in fixed_points:
        cases.append(derived(kind, lambda r, d=data: setattr(r, "points", d)))
    serialized = base.SerializeToString()
    cases += [
        Case("raw: empty message", raw=b""),
        Case("raw: 0xff x 64", raw=b"\xff" * 64),
        Case("raw: length prefix of 2 GB", raw=b"\x12\xff\xff\xff\xff\x07abc"),
        Case("raw: wrong wire type for frame_id", raw=b"\x0d\x00\x00\x00\x00"),
        Case("raw: unknown fields only", raw=b"\xf8\x07\x01" * 20),
        Case("raw: nested garbage in calibration", raw=b"\x22\x05\xff\xff\xff\xff\xff"),
        Case("raw: the request, truncated by one byte", raw=serialized[:-1]),
    ]
    while len(cases) < count:
        roll = rng.random()
        if roll < 0.3:
            cut = rng.randrange(1, len(serialized))
            cases.append(Case("raw: truncated request", raw=serialized[:cut]))
        elif roll < 0.55:
            data = bytearray(serialized[: rng.randrange(64, 4096)])
            for _ in range(rng.randrange(1, 8)):
                data[rng.randrange(len(data))] = rng.randrange(256)
            cases.append(Case("raw: bit-flipped request prefix", raw=bytes(data)))
        elif roll < 0.65:
            cases.append(Case("raw: random bytes", raw=rng.randbytes(rng.randrange(1, 2048))))
        elif roll < 0.75:
            length = rng.randrange(0, 4096)
            data = points.tobytes()[:length]
            cases.append(
                derived("points: random length", lambda r, d=data: setattr(r, "points", d))
            )
        elif roll < 0.85:
            data = bytearray(base.image)
            for _ in range(rng.randrange(1, 16)):
                data[rng.randrange(8, len(data))] = rng.randrange(256)
            cases.append(
                derived("image: corrupted bytes", lambda r, d=bytes(data): setattr(r, "image", d))
            )
        else:
            values = [rng.choice([0.0, 1e308, -1e-300, float("nan"), rng.uniform(-1e3, 1e3)])
                      for _ in range(12)]  # fmt: skip
            change = lambda r, v=values: r.calibration.p2.__setitem__(slice(None), v)  # noqa: E731
            cases.append(derived("calibration: random P2", change))
    return cases[:count] if count >= len(cases) else _spread(cases, count)


def _spread(cases: list[Case], count: int) -> list[Case]:
    """count cases covering every kind (the first of each), then the rest in order."""
    firsts, seen = [], set()
    for case in cases:
        if case.kind not in seen:
            seen.add(case.kind)
            firsts.append(case)
    chosen = {id(c) for c in firsts}
    return (firsts + [c for c in cases if id(c) not in chosen])[:count]


def _with(points: np.ndarray, at: tuple[int, int], value: float) -> bytes:
    changed = points.copy()
    changed[at] = value
    return changed.astype("<f4").tobytes()


def send(channel: grpc.Channel, case: Case, metadata=()) -> tuple[grpc.StatusCode, str]:
    """(status code, details) of one call."""
    from serving.client import pb2_grpc

    try:
        if case.raw is not None:
            call = channel.unary_unary(LABEL_FRAME)
            call(case.raw, timeout=60, metadata=metadata)
        else:
            pb2_grpc.AutoLabelerStub(channel).LabelFrame(case.request, timeout=60,
                                                         metadata=metadata)  # fmt: skip
        return grpc.StatusCode.OK, ""
    except grpc.RpcError as error:
        return error.code(), error.details() or ""


def run_cases(target: str, cases: list[Case]) -> Iterator[tuple[Case, grpc.StatusCode, str]]:
    options = [("grpc.max_send_message_length", 256 << 20),
               ("grpc.max_receive_message_length", 256 << 20)]  # fmt: skip
    with grpc.insecure_channel(target, options=options) as channel:
        for case in cases:
            code, details = send(channel, case)
            yield case, code, details


def stored_keys(store: Path) -> set[tuple[str, str]]:
    from serving.store import list_frames

    return {r.key for r in list_frames(store)} if (store / "shards").is_dir() else set()


def main() -> None:
    parser = benchmark_parser(__doc__)
    parser.add_argument("--cases", type=int, default=1200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--config", default="configs/tiny.toml")
    parser.add_argument("--work", help="working directory (default: a temporary one)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args()
    from benchmarks.service_common import sample_requests
    from serving.store import check_integrity

    work = Path(args.work or tempfile.mkdtemp(prefix="service_fuzz_"))
    repository = prepare_repository(work, args.config)
    store = work / f"store_fuzz_{args.seed}_{random.randrange(1 << 30)}"
    valid = sample_requests(prefix="valid")
    cases = fuzz_cases(valid, args.cases, args.seed)
    codes: Counter[str] = Counter()
    by_kind: dict[str, Counter[str]] = {}
    accepted: set[tuple[str, str]] = set()
    with serve(repository, store) as server:
        with RssSampler(server.pid, 0.25) as rss:
            rss_start = server.rss_mib()
            for case, code, details in run_cases(server.target, cases):
                codes[code.name] += 1
                by_kind.setdefault(case.kind.split(":")[0], Counter())[code.name] += 1
                if code == grpc.StatusCode.OK and case.request is not None:
                    accepted.add((case.request.namespace or "default", case.request.frame_id))
                if code in (grpc.StatusCode.INTERNAL, grpc.StatusCode.UNKNOWN):
                    print(f"{code.name}: {case.kind}: {details[:200]}")
            alive = server.process.poll() is None
            from benchmarks.service_stall import measure  # health + a valid call afterwards

            after = measure(server.target, 2.0) if alive else None
        log = server.log()
    changed = stored_keys(store) - accepted
    errors = [line for line in log.splitlines() if '"level": "ERROR"' in line
              or "Traceback" in line]  # fmt: skip
    integrity = check_integrity(store)
    print(f"{len(cases)} cases (seed {args.seed}) against detmatch serve, model {args.config}")
    print("\n| status | calls |\n| --- | ---: |")
    for name, count in codes.most_common():
        print(f"| {name} | {count} |")
    print("\n| case family | status codes |\n| --- | --- |")
    for kind, counter in sorted(by_kind.items()):
        print(f"| {kind} | {', '.join(f'{k} {v}' for k, v in counter.most_common())} |")
    serving = after is not None and after["frames_per_s"] > 0 and not after["label_failures"]
    print(f"\nINTERNAL: {codes['INTERNAL']}, UNKNOWN: {codes['UNKNOWN']}; server alive: {alive}; "
          f"SERVING and labeling afterwards: {serving}")  # fmt: skip
    print(f"store: {len(accepted)} keys stored by OK calls, {len(changed)} other keys; "
          f"integrity problems: {len(integrity)}")  # fmt: skip
    print(f"error lines in the server log: {len(errors)}")
    print(f"server RSS: {rss_start:.0f} MiB at the start, peak {rss.peak:.0f} MiB, "
          f"{rss.samples[-1][1]:.0f} MiB at the end")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps({"codes": codes, "by_kind": by_kind,
                                               "alive": alive, "serving": serving,
                                               "other_keys": len(changed),
                                               "error_lines": errors[:20],
                                               "rss": rss.samples}, indent=2) + "\n")  # fmt: skip
    argv = ["--cases", str(args.cases), "--seed", str(args.seed), "--config", args.config]
    print(f"\nrerun: {rerun('service_fuzz', argv)}")


if __name__ == "__main__":
    main()
