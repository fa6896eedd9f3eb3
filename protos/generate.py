"""Regenerate the Python code of every ``protos/*.proto``: ``python -m protos.generate`` (repo root).

protoc runs with the repository root as the include path, so generated modules import each other as
``from protos import replay_pb2``. The output depends on the grpcio-tools version (its bundled protoc
and templates); the version that generated the committed files is recorded in their headers.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def proto_files() -> list[Path]:
    """Every ``.proto`` under ``protos/``, relative to the repository root."""
    return sorted(p.relative_to(ROOT) for p in (ROOT / "protos").glob("*.proto"))


def generate(out_dir: Path = ROOT) -> list[Path]:
    """Write ``*_pb2.py``, ``*_pb2_grpc.py`` and ``*_pb2.pyi`` for every proto under ``out_dir/protos``;
    returns the written paths relative to ``out_dir``. Raises ``RuntimeError`` if protoc fails."""
    from grpc_tools import protoc  # only needed here: importing protos must not need grpcio-tools

    out_dir = Path(out_dir)
    (out_dir / "protos").mkdir(parents=True, exist_ok=True)
    written = []
    for proto in proto_files():
        args = [
            "grpc_tools.protoc",
            f"-I{ROOT}",
            f"--python_out={out_dir}",
            f"--grpc_python_out={out_dir}",
            f"--pyi_out={out_dir}",
            str(ROOT / proto),
        ]
        if protoc.main(args) != 0:
            raise RuntimeError(f"protoc failed on {proto} (arguments {args})")
        stem = proto.with_suffix("")
        written += [Path(f"{stem}_pb2.py"), Path(f"{stem}_pb2_grpc.py"), Path(f"{stem}_pb2.pyi")]
    return written


if __name__ == "__main__":
    for path in generate():
        print(path)
    sys.exit(0)
