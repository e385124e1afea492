"""torch -> ONNX: both detectors exported with their preprocessing and decoding, checked
(onnx.checker, onnxruntime-vs-PyTorch parity) and published as a version of a model
repository (`serving.repository`). Entry point: `detmatch-export` (commands.export)."""
