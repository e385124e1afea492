"""A small Python client of the AutoLabeler service.

with LabelingClient("localhost:50051") as client:
    response = client.label_kitti_frame("data/kitti", "000000")
    for label in response.labels:
        print(label.class_name, label.box_3d, label.score_3d)

Any frame: `client.label_frame(FrameRequest.from_arrays(frame_id, png_bytes, points, calib))`;
`request_message(request)` (serving.messages) is the LabelFrameRequest it sends.
"""

from __future__ import annotations

import os
from pathlib import Path

import grpc

from detmatch.data.kitti import KittiDataset
from serving.messages import request_message
from serving.proto import load as load_stubs
from serving.request import DEFAULT_OPTIONS, FrameRequest, LabelOptions

pb2, pb2_grpc = load_stubs()


class LabelingClient:
    def __init__(
        self,
        target: str,
        token: str | None = None,
        root_certificates: bytes | None = None,
        timeout_s: float | None = 60.0,
        max_message_bytes: int = 64 * 1024 * 1024,
        server_name: str | None = None,
    ) -> None:
        """target: host:port; root_certificates: PEM bytes to verify the server (enables TLS);
        server_name: the name the certificate holds, if not the target's host."""
        options = [
            ("grpc.max_send_message_length", max_message_bytes),
            ("grpc.max_receive_message_length", max_message_bytes),
        ]
        if server_name:
            options.append(("grpc.ssl_target_name_override", server_name))
        if root_certificates is not None:
            credentials = grpc.ssl_channel_credentials(root_certificates=root_certificates)
            self.channel = grpc.secure_channel(target, credentials, options=options)
        else:
            self.channel = grpc.insecure_channel(target, options=options)
        self.stub = pb2_grpc.AutoLabelerStub(self.channel)
        self.metadata = (("authorization", f"Bearer {token}"),) if token else ()
        self.timeout_s = timeout_s

    def label_frame(self, request: FrameRequest, timeout_s: float | None = None):
        """Send one frame; the LabelFrameResponse."""
        return self.stub.LabelFrame(
            request_message(request), timeout=timeout_s or self.timeout_s, metadata=self.metadata
        )

    def label_kitti_frame(
        self,
        root: str | os.PathLike,
        frame_id: str,
        *,
        send_as: str | None = None,
        namespace: str | None = None,
        store: bool = True,
        timeout_s: float | None = None,
        raw_image: bool = False,
    ):
        """Send frame_id of a KITTI-layout directory (training/image_2, velodyne, calib),
        under the id send_as if given; raw_image: the decoded pixels instead of the file. Other
        options: label_frame(kitti_frame(...))."""
        request = kitti_frame(root, frame_id, send_as=send_as, namespace=namespace,
                              options=LabelOptions(store=store), raw_image=raw_image)  # fmt: skip
        return self.label_frame(request, timeout_s)

    def model_info(self):
        return self.stub.GetModelInfo(
            pb2.GetModelInfoRequest(), timeout=self.timeout_s, metadata=self.metadata
        )

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> LabelingClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def kitti_frame(
    root: str | os.PathLike,
    frame_id: str,
    *,
    send_as: str | None = None,
    namespace: str | None = None,
    options: LabelOptions = DEFAULT_OPTIONS,
    raw_image: bool = False,
) -> FrameRequest:
    """The request for frame_id of a KITTI-layout directory, under the id send_as if given;
    raw_image: the image's pixels uncompressed (RawImage) instead of its file's bytes."""
    dataset = KittiDataset(Path(root))
    frame = dataset.load_frame(frame_id, with_labels=False)
    image = frame.image if raw_image else dataset.image_path(frame_id).read_bytes()
    return FrameRequest.from_arrays(
        send_as or frame_id, image, frame.points, frame.calib, namespace=namespace, options=options
    )
