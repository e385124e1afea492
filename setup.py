"""Build step of the wheel: generate the gRPC stubs from protos/ into the built `serving`
package (serving/proto.py does the work; editable installs generate them on first import).
Everything else about the package is in pyproject.toml."""

import importlib.util
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent


class BuildPyWithStubs(build_py):
    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        spec = importlib.util.spec_from_file_location("_proto_build", ROOT / "serving" / "proto.py")
        proto = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(proto)
        proto.generate(force=True, target=Path(self.build_lib) / "serving" / "_generated")


setup(
    packages=[
        *find_packages(include=["detmatch*", "export*", "serving*", "retrain*", "commands*"]),
        "detmatch.configs",
    ],
    package_dir={"detmatch.configs": "configs"},
    cmdclass={"build_py": BuildPyWithStubs},
)
