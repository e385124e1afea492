"""Synthetic paired camera + LiDAR data in KITTI layout (docs/design.md section 6).

Road scenes with Cars, Vans, Pedestrians and Cyclists, pedestrian-sized clutter (ambiguous in
the point cloud, obvious in colour) and parked rows (overlapping in the image, apart in 3D),
rendered by ray casting into a KITTI-like camera image and a 64-beam LiDAR sweep.
"""

from detmatch.data.synth.dataset import (
    SynthFrame,
    generate_dataset,
    generate_frame,
    render_scene,
    split_ids,
)
from detmatch.data.synth.layout import sample_scene
from detmatch.data.synth.scene import Scene, SceneObject

__all__ = [
    "Scene",
    "SceneObject",
    "SynthFrame",
    "generate_dataset",
    "generate_frame",
    "render_scene",
    "sample_scene",
    "split_ids",
]
