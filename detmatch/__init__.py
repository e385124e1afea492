"""DetMatch: joint 2D-3D semi-supervised object detection.

Importing the package imports no torch: the labeling service shares structures, geometry and
matching with training.
"""

__version__ = "0.1.0"
