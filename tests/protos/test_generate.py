"""The committed generated code under protos/ is what the committed .proto files generate today."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from protos import generate

# The generator's version is stamped into the files; another version writes other bytes.
VERSION_LINES = re.compile(r"^(# Protobuf Python Version: .*|GRPC_GENERATED_VERSION = .*)$", re.MULTILINE)
# What the .proto files decide, whichever generator wrote the code: the serialized file descriptor
# (_pb2.py), the rpc paths and message classes (_pb2_grpc.py), the classes and fields (.pyi).
DECIDED = re.compile(
    r"AddSerializedFile\((b'.*?')\)"
    r"|'/asac\.\w+/\w+'"
    r"|\w+_pb2\.\w+\.(?:SerializeToString|FromString)"
    r"|^class \w+"
    r"|\w+_FIELD_NUMBER",
    re.MULTILINE | re.DOTALL,
)


def decided(text: str) -> list[str]:
    """What in a generated file comes from the .proto files, not from the generator's version."""
    return sorted(m.group(0) for m in DECIDED.finditer(text))


def test_generated_code_is_fresh(tmp_path: Path) -> None:
    """The same generator writes the same bytes; another one (a grpcio-tools other than the one that
    wrote the committed files) must still find every descriptor, rpc, class and field the same."""
    written = generate.generate(tmp_path)
    assert written, "no .proto files under protos/"
    stale = []
    for path in written:
        committed, fresh = generate.ROOT / path, tmp_path / path
        assert committed.exists(), f"{path} is not committed: run python -m protos.generate"
        if committed.read_bytes() == fresh.read_bytes():
            continue
        ours, theirs = committed.read_text(), fresh.read_text()
        same_generator = VERSION_LINES.findall(ours) == VERSION_LINES.findall(theirs)
        if same_generator or decided(ours) != decided(theirs):
            stale.append(str(path))
    assert not stale, f"stale generated code {stale}: run python -m protos.generate from the repository root"


def test_what_a_proto_decides_is_read_from_each_generated_file() -> None:
    """The comparison above sees something in every kind of generated file (else it could not fail)."""
    for stem in ("replay", "learner", "evolver"):
        for suffix in ("_pb2.py", "_pb2_grpc.py", "_pb2.pyi"):
            assert decided((generate.ROOT / "protos" / f"{stem}{suffix}").read_text()), f"{stem}{suffix}"


def test_every_proto_is_generated() -> None:
    assert {p.stem for p in generate.proto_files()} >= {"replay", "learner", "evolver"}


@pytest.mark.parametrize(
    "name, service", [("replay", "ReplayService"), ("learner", "LearnerService"), ("evolver", "EvolverService")]
)
def test_generated_modules_import_as_the_protos_package(name: str, service: str) -> None:
    import importlib

    pb2 = importlib.import_module(f"protos.{name}_pb2")
    pb2_grpc = importlib.import_module(f"protos.{name}_pb2_grpc")
    assert pb2.DESCRIPTOR.name == f"protos/{name}.proto"
    assert getattr(pb2_grpc, f"{service}Stub").__module__ == f"protos.{name}_pb2_grpc"
    assert pb2.DESCRIPTOR.services_by_name[service].full_name == f"asac.{service}"


def test_learner_proto_shares_the_replay_tensor() -> None:
    from protos import learner_pb2, replay_pb2

    field = learner_pb2.GetActionRequest.DESCRIPTOR.fields_by_name["obs"]
    assert field.message_type is replay_pb2.Tensor.DESCRIPTOR
