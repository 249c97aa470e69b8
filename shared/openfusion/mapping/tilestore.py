"""The tile store: a map on disk as a mapping tile key -> compressed tile, in an LMDB environment.

After zarr's store/codec split (design.md section 10): a tile is a key (:func:`~openfusion.mapping.tiles.tile_key`),
its value the tile's blocks encoded by the codec the store's header names (:data:`CODECS`), so a
store or a codec can change without touching the mapping code.

Why LMDB and zstd (measured by ``bench/bench_tilestore.py`` against SQLite and lz4; README "Scale")
    LMDB (``lmdb``, the binding of the Lightning Memory-Mapped Database) is copy-on-write: a write
    transaction either commits whole or leaves the previous state, with no journal to replay, so
    a ``kill -9`` at any instant leaves the last committed checkpoint loadable (tested by
    ``tests/process/test_tilestore_crash.py`` and, for the geometry service,
    ``tests/process/test_geometry_checkpoint_kill.py``); readers in other processes (``openfusion
    query --map-dir`` on a running geometry's checkpoint) see a consistent snapshot without
    blocking the writer, and ``Environment.copy`` makes a consistent copy for a save elsewhere.
    SQLite in WAL mode has the same guarantees and is in the standard library; measured on tiles
    of the built-in room it wrote and read tiles slower (see the bench) and needs a checkpointing
    journal. zstd (``zstandard``, level 6) on byte-shuffled attributes (blosc's shuffle: every byte
    plane of the float TSDF together) gives the smaller map; lz4 is faster to decode but larger.
    Level 6 against level 3 (measured on a 2-room walk): 5.6 % smaller, 2.3x the encoding time
    (still outside the lock a checkpoint holds); level 9 saves 1 % more for 1.8x again.

Layout (one LMDB environment, a folder holding ``data.mdb`` and ``lock.mdb``; sub-databases)
    ``meta``    ``header`` (JSON: format, version, codec, tile_blocks, volume parameters,
                dictionary scalars, caller meta, the committed ``generation``, per-array
                shape/dtype/CRC-32) and numpy arrays (``.npy`` bytes, no pickle): dictionary,
                region summaries, key-slot table, tile index;
    ``tiles``   tile key (12 bytes) + generation (4 bytes, big-endian) -> blob. The map of the
                last committed checkpoint is, per tile, its entry of the newest generation not
                above the header's ``generation``. A writer writes into the next generation
                (tiles paged out, the slices of a checkpoint being written: :mod:`openfusion.mapping.paging`),
                so nothing committed is ever overwritten; a checkpoint's last transaction writes
                the header naming that generation and deletes the entries it superseded. Entries
                above the header's generation are not part of any checkpoint: a reader ignores them
                and a writer that opens the store deletes them (state of a writer that died).

Why generations: a checkpoint of a building writes hundreds of tiles; written in slices (each its
own transaction, a bounded amount of memory: LMDB holds a write transaction's dirty pages in memory
until it commits) and committed by one small last transaction, it never holds a whole checkpoint's
tiles, raw or encoded, at once. Entries of the generation being built are invisible to readers of
the committed one, so crash safety is the one-transaction kind.

Tile blob: the codec's frame of one tile's arrays, byte-shuffled (formats 1 and 2, the codecs and
why: :mod:`openfusion.mapping.tilecodec`, whose names are re-exported here).
"""

from __future__ import annotations

import io
import json
import logging
import os
import shutil
import struct
import tempfile
import threading
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import lmdb
import numpy as np

from openfusion.mapping.errors import MapFormatError, StoreWriteError
from openfusion.mapping.tilecodec import CODECS as CODECS
from openfusion.mapping.tilecodec import DEFAULT_CODEC, make_codec
from openfusion.mapping.tilecodec import TILE_ATTRS as TILE_ATTRS
from openfusion.mapping.tilecodec import decode_tile as decode_tile
from openfusion.mapping.tilecodec import encode_tile as encode_tile
from openfusion.mapping.tiles import tile_key, tile_of_key

logger = logging.getLogger(__name__)

STORE_DIR_NAME = "map.ofz"  # the LMDB environment's folder inside a map folder
_MAP_SIZE = 1 << 40  # LMDB's address-space reservation (sparse: the file holds only what is written)
_GEN = struct.Struct(">I")
_TILE_KEY_BYTES = 12
_NEWEST = 0xFFFFFFFF  # a generation above every real one


def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def _crc(arr: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(arr).view(np.uint8).reshape(-1)) & 0xFFFFFFFF


def is_store(path: str | os.PathLike[str]) -> bool:
    """``path`` is a tile store folder (holds an LMDB ``data.mdb``)."""
    return (Path(path) / "data.mdb").is_file()


def _entry_key(tile: tuple[int, int, int], generation: int) -> bytes:
    return tile_key(tile) + _GEN.pack(generation)


def _split_entry(key: bytes) -> tuple[bytes, int]:
    if len(key) != _TILE_KEY_BYTES + _GEN.size:
        raise MapFormatError(f"a tile entry key is {_TILE_KEY_BYTES + _GEN.size} bytes (tile and generation), got "
                             f"{len(key)}: a store of another layout")
    return key[:_TILE_KEY_BYTES], _GEN.unpack_from(key, _TILE_KEY_BYTES)[0]


def header_generation(header: dict[str, Any] | None) -> int:
    """The generation a header commits (0: no checkpoint yet)."""
    return int(header.get("generation", 0)) if header else 0


class TileStore:
    """One map's tile store (module docstring). Thread-safe as LMDB is: one writer at a time
    (others wait), readers never wait.

    ``readonly``: for readers of a saved map (never writes; reads the committed generation). A
    writable store deletes the entries above its committed generation on open (a writer that died
    left them) and writes into :attr:`generation`."""

    def __init__(self, path: str | os.PathLike[str], *, readonly: bool = False, codec: str = DEFAULT_CODEC) -> None:
        self.path = Path(path)
        self.readonly = readonly
        if readonly and not is_store(self.path):
            raise MapFormatError(f"{self.path}: no tile store there")
        if not readonly:
            self.path.mkdir(parents=True, exist_ok=True)
        self.env = _EnvRegistry.acquire(self.path, readonly)
        self._closed = False
        self._meta = self.env.open_db(b"meta", create=not readonly)
        self._tiles = self.env.open_db(b"tiles", create=not readonly)
        header = self.read_header()
        self.codec_name = str(header.get("codec", codec)) if header else codec
        self.codec = make_codec(self.codec_name)
        self.committed_generation = header_generation(header)
        #: The generation a writer's tiles go to (the checkpoint being built).
        self.generation = self.committed_generation + 1
        #: Entries a writable open deleted (above the committed generation: a writer that died).
        self.discarded_on_open = 0 if readonly else self.discard_uncommitted()

    # ------------------------------------------------------------------ life
    def close(self) -> None:
        if not self._closed:
            self._closed = True
            _EnvRegistry.release(self.path)

    def __enter__(self) -> TileStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ header and arrays
    def read_header(self, txn: Any = None) -> dict[str, Any] | None:
        """The header of the last committed checkpoint (None for a store never committed)."""
        if txn is None:
            with self.env.begin(db=self._meta) as own:
                return self.read_header(own)
        raw = txn.get(b"header", db=self._meta)
        if raw is None:
            return None
        try:
            return json.loads(bytes(raw).decode())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise MapFormatError(f"{self.path}: unreadable header ({exc})") from exc

    def read_arrays(self, names: list[str], header: dict[str, Any], txn: Any = None) -> dict[str, np.ndarray]:
        """Arrays of the last checkpoint, each checked against the header's shape, dtype and CRC-32
        (``txn``: read in that transaction, e.g. the one the header came from)."""
        if txn is None:
            with self.env.begin(db=self._meta) as own:
                return self.read_arrays(names, header, own)
        specs = header.get("arrays", {})
        out: dict[str, np.ndarray] = {}
        for name in names:
            raw = txn.get(b"array/" + name.encode(), db=self._meta)
            if raw is None or name not in specs:
                raise MapFormatError(f"{self.path}: array {name!r} is missing")
            try:
                arr = np.load(io.BytesIO(bytes(raw)), allow_pickle=False)
            except (ValueError, OSError, EOFError) as exc:
                raise MapFormatError(f"{self.path}: array {name!r} is unreadable ({exc})") from exc
            spec = specs[name]
            if list(arr.shape) != list(spec["shape"]) or arr.dtype.str != spec["dtype"]:
                raise MapFormatError(f"{self.path}: array {name!r} is {arr.dtype.str} {arr.shape}, header says "
                                     f"{spec['dtype']} {tuple(spec['shape'])}")
            if _crc(arr) != int(spec["crc32"]):
                raise MapFormatError(f"{self.path}: array {name!r} fails its CRC-32 check (corrupt store)")
            out[name] = arr
        return out

    # ------------------------------------------------------------------ tiles
    def _newest(self, txn: Any, tile: tuple[int, int, int], limit: int) -> tuple[bytes, bytes] | None:
        """(entry key, blob) of ``tile``'s newest entry of a generation <= ``limit``."""
        prefix = tile_key(tile)
        cur = txn.cursor(db=self._tiles)
        found = cur.set_range(prefix + _GEN.pack(min(limit + 1, _NEWEST)))
        if not (cur.prev() if found else cur.last()):
            return None
        key = bytes(cur.key())
        if key[:_TILE_KEY_BYTES] != prefix or _split_entry(key)[1] > limit:
            return None
        return key, bytes(cur.value())

    def get(self, tile: tuple[int, int, int]) -> bytes | None:
        """The blob of ``tile``: a writer's newest (its own uncommitted writes included); a
        read-only store's as of the checkpoint committed when the read begins."""
        with self.env.begin() as txn:
            limit = _NEWEST if not self.readonly else header_generation(self.read_header(txn))
            got = self._newest(txn, tile, limit)
        return None if got is None else got[1]

    def put(self, tile: tuple[int, int, int], blob: bytes) -> None:
        """Write a tile into the generation being built (a page-out): not durable until a
        checkpoint commits that generation."""
        self.put_many({tile: blob})

    def put_many(self, blobs: dict[tuple[int, int, int], bytes], *, keep: Any = None) -> int:
        """Write tiles into the generation being built, in one transaction; ``keep(tile)``, asked
        inside the transaction (other writers wait), can skip a tile. Returns the tiles written."""
        if self.readonly:
            raise MapFormatError(f"{self.path}: the store is open read-only")
        written = 0
        try:
            with self.env.begin(write=True, db=self._tiles) as txn:
                generation = self.generation
                for tile, blob in blobs.items():
                    if keep is None or keep(tile):
                        txn.put(_entry_key(tile, generation), blob)
                        written += 1
        except lmdb.Error as exc:
            raise StoreWriteError(f"{self.path}: could not write {len(blobs)} tiles: {exc}") from exc
        return written

    def discard_uncommitted(self) -> int:
        """Delete every entry above the committed generation (a writer opening the store: a writer
        before it died after writing them)."""
        limit = self.committed_generation
        with self.env.begin(write=True, db=self._tiles) as txn:
            stale = [bytes(k) for k in txn.cursor().iternext(keys=True, values=False) if _split_entry(bytes(k))[1] > limit]
            for k in stale:
                txn.delete(k)
        if stale:
            logger.info("%s: discarded %d tiles written after the last checkpoint", self.path, len(stale))
        return len(stale)

    def _committed_entries(self, txn: Any, limit: int) -> Iterator[tuple[bytes, bytes]]:
        """(entry key, value) of every tile's newest entry <= ``limit``, in tile order."""
        best: tuple[bytes, bytes] | None = None
        for k, v in txn.cursor(db=self._tiles):
            key = bytes(k)
            if _split_entry(key)[1] > limit:
                continue
            if best is not None and best[0][:_TILE_KEY_BYTES] != key[:_TILE_KEY_BYTES]:
                yield best
            best = (key, v)
        if best is not None:
            yield best

    def committed_tiles(self) -> list[tuple[int, int, int]]:
        with self.env.begin() as txn:
            limit = header_generation(self.read_header(txn))
            return [tile_of_key(k[:_TILE_KEY_BYTES]) for k, _ in self._committed_entries(txn, limit)]

    def iter_committed(self) -> Iterator[tuple[tuple[int, int, int], bytes]]:
        """Every committed tile with its blob, in key order, as of the checkpoint committed when the
        iteration begins (one read transaction)."""
        with self.env.begin() as txn:
            limit = header_generation(self.read_header(txn))
            for k, v in self._committed_entries(txn, limit):
                yield tile_of_key(k[:_TILE_KEY_BYTES]), bytes(v)

    def read_committed(self, names: Callable[[dict[str, Any]], list[str]]) -> tuple[dict[str, Any] | None, dict[str, np.ndarray], Iterator[tuple[tuple[int, int, int], bytes]]]:
        """``(header, arrays, tiles)`` of one committed checkpoint, all from one read transaction
        (a writer committing meanwhile changes none of them); ``names(header)`` picks the arrays.
        The tile iterator holds the transaction until it is exhausted or closed."""
        txn = self.env.begin()
        try:
            header = self.read_header(txn)
            arrays = self.read_arrays(names(header), header, txn) if header is not None else {}
        except BaseException:
            txn.abort()
            raise

        def tiles() -> Iterator[tuple[tuple[int, int, int], bytes]]:
            try:
                for k, v in self._committed_entries(txn, header_generation(header)):
                    yield tile_of_key(k[:_TILE_KEY_BYTES]), bytes(v)
            finally:
                txn.abort()

        return header, arrays, tiles()

    def committed_entry_key(self, tile: tuple[int, int, int]) -> bytes | None:
        """The LMDB key of ``tile``'s committed entry (tests that damage a stored tile use it)."""
        with self.env.begin() as txn:
            got = self._newest(txn, tile, header_generation(self.read_header(txn)))
        return None if got is None else got[0]

    def commit(
        self,
        *,
        blobs: dict[tuple[int, int, int], bytes],
        header: dict[str, Any],
        arrays: dict[str, np.ndarray],
        generation: int | None = None,
    ) -> None:
        """Commit ``generation`` (default: :attr:`generation`) in one transaction: ``blobs`` are
        written into it, the header naming it and the arrays replace the previous ones, and every
        entry it supersedes (an older generation of a tile it holds) is deleted. Entries of later
        generations (tiles paged out meanwhile) are kept. The next writes go to the generation
        after the highest committed or begun one."""
        if self.readonly:
            raise MapFormatError(f"{self.path}: the store is open read-only")
        generation = self.generation if generation is None else int(generation)
        header = dict(header)
        header["codec"] = self.codec_name
        header["generation"] = generation
        header["arrays"] = {n: {"shape": list(a.shape), "dtype": a.dtype.str, "crc32": _crc(a)} for n, a in arrays.items()}
        try:
            self._commit(generation, blobs, header, arrays)
        except lmdb.Error as exc:
            raise StoreWriteError(f"{self.path}: checkpoint not written: {exc}") from exc
        self.committed_generation = generation
        self.generation = max(self.generation, generation + 1)

    def begin_generation(self) -> int:
        """Start the next generation (later writes go there); returns the one before it, which a
        checkpoint then commits while page-outs go on into the new one."""
        building = self.generation
        self.generation = building + 1
        return building

    def _commit(self, generation: int, blobs: dict[tuple[int, int, int], bytes], header: dict[str, Any],
                arrays: dict[str, np.ndarray]) -> None:
        with self.env.begin(write=True) as txn:
            for tile, blob in blobs.items():
                txn.put(_entry_key(tile, generation), blob, db=self._tiles)
            # Superseded entries: per tile, every entry older than its newest one <= generation.
            doomed: list[bytes] = []
            group: list[bytes] = []
            for k in txn.cursor(db=self._tiles).iternext(keys=True, values=False):
                key = bytes(k)
                if group and group[-1][:_TILE_KEY_BYTES] != key[:_TILE_KEY_BYTES]:
                    doomed.extend(_superseded(group, generation))
                    group = []
                group.append(key)
            doomed.extend(_superseded(group, generation))
            for key in doomed:
                txn.delete(key, db=self._tiles)
            old = [bytes(k) for k in txn.cursor(db=self._meta).iternext(keys=True, values=False) if bytes(k).startswith(b"array/")]
            for k in old:
                txn.delete(k, db=self._meta)
            for name, arr in arrays.items():
                txn.put(b"array/" + name.encode(), _npy_bytes(arr), db=self._meta)
            txn.put(b"header", json.dumps(header).encode(), db=self._meta)

    def size_bytes(self) -> int:
        """Bytes the store's data file takes on disk."""
        try:
            return int((self.path / "data.mdb").stat().st_blocks * 512)
        except OSError:
            return 0

    def copy_to(self, target: str | os.PathLike[str]) -> Path:
        """A compacted, consistent copy of the committed state at ``target`` (a new folder),
        written next to it and renamed into place; an older store there is replaced."""
        target = Path(target)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
        try:
            self.env.copy(str(tmp), compact=True)
            with TileStore(tmp) as copy:  # a writable open drops the copy's uncommitted entries
                dropped = copy.discarded_on_open
                copy.env.sync(True)
            if dropped:  # their pages are free now: compact once more so the map holds none
                again = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
                try:
                    with TileStore(tmp, readonly=True) as copy:
                        copy.env.copy(str(again), compact=True)
                finally:
                    shutil.rmtree(tmp, ignore_errors=True)
                tmp = again
            install_store(tmp, target)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return target


def _superseded(group: list[bytes], generation: int) -> list[bytes]:
    """Entry keys of one tile (sorted by generation) that its newest entry <= ``generation`` supersedes."""
    upto = [k for k in group if _split_entry(k)[1] <= generation]
    return upto[:-1]


class _EnvRegistry:
    """LMDB forbids opening one environment twice in a process: every :class:`TileStore` of a
    folder shares one ``Environment`` (a reader of a store the geometry service writes in the same
    process, as tests do, reads through the writer's)."""

    _envs: dict[str, list[Any]] = {}  # realpath -> [env, refcount, readonly]
    _lock = threading.Lock()

    @classmethod
    def acquire(cls, path: Path, readonly: bool) -> lmdb.Environment:
        key = os.path.realpath(path)
        with cls._lock:
            entry = cls._envs.get(key)
            if entry is not None:
                if entry[2] and not readonly:
                    raise MapFormatError(f"{path}: the tile store is open read-only in this process")
                entry[1] += 1
                return entry[0]
            try:
                env = lmdb.open(key, map_size=_MAP_SIZE, max_dbs=4, readonly=readonly, lock=True,
                                subdir=True, create=not readonly, max_readers=256)
            except lmdb.ReadonlyError:  # a read-only folder: read without the reader lock table
                env = lmdb.open(key, map_size=_MAP_SIZE, max_dbs=4, readonly=True, lock=False)
            except lmdb.Error as exc:
                raise MapFormatError(f"{path}: cannot open the tile store ({exc})") from exc
            cls._envs[key] = [env, 1, readonly]
            return env

    @classmethod
    def release(cls, path: Path) -> None:
        key = os.path.realpath(path)
        with cls._lock:
            entry = cls._envs.get(key)
            if entry is None:
                return
            entry[1] -= 1
            if entry[1] <= 0:
                del cls._envs[key]
                entry[0].close()


def install_store(tmp: Path, target: Path) -> None:
    """Put the store folder ``tmp`` at ``target``: an older store there is renamed aside first and
    removed after (a crash in between leaves one of them whole; :func:`find_store` takes either)."""
    old = target.with_name(target.name + ".old")
    if old.exists():
        shutil.rmtree(old)
    if target.exists():
        os.replace(target, old)
    os.replace(tmp, target)
    fsync_dir(target.parent)
    if old.exists():
        shutil.rmtree(old, ignore_errors=True)


def find_store(folder: Path) -> Path | None:
    """The tile store of a map folder (``folder/map.ofz``, or the ``.old`` one a crash left), or None."""
    for name in (STORE_DIR_NAME, STORE_DIR_NAME + ".old"):
        if is_store(folder / name):
            return folder / name
    if is_store(folder):
        return folder
    return None


def fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (fsync of the folder; a no-op where that is not supported)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        logger.debug("fsync of folder %s not supported", folder)
    finally:
        os.close(fd)
