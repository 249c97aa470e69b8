"""Messages of a geometry checkpoint served to a peer: a replica that starts with no checkpoint of
its own copies its peer's (docs/SHARDS.md, "Replicas"; :mod:`openfusion.services.geometry.peer_copy`).

The peer answers a :class:`CheckpointListRequest` with a :class:`CheckpointListing` naming one
*snapshot* (a consistent copy of its newest committed checkpoint, made for this request): its
files with their sizes and SHA-256 digests. The replica then asks each file in chunks
(:class:`CheckpointChunkRequest` -> :class:`CheckpointChunk`, at most
:data:`~openfusion.wire.limits.MAX_CHECKPOINT_CHUNK_BYTES` each, each with its own digest) and
lets the snapshot go (:class:`CheckpointRelease`). File names are relative paths whose every part
is one key segment (no ``..``, no absolute path), so a listing can never name a file outside the
folder it is written into.
"""

from __future__ import annotations

import re
from typing import Annotated, ClassVar

from pydantic import AfterValidator, Field, model_validator

from openfusion.wire.codec import ndarray
from openfusion.wire.keys import segment_error
from openfusion.wire.limits import MAX_CHECKPOINT_CHUNK_BYTES, MAX_CHECKPOINT_FILES
from openfusion.wire.message import Message, Record

_HEX64 = re.compile(r"^[0-9a-f]{64}$")
_SNAPSHOT = re.compile(r"^[0-9a-f]{8,64}$")
#: Most folder levels in a checkpoint file's name (``map.ofz/data.mdb`` is two).
MAX_NAME_PARTS = 4


def check_file_name(name: str) -> str:
    """A checkpoint file's name: a relative path of 1 to :data:`MAX_NAME_PARTS` parts, each a valid
    key segment (so never ``..``, ``/`` first, a hidden file or a wildcard)."""
    parts = name.split("/")
    if not 1 <= len(parts) <= MAX_NAME_PARTS:
        raise ValueError(f"checkpoint file name {name!r} must have 1 to {MAX_NAME_PARTS} parts")
    for part in parts:
        why = segment_error(part)
        if why is not None:
            raise ValueError(f"checkpoint file name {name!r} is not valid: part {part!r} {why}")
    return name


def check_sha256(text: str) -> str:
    if not _HEX64.match(text):
        raise ValueError("a SHA-256 digest is 64 lowercase hex digits")
    return text


def check_snapshot_id(text: str) -> str:
    if not _SNAPSHOT.match(text):
        raise ValueError("a snapshot id is 8 to 64 lowercase hex digits")
    return text


FileName = Annotated[str, AfterValidator(check_file_name)]
Sha256 = Annotated[str, AfterValidator(check_sha256)]
SnapshotId = Annotated[str, AfterValidator(check_snapshot_id)]


class CheckpointFile(Record):
    """One file of a served checkpoint."""

    name: FileName
    size_bytes: int = Field(ge=0)
    sha256: Sha256


class CheckpointListRequest(Message):
    """Ask a geometry (one replica of a shard, at its own key) for its newest complete checkpoint.

    ``checkpoint_first``: it checkpoints what it holds now before serving (when anything changed
    since its last checkpoint), so the copy misses as few frames as it can (a live source's frames
    between the checkpoint and the asker's start are never replayed); ``requester``: the asking
    service's name, for the peer's log."""

    schema_name: ClassVar[str] = "geometry.checkpoint_list_request"
    schema_version: ClassVar[int] = 1

    checkpoint_first: bool = True
    requester: str = Field("", max_length=64)


class CheckpointListing(Message):
    """A snapshot of the peer's checkpoint, ready to be copied: its files (names, sizes, digests)
    and what it holds (``last_frame_id`` of the map's first robot, -1: none; ``frames_integrated``;
    ``tiles``). ``chunk_bytes``: the largest chunk the peer serves; ``source``: the peer's service
    name (``geometry-0of2``)."""

    schema_name: ClassVar[str] = "geometry.checkpoint_listing"
    schema_version: ClassVar[int] = 1

    snapshot_id: SnapshotId
    source: str = Field(min_length=1, max_length=64)
    files: list[CheckpointFile] = Field(min_length=1, max_length=MAX_CHECKPOINT_FILES)
    chunk_bytes: int = Field(gt=0, le=MAX_CHECKPOINT_CHUNK_BYTES)
    last_frame_id: int = Field(-1, ge=-1)
    frames_integrated: int = Field(0, ge=0)
    tiles: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _unique(self) -> CheckpointListing:
        names = [f.name for f in self.files]
        if len(set(names)) != len(names):
            raise ValueError("a checkpoint listing names a file twice")
        return self

    @property
    def total_bytes(self) -> int:
        return sum(f.size_bytes for f in self.files)


class CheckpointChunkRequest(Message):
    """Bytes ``offset_bytes`` .. ``offset_bytes + length_bytes`` of file ``name`` of a snapshot."""

    schema_name: ClassVar[str] = "geometry.checkpoint_chunk_request"
    schema_version: ClassVar[int] = 1

    snapshot_id: SnapshotId
    name: FileName
    offset_bytes: int = Field(ge=0)
    length_bytes: int = Field(gt=0, le=MAX_CHECKPOINT_CHUNK_BYTES)


class CheckpointChunk(Message):
    """One chunk of a snapshot's file: ``data`` (bytes ``offset_bytes`` on; shorter than asked only
    at the end of the file) and its SHA-256 digest."""

    schema_name: ClassVar[str] = "geometry.checkpoint_chunk"
    schema_version: ClassVar[int] = 1

    snapshot_id: SnapshotId
    name: FileName
    offset_bytes: int = Field(ge=0)
    data: ndarray("uint8", shape=(None,))  # type: ignore[valid-type]
    sha256: Sha256

    @model_validator(mode="after")
    def _size(self) -> CheckpointChunk:
        if self.data.size > MAX_CHECKPOINT_CHUNK_BYTES:
            raise ValueError(f"a chunk carries at most {MAX_CHECKPOINT_CHUNK_BYTES} bytes, got {self.data.size}")
        return self


class CheckpointRelease(Message):
    """The asker is done with a snapshot (copied, or given up): the peer deletes it now rather
    than when it has been idle for a while."""

    schema_name: ClassVar[str] = "geometry.checkpoint_release"
    schema_version: ClassVar[int] = 1

    snapshot_id: SnapshotId
