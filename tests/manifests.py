"""A valid, minimal manifest for repository tests that publish placeholder files."""

from __future__ import annotations

from serving.manifest import (
    MANIFEST_FORMAT,
    FileRecord,
    ImagePreprocessing,
    Manifest,
    MatchingSpec,
    Model2DSpec,
    Model3DSpec,
    Models,
    PillarGridSpec,
    PillarPreprocessing,
    Postprocessing,
    TrainingRecord,
)


def minimal_manifest(version: str, files: dict[str, FileRecord]) -> Manifest:
    """Both model entries point at the first listed file."""
    first = next(iter(files))
    post = Postprocessing(in_graph="decode", boxes="boxes", outside_graph="threshold")
    grid = PillarGridSpec((0.0, -8.0, -3.0, 16.0, 8.0, 1.0), (0.5, 0.5), 4, 100)
    return Manifest(
        format=MANIFEST_FORMAT,
        version=version,
        exported_at="2026-01-01T00:00:00Z",
        classes=("Car",),
        models=Models(
            detector2d=Model2DSpec(
                file=first,
                opset=17,
                inputs=(),
                outputs=(),
                preprocessing=ImagePreprocessing(
                    True, "image", (), (64, 32), (0.5, 0.5, 0.5), (0.2, 0.2, 0.2)
                ),
                postprocessing=post,
                max_detections=10,
                score_threshold=0.1,
            ),
            detector3d=Model3DSpec(
                file=first,
                opset=17,
                inputs=(),
                outputs=(),
                preprocessing=PillarPreprocessing(False, "points", "pillarize", grid),
                postprocessing=post,
                max_detections=10,
                score_threshold=0.1,
            ),
        ),  # fmt: skip
        matching=MatchingSpec(tau_hung=-1.5, tau_3d_outside_view=0.3, function="match"),
        training=TrainingRecord("ckpt.pt", "0" * 64, 1, {}, {}),
        parity={},
        tools={},
        files=files,
    )
