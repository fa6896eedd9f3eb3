"""Damage saved files the way disks, copies and interrupted transfers do, for the tests of what reads them."""

from __future__ import annotations

import hashlib
import struct
import zipfile
from pathlib import Path


def flip_in_largest_record(path: Path, xor: int = 0x40) -> None:
    """Flip one bit in the middle of the largest data member of a zip file (a checkpoint's largest
    tensor, not its pickle; a replay snapshot's largest array): the bytes change, the layout does not."""
    with zipfile.ZipFile(path) as archive:
        members = archive.infolist()
        info = max([m for m in members if "/data/" in m.filename] or members, key=lambda m: m.file_size)
    data = bytearray(path.read_bytes())
    name_length, extra_length = struct.unpack_from("<HH", data, info.header_offset + 26)  # local file header
    data[info.header_offset + 30 + name_length + extra_length + info.file_size // 2] ^= xor
    path.write_bytes(bytes(data))


def truncate(path: Path, fraction: float = 0.5) -> None:
    """Keep the first ``fraction`` of the file, as an interrupted copy leaves it."""
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


def tree_digest(root: Path) -> dict[str, str]:
    """Every file under ``root`` by relative path, with the SHA-256 of its bytes."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }
