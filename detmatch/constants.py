"""The method's constants (docs/design.md section 3), defined once.

The config's defaults, the matching, the pseudo-label rules, the 2D detector's normalisation,
the photometric augmentation and the exported manifest all read them from here. No imports:
the torch-free service uses them too.
"""

# Hungarian matching: assigned 2D-3D pairs with cost <= TAU_HUNG become pseudo-labels.
TAU_HUNG = -1.5
# Single-modality confidence thresholding (also the 3D fallback outside the camera's view).
TAU_3D = 0.3
TAU_2D = 0.7
# A teacher's own decoding keeps boxes whose max class probability exceeds this.
SCORE_THRESHOLD = 0.1
# The 2D-teacher -> 3D-student consistency loss on matched pairs: 2 x focal loss of the 3D
# student's class logits, 20 x mean L1 of normalised xyxy, 2 x mean (1 - GIoU).
CONSISTENCY_CLASS_WEIGHT = 2.0
CONSISTENCY_L1_WEIGHT = 20.0
CONSISTENCY_GIOU_WEIGHT = 2.0

# The 2D detector's input normalisation, per RGB channel, for images in [0, 1]
# (ImageNet's statistics; multiply by 255 for [0, 255] pixels).
IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)

# `detmatch review export` (serving.review): its formats and frame selections, and the path
# Label Studio serves files under LOCAL_FILES_DOCUMENT_ROOT at (here so that building the
# command line imports nothing of the service).
REVIEW_3D_FORMATS = ("cvat-3d", "kitti-raw", "datumaro-3d")  # CVAT's 3D formats (datumaro)
REVIEW_FORMATS = (*REVIEW_3D_FORMATS, "label-studio")
REVIEW_SELECTIONS = ("all", "random", "least-confident", "disagreement")
LABEL_STUDIO_LOCAL_FILES = "/data/local-files/?d="
# `detmatch retrain`'s exit status when another retraining holds the repository's lock (what
# the review backend's queue waits on).
RETRAIN_LOCK_HELD_EXIT = 3
# The labels a reviewer can choose from in an exported review set (with any other class the
# exported labels hold), and the ones an import accepts by default.
REVIEW_CLASSES = ("Car", "Pedestrian", "Cyclist", "Van")
