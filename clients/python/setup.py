"""Builds nak-client, compiling nak's gRPC API (proto/nak/v1/deformation.proto) into the package first."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent
PROTO = "nak/v1/deformation.proto"


def proto_root() -> Path:
    """The repository's proto/ (the client lives at clients/python in the nak repository)."""
    for candidate in (HERE.parents[1] / "proto", HERE / "proto"):
        if (candidate / PROTO).exists():
            return candidate
    raise FileNotFoundError(f"{PROTO} not found: build nak-client from the nak repository (clients/python)")


class BuildWithStubs(build_py):  # type: ignore[misc]  # setuptools ships no type stubs
    """Generates `nak_client/_generated/` (messages with type stubs, and the gRPC stub) before building."""

    def run(self) -> None:
        from grpc_tools import protoc

        target = HERE / "src" / "nak_client" / "_generated"
        target.mkdir(exist_ok=True)
        with tempfile.TemporaryDirectory() as out:
            args = [
                "protoc",
                f"-I{proto_root()}",
                f"--python_out={out}",
                f"--pyi_out={out}",
                f"--grpc_python_out={out}",
            ]
            if protoc.main([*args, PROTO]) != 0:
                raise RuntimeError(f"protoc failed on {PROTO}")
            for generated in (Path(out) / "nak" / "v1").iterdir():
                text = generated.read_text()
                # protoc writes absolute imports (`from nak.v1 import …`); inside the package they are relative.
                text = re.sub(r"^from nak\.v1 import", "from . import", text, flags=re.MULTILINE)
                (target / generated.name).write_text(text)
        (target / "__init__.py").write_text('"""Generated from proto/nak/v1/deformation.proto at build time."""\n')
        super().run()


setup(cmdclass={"build_py": BuildWithStubs})
