from tests.onnx_fixtures import (  # noqa: F401
    _one_torch_thread,
    exported_repository,
    served_labeler,
    trained_checkpoint,
)
