"""The labeling service's side: numpy + scipy + onnxruntime, never torch.

`serving.repository` reads (and the exporter writes) the versioned model repository;
`serving.labeler.Labeler` labels one paired frame with a version's two ONNX models;
`serving.offline` labels a whole KITTI-layout data set (`detmatch label`).
"""
