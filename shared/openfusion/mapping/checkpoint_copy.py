"""A checkpoint copied between two geometry processes as files: the library half of a replica's
copy of its peer's checkpoint (docs/SHARDS.md, "Replicas"; the bus half is
:mod:`openfusion.services.geometry.peer_copy`). No bus here: tests call every step directly.

Serving side (the peer)
    :func:`snapshot_checkpoint` makes a **snapshot**: a compacted, consistent copy of the newest
    *committed* checkpoint of a checkpoint folder (:meth:`TileStore.copy_to`, LMDB's own
    ``Environment.copy``), in a folder of its own, and lists its files (names relative to it,
    sizes, SHA-256 digests; LMDB's ``lock.mdb``, a reader table and no data, is left out).
    :func:`read_chunk` reads a bounded byte range of one of them.

    Copy-on-serve, not pinning: an LMDB ``data.mdb`` is not a consistent file while its writer
    goes on (meta pages and freed pages change under a reader), so a pinned read transaction can
    serve tiles but never the file; serving tiles one by one would hold that transaction, and so
    every page the writer frees meanwhile, for the whole transfer (minutes over a slow link,
    growing the peer's file). The snapshot costs one compacted copy on the peer's disk (the
    map's size, without free pages or tiles paged out after the checkpoint) and the time of a
    local copy, and it is immutable: a chunk asked twice is the same bytes, and the digests are
    known before the first chunk leaves. A half-written checkpoint is never served: the copy holds
    only what the store's header commits (:meth:`TileStore.copy_to` drops later generations).

Receiving side (the replica)
    :class:`CopyReceiver` writes the chunks of a listing into a fresh folder, checking each
    chunk's digest and place (the next offset of its file, never past its size) and, at the end,
    every file's size and digest. :func:`verify_store` opens the copy as a map (its header and
    every array's CRC-32) before :func:`install_copy` puts it in the checkpoint folder (renamed
    into place: :func:`~openfusion.mapping.tilestore.install_store`). Anything wrong raises
    :class:`CheckpointCopyError` and the caller removes the folder: a half copy is never loaded.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lmdb

from openfusion.mapping.errors import MapFormatError, MappingError
from openfusion.mapping.mapstore import check_header
from openfusion.mapping.tilestore import STORE_DIR_NAME, TileStore, find_store, install_store

#: LMDB's lock file: a table of readers, rebuilt by whoever opens the store; never copied.
LOCK_FILE = "lock.mdb"
_READ_BLOCK = 1 << 20


class CheckpointCopyError(MappingError):
    """A checkpoint copy that cannot be used (no checkpoint to serve, a chunk out of place, a
    digest or size that disagrees, a copy that does not open as a map); ``reason`` is a short code
    for counters and logs (``no_checkpoint``, ``bad_chunk``, ``bad_digest``, ``incomplete``,
    ``bad_map``, ``no_space``, ``bad_name``, ``snapshot_failed``)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class FileEntry:
    """One file of a snapshot: its name relative to the snapshot's folder, size and SHA-256."""

    name: str
    size_bytes: int
    sha256: str


@dataclass
class Snapshot:
    """A served copy of one committed checkpoint (module docstring)."""

    snapshot_id: str
    folder: Path
    files: list[FileEntry]
    last_frame_id: int
    frames_integrated: int
    tiles: int
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def total_bytes(self) -> int:
        return sum(f.size_bytes for f in self.files)

    def file(self, name: str) -> FileEntry:
        for f in self.files:
            if f.name == name:
                return f
        raise CheckpointCopyError("bad_name", f"snapshot {self.snapshot_id} has no file {name!r}")

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_READ_BLOCK):
            h.update(block)
    return h.hexdigest()


def list_files(folder: Path) -> list[FileEntry]:
    """Every file under ``folder`` but LMDB lock files, sorted by name (``map.ofz/data.mdb``)."""
    out = []
    for path in sorted(p for p in Path(folder).rglob("*") if p.is_file() and p.name != LOCK_FILE):
        out.append(FileEntry(path.relative_to(folder).as_posix(), path.stat().st_size, file_sha256(path)))
    return out


def _store_info(store: TileStore) -> dict[str, Any]:
    header = check_header(store, store.read_header())
    meta = dict(header.get("meta") or {})
    tiles = store.read_arrays(["tile_index"], header)["tile_index"] if "tile_index" in header.get("arrays", {}) else None
    last = meta.get("last_frame_id")
    return {"meta": meta, "last_frame_id": -1 if last is None else int(last),
            "frames_integrated": int(meta.get("frames_integrated") or 0),
            "tiles": 0 if tiles is None else int(len(tiles))}


def snapshot_checkpoint(checkpoint_dir: Path, snapshots_dir: Path) -> Snapshot:
    """A snapshot of the newest committed checkpoint in ``checkpoint_dir`` (its tile store), in a
    new folder under ``snapshots_dir``; :class:`CheckpointCopyError` (``no_checkpoint``) when it
    holds no committed tile store (an older ``map.ofz.npz`` checkpoint is not served)."""
    source = find_store(Path(checkpoint_dir))
    if source is None:
        raise CheckpointCopyError("no_checkpoint", f"{checkpoint_dir}: no tile store checkpoint to serve")
    snapshot_id = uuid.uuid4().hex
    folder = Path(snapshots_dir) / snapshot_id
    try:
        with TileStore(source, readonly=True) as store:
            if store.read_header() is None:
                raise CheckpointCopyError("no_checkpoint", f"{checkpoint_dir}: the tile store holds no checkpoint yet")
            store.copy_to(folder / STORE_DIR_NAME)
        with TileStore(folder / STORE_DIR_NAME, readonly=True) as copy:  # what the copy holds, not the source now
            info = _store_info(copy)
        return Snapshot(snapshot_id, folder, list_files(folder), info["last_frame_id"], info["frames_integrated"],
                        info["tiles"], info["meta"])
    except (OSError, lmdb.Error) as exc:  # disk full, a folder it may not write...: said, not a crash
        shutil.rmtree(folder, ignore_errors=True)
        raise CheckpointCopyError("snapshot_failed", f"{checkpoint_dir}: could not snapshot the checkpoint: {exc}") from exc
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise


def read_chunk(snapshot: Snapshot, name: str, offset_bytes: int, length_bytes: int) -> bytes:
    """Bytes ``offset_bytes`` .. ``+ length_bytes`` of file ``name`` of ``snapshot`` (fewer at its
    end); only files the snapshot lists are read."""
    entry = snapshot.file(name)
    if offset_bytes < 0 or length_bytes <= 0 or offset_bytes > entry.size_bytes:
        raise CheckpointCopyError("bad_chunk", f"{name}: bytes {offset_bytes}+{length_bytes} are outside its "
                                  f"{entry.size_bytes} bytes")
    with open(snapshot.folder / entry.name, "rb") as f:
        f.seek(offset_bytes)
        return f.read(length_bytes)


class CopyReceiver:
    """Writes one snapshot's files into ``folder`` (new, empty) chunk by chunk, in order, checking
    each chunk's digest and place and each file's size and digest at the end (module docstring)."""

    def __init__(self, files: list[FileEntry], folder: Path) -> None:
        self.files = {f.name: f for f in files}
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=False)
        self._written = dict.fromkeys(self.files, 0)
        self._hashes = {name: hashlib.sha256() for name in self.files}
        self.bytes_written = 0
        root = self.folder.resolve()
        for name in self.files:
            target = (self.folder / name).resolve()
            if root not in target.parents:
                raise CheckpointCopyError("bad_name", f"checkpoint file name {name!r} points outside the copy")
            target.parent.mkdir(parents=True, exist_ok=True)
            target.touch()

    def next_offset(self, name: str) -> int:
        return self._written[name]

    def done(self, name: str) -> bool:
        return self._written[name] >= self.files[name].size_bytes

    def write(self, name: str, offset_bytes: int, data: bytes | memoryview, sha256: str) -> None:
        """Append one chunk of file ``name``; :class:`CheckpointCopyError` when its digest, place or
        size is wrong (nothing of it is written)."""
        entry = self.files.get(name)
        if entry is None:
            raise CheckpointCopyError("bad_chunk", f"a chunk of {name!r}, which the listing does not name")
        if offset_bytes != self._written[name]:
            raise CheckpointCopyError("bad_chunk", f"{name}: a chunk at byte {offset_bytes}, expected "
                                      f"{self._written[name]}")
        if not data or offset_bytes + len(data) > entry.size_bytes:
            raise CheckpointCopyError("bad_chunk", f"{name}: a chunk of {len(data)} bytes at {offset_bytes} does not "
                                      f"fit its {entry.size_bytes} bytes")
        if hashlib.sha256(data).hexdigest() != sha256:
            raise CheckpointCopyError("bad_digest", f"{name}: the chunk at byte {offset_bytes} fails its SHA-256 "
                                      "digest (corrupt in transit)")
        with open(self.folder / name, "r+b") as f:
            f.seek(offset_bytes)
            f.write(data)
        self._hashes[name].update(data)
        self._written[name] += len(data)
        self.bytes_written += len(data)

    def finish(self) -> None:
        """Every file complete, with the listing's digest, and flushed to disk."""
        for name, entry in self.files.items():
            if self._written[name] != entry.size_bytes:
                raise CheckpointCopyError("incomplete", f"{name}: {self._written[name]} of {entry.size_bytes} bytes "
                                          "copied")
            if self._hashes[name].hexdigest() != entry.sha256:
                raise CheckpointCopyError("bad_digest", f"{name}: the copy fails the listing's SHA-256 digest")
            with open(self.folder / name, "rb+") as f:
                os.fsync(f.fileno())

    def discard(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def verify_store(folder: Path) -> dict[str, Any]:
    """The copy in ``folder`` opens as a map: a committed header of this format, every array of it
    intact (CRC-32); returns what it holds (``last_frame_id``, ``frames_integrated``, ``tiles``,
    ``meta``). :class:`CheckpointCopyError` (``bad_map``) otherwise."""
    store_dir = Path(folder) / STORE_DIR_NAME
    try:
        with TileStore(store_dir, readonly=True) as store:
            header = check_header(store, store.read_header())
            store.read_arrays(sorted(header.get("arrays", {})), header)
            return _store_info(store)
    except MapFormatError as exc:
        raise CheckpointCopyError("bad_map", f"the copied checkpoint does not open as a map: {exc}") from exc


def install_copy(folder: Path, checkpoint_dir: Path) -> Path:
    """Put the verified copy in ``folder`` in ``checkpoint_dir`` as its tile store (an empty
    store there is replaced; renamed into place), and remove ``folder``."""
    target = Path(checkpoint_dir) / STORE_DIR_NAME
    Path(checkpoint_dir).mkdir(parents=True, exist_ok=True)
    install_store(Path(folder) / STORE_DIR_NAME, target)
    shutil.rmtree(folder, ignore_errors=True)
    return target


def free_bytes(folder: Path) -> int:
    """Bytes free on the disk of ``folder`` (or of its nearest existing parent)."""
    path = Path(folder)
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free
