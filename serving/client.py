"""A small Python client of the AutoLabeler service.

with LabelingClient("localhost:50051") as client:
    response = client.label_kitti_frame("data/kitti", "000000")
    for label in response.labels:
        print(label.class_name, label.box_3d, label.score_3d)
"""

from __future__ import annotations

import os
from pathlib import Path

import grpc
import numpy as np

from detmatch.data.kitti import KittiDataset
from detmatch.structures import Calibration
from serving.decode import encode_points
from serving.proto import load as load_stubs

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

    def label_frame(
        self,
        frame_id: str,
        image: bytes,
        points: np.ndarray | bytes,
        calib: Calibration,
        *,
        store: bool = True,
        tau_hung: float | None = None,
        score_threshold_2d: float | None = None,
        score_threshold_3d: float | None = None,
        timeout_s: float | None = None,
        namespace: str | None = None,
    ):
        """image: PNG or JPEG bytes; points: (N, 4) LiDAR points (or their wire bytes);
        namespace: the data set the frame id belongs to (None: the server's default)."""
        request = self.request(
            frame_id, image, points, calib, store=store, tau_hung=tau_hung,
            score_threshold_2d=score_threshold_2d, score_threshold_3d=score_threshold_3d,
            namespace=namespace,
        )  # fmt: skip
        return self.stub.LabelFrame(
            request, timeout=timeout_s or self.timeout_s, metadata=self.metadata
        )

    @staticmethod
    def request(
        frame_id: str,
        image: bytes,
        points: np.ndarray | bytes,
        calib: Calibration,
        *,
        store: bool = True,
        tau_hung: float | None = None,
        score_threshold_2d: float | None = None,
        score_threshold_3d: float | None = None,
        namespace: str | None = None,
    ):
        """The LabelFrameRequest that label_frame sends."""
        options = pb2.LabelOptions(store=store)
        for name, value in (
            ("tau_hung", tau_hung),
            ("score_threshold_2d", score_threshold_2d),
            ("score_threshold_3d", score_threshold_3d),
        ):
            if value is not None:
                setattr(options, name, value)
        request = pb2.LabelFrameRequest(
            frame_id=frame_id,
            image=image,
            points=points if isinstance(points, bytes) else encode_points(points),
            calibration=calibration_message(calib),
            options=options,
        )
        if namespace is not None:
            request.namespace = namespace
        return request

    def label_kitti_frame(
        self, root: str | os.PathLike, frame_id: str, *, send_as: str | None = None, **kwargs
    ):
        """Send frame_id of a KITTI-layout directory (training/image_2, velodyne, calib),
        under the id send_as if given; kwargs as label_frame's."""
        timeout_s = kwargs.pop("timeout_s", None)
        request = self.kitti_request(root, frame_id, send_as=send_as, **kwargs)
        return self.stub.LabelFrame(
            request, timeout=timeout_s or self.timeout_s, metadata=self.metadata
        )

    @staticmethod
    def kitti_request(
        root: str | os.PathLike, frame_id: str, *, send_as: str | None = None, **kwargs
    ):
        """The request label_kitti_frame sends; kwargs as request's."""
        dataset = KittiDataset(Path(root))
        frame = dataset.load_frame(frame_id, with_labels=False)
        image = dataset.image_path(frame_id).read_bytes()
        return LabelingClient.request(
            send_as or frame_id, image, frame.points, frame.calib, **kwargs
        )

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


def calibration_message(calib: Calibration):
    return pb2.Calibration(
        p2=calib.P2.reshape(-1).tolist(),
        r0_rect=calib.R0_rect.reshape(-1).tolist(),
        tr_velo_to_cam=calib.Tr_velo_to_cam.reshape(-1).tolist(),
    )
