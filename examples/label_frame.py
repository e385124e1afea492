"""Send one frame of a KITTI-layout directory to a running `detmatch serve` and print its labels.

python examples/label_frame.py --target 127.0.0.1:50051 --data data/synth --frame 000000
DETMATCH_TOKEN=... python examples/label_frame.py --target host:443 --ca-cert ca.pem ...

The bearer token comes from $DETMATCH_TOKEN (the server's own variable); none is sent when it is
unset, for a server started with --no-auth. A refused call, an unreachable server or a missing
frame ends in one line on stderr and exit status 1 (the server's status code and its message),
not a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import grpc

from serving.client import LabelingClient, pb2


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--target", default="127.0.0.1:50051", help="server host:port")
    parser.add_argument("--data", required=True, help="KITTI-layout directory (training/...)")
    parser.add_argument("--frame", required=True, help="frame id, e.g. 000000")
    parser.add_argument("--ca-cert", help="PEM certificate to verify the server (TLS)")
    parser.add_argument(
        "--namespace", help="the data set the frame id belongs to (default: default)"
    )
    parser.add_argument("--no-store", action="store_true", help="label without storing")
    parser.add_argument("--raw-image", action="store_true",
                        help="send the image's pixels uncompressed (no decode on the server; "
                        "for labeling without storing)")  # fmt: skip
    args = parser.parse_args()
    token = os.environ.get("DETMATCH_TOKEN") or None
    try:
        root_certificates = Path(args.ca_cert).read_bytes() if args.ca_cert else None
        with LabelingClient(
            args.target, token=token, root_certificates=root_certificates
        ) as client:
            response = client.label_kitti_frame(
                Path(args.data),
                args.frame,
                store=not args.no_store,
                namespace=args.namespace,
                raw_image=args.raw_image,
            )
    except grpc.RpcError as error:
        hint = ""
        if error.code() == grpc.StatusCode.UNAUTHENTICATED and token is None:
            hint = " (set $DETMATCH_TOKEN to the server's token)"
        print(f"label_frame: {error.code().name}: {error.details()}{hint}", file=sys.stderr)
        return 1
    except FileNotFoundError as error:  # a frame or certificate that is not there
        print(f"label_frame: error: no such file: {error.filename}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as error:  # an unreadable file, a bad frame id
        print(f"label_frame: error: {error}", file=sys.stderr)
        return 1
    outcome = pb2.StoreOutcome.Name(response.store_outcome).removeprefix("STORE_OUTCOME_")
    print(
        f"frame {response.namespace}/{response.frame_id}: {len(response.labels)} labels from "
        f"model version {response.model_version} in {response.timing.total_s * 1000:.1f} ms"
        f"{f' (stored: {outcome.lower()})' if response.stored else ''}"
    )
    for label in response.labels:
        b = label.box_3d
        line = (
            f"{pb2.Provenance.Name(label.provenance):36s} {label.class_name:10s} "
            f"3D ({b.x:.2f} {b.y:.2f} {b.z:.2f} {b.l:.2f} {b.w:.2f} {b.h:.2f} {b.yaw:.2f}) "
            f"score {label.score_3d:.3f}"
        )
        if label.HasField("box_2d"):
            c = label.box_2d
            line += (
                f" | 2D {label.class_name_2d} ({c.x1:.0f} {c.y1:.0f} {c.x2:.0f} {c.y2:.0f}) "
                f"score {label.score_2d:.3f} cost {label.match_cost:.3f}"
            )
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
