"""The tile store: a map on disk as a mapping tile key -> compressed tile, in an LMDB environment.

After zarr's store/codec split (design.md section 10): a tile is a key (:func:`~openfusion.mapping.tiles.tile_key`),
its value the tile's blocks encoded by the codec the store's header names (:data:`CODECS`), so a
store or a codec can change without touching the mapping code.

Why LMDB and zstd (measured by ``bench/bench_tilestore.py`` against SQLite and lz4; README "Scale")
    LMDB (``lmdb``, the binding of the Lightning Memory-Mapped Database) is copy-on-write: a write
    transaction either commits whole or leaves the previous state, with no journal to replay, so
    a ``kill -9`` at any instant leaves the last committed checkpoint loadable (tested by
    ``tests/process/test_tilestore_crash.py``); readers in other processes (``openfusion query
    --map-dir`` on a running geometry's checkpoint) see a consistent snapshot without blocking
    the writer, and ``Environment.copy`` makes a consistent copy for a save elsewhere. SQLite in
    WAL mode has the same guarantees and is in the standard library; measured on tiles of the
    built-in room it wrote and read tiles slower (see the bench) and needs a checkpointing
    journal. zstd (``zstandard``, level 6) on byte-shuffled attributes (blosc's shuffle: every byte
    plane of the float TSDF together) gives the smaller map; lz4 is faster to decode but larger.
    Level 6 against level 3 (measured on a 2-room walk): 5.6 % smaller, 2.3x the encoding time
    (still outside the lock a checkpoint holds); level 9 saves 1 % more for 1.8x again.

Layout (one LMDB environment, a folder holding ``data.mdb`` and ``lock.mdb``; sub-databases)
    ``meta``    ``header`` (JSON: format, version, codec, tile_blocks, volume parameters,
                dictionary scalars, caller meta, per-array shape/dtype/CRC-32) and numpy arrays
                (``.npy`` bytes, no pickle): dictionary, region summaries, key-slot table;
    ``tiles``   tile key -> blob: the map as of the last committed checkpoint;
    ``paged``   epoch (4 bytes) + tile key -> blob: tiles paged out since then
                (:mod:`openfusion.mapping.paging`). Not part of any checkpoint: a reader ignores
                them and a writer that opens the store discards them (they hold state newer than the
                committed header). A checkpoint moves the entries of its epoch and older into
                ``tiles`` in the same transaction that writes its header.

Tile blob: ``OFZT`` magic, format byte, block resolution, block count, then the codec's frame of
the block coordinates (int32) and every attribute in :data:`~openfusion.mapping.storage.RAW_DTYPES`,
each byte-shuffled. zstd and lz4 frames carry a content checksum, so a flipped byte fails to decode
(:class:`~openfusion.mapping.errors.MapFormatError`).
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
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import lmdb
import numpy as np

from openfusion.mapping.errors import MapFormatError, StoreWriteError
from openfusion.mapping.tiles import tile_key, tile_of_key

logger = logging.getLogger(__name__)

STORE_DIR_NAME = "map.ofz"  # the LMDB environment's folder inside a map folder
_MAP_SIZE = 1 << 40  # LMDB's address-space reservation (sparse: the file holds only what is written)
_BLOB = struct.Struct(">4sBBI")  # magic, blob format, block resolution, block count
_MAGIC = b"OFZT"
_BLOB_FORMAT = 1
_EPOCH = struct.Struct(">I")

# Stored attribute order and dtypes: the same as openfusion.mapping.storage (kept here as plain
# numpy so reading a map's summaries imports neither Open3D nor the volume).
TILE_ATTRS: tuple[tuple[str, type, int], ...] = (
    ("tsdf", np.float32, 1),
    ("weight", np.uint16, 1),
    ("color", np.uint16, 3),
    ("key", np.uint16, 1),
    ("conf", np.uint16, 1),
)


class _Zstd:
    """zstd with a content checksum. ``zstandard``'s compressor and decompressor objects are not
    thread-safe (a checkpoint encodes on the service's thread while integration pages tiles out
    on another: sharing one crashed the process), so each thread gets its own."""

    name = "zstd"

    def __init__(self, level: int = 6) -> None:
        import zstandard

        self._zstd = zstandard
        self._level = level
        self._local = threading.local()

    def _pair(self) -> tuple[Any, Any]:
        pair = getattr(self._local, "pair", None)
        if pair is None:
            pair = (self._zstd.ZstdCompressor(level=self._level, write_checksum=True), self._zstd.ZstdDecompressor())
            self._local.pair = pair
        return pair

    def compress(self, data: bytes) -> bytes:
        return self._pair()[0].compress(data)

    def decompress(self, data: bytes) -> bytes:
        return self._pair()[1].decompress(data)


class _Lz4:
    name = "lz4"

    def __init__(self) -> None:
        import lz4.frame

        self._f = lz4.frame

    def compress(self, data: bytes) -> bytes:
        return self._f.compress(data, content_checksum=True)

    def decompress(self, data: bytes) -> bytes:
        return self._f.decompress(data)


#: Codecs a store may name in its header (``zstd`` is written by default).
CODECS = {"zstd": _Zstd, "lz4": _Lz4}
DEFAULT_CODEC = "zstd"


def make_codec(name: str) -> Any:
    if name not in CODECS:
        raise MapFormatError(f"unknown tile codec {name!r} (this build reads {', '.join(sorted(CODECS))})")
    return CODECS[name]()


def _shuffle(arr: np.ndarray) -> bytes:
    a = np.ascontiguousarray(arr)
    return a.view(np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()


def _unshuffle(data: memoryview, dtype: type, count: int) -> np.ndarray:
    itemsize = np.dtype(dtype).itemsize
    planes = np.frombuffer(data, np.uint8, count * itemsize).reshape(itemsize, count)
    return np.ascontiguousarray(planes.T).view(dtype).reshape(-1)


def encode_tile(codec: Any, coords: np.ndarray, raw: dict[str, np.ndarray], res: int) -> bytes:
    """One tile's blob: ``coords`` (n, 3) block coordinates and ``raw`` stored values of those blocks."""
    n = len(coords)
    parts = [_shuffle(np.asarray(coords, np.int32))]
    for name, dtype, _ in TILE_ATTRS:
        parts.append(_shuffle(np.asarray(raw[name], dtype)))
    return _BLOB.pack(_MAGIC, _BLOB_FORMAT, res, n) + codec.compress(b"".join(parts))


def decode_tile(codec: Any, blob: bytes, where: str = "tile") -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``(coords (n, 3) int32, raw arrays)`` of a blob; :class:`MapFormatError` when it is corrupt."""
    if len(blob) < _BLOB.size:
        raise MapFormatError(f"{where}: truncated tile ({len(blob)} bytes)")
    magic, fmt, res, n = _BLOB.unpack_from(blob)
    if magic != _MAGIC or fmt != _BLOB_FORMAT:
        raise MapFormatError(f"{where}: not a tile of this format (magic {magic!r}, format {fmt})")
    try:
        payload = memoryview(codec.decompress(bytes(blob[_BLOB.size :])))
    except Exception as exc:  # every codec raises its own error class for a corrupt frame
        raise MapFormatError(f"{where}: corrupt tile ({type(exc).__name__}: {exc})") from exc
    nvox = n * res**3
    sizes = [n * 3 * 4] + [nvox * ch * np.dtype(dt).itemsize for _, dt, ch in TILE_ATTRS]
    if len(payload) != sum(sizes):
        raise MapFormatError(f"{where}: tile holds {len(payload)} bytes, expected {sum(sizes)} for {n} blocks")
    off = 0
    coords = _unshuffle(payload[off : off + sizes[0]], np.int32, n * 3).reshape(n, 3)
    off += sizes[0]
    raw: dict[str, np.ndarray] = {}
    for (name, dtype, ch), size in zip(TILE_ATTRS, sizes[1:], strict=True):
        arr = _unshuffle(payload[off : off + size], dtype, nvox * ch)
        raw[name] = arr.reshape((n, res, res, res) + ((3,) if ch == 3 else ()))
        off += size
    return coords, raw


def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def _crc(arr: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(arr).view(np.uint8).reshape(-1)) & 0xFFFFFFFF


def is_store(path: str | os.PathLike[str]) -> bool:
    """``path`` is a tile store folder (holds an LMDB ``data.mdb``)."""
    return (Path(path) / "data.mdb").is_file()


class TileStore:
    """One map's tile store (module docstring). Thread-safe as LMDB is: one writer at a time
    (others wait), readers never wait.

    ``readonly``: for readers of a saved map (never writes, ignores ``paged``). A writable store
    discards its ``paged`` entries on open (state newer than its last checkpoint)."""

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
        self._paged = self.env.open_db(b"paged", create=not readonly)
        header = self.read_header()
        self.codec_name = str(header.get("codec", codec)) if header else codec
        self.codec = make_codec(self.codec_name)
        if not readonly:
            self.discard_paged()

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
    def read_header(self) -> dict[str, Any] | None:
        """The header of the last committed checkpoint (None for a store never committed)."""
        with self.env.begin(db=self._meta) as txn:
            raw = txn.get(b"header")
        if raw is None:
            return None
        try:
            return json.loads(bytes(raw).decode())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise MapFormatError(f"{self.path}: unreadable header ({exc})") from exc

    def read_arrays(self, names: list[str], header: dict[str, Any]) -> dict[str, np.ndarray]:
        """Arrays of the last checkpoint, each checked against the header's shape, dtype and CRC-32."""
        specs = header.get("arrays", {})
        out: dict[str, np.ndarray] = {}
        with self.env.begin(db=self._meta) as txn:
            for name in names:
                raw = txn.get(b"array/" + name.encode())
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
    def get(self, tile: tuple[int, int, int], epoch: int = -1) -> bytes | None:
        """The blob of ``tile``: the paged entry of ``epoch`` (>= 0), else the committed one."""
        key = tile_key(tile)
        with self.env.begin() as txn:
            if epoch >= 0:
                blob = txn.get(_EPOCH.pack(epoch) + key, db=self._paged)
                if blob is not None:
                    return bytes(blob)
            blob = txn.get(key, db=self._tiles)
        return None if blob is None else bytes(blob)

    def put_paged(self, epoch: int, tile: tuple[int, int, int], blob: bytes) -> None:
        """Keep a tile paged out in ``epoch`` (not durable until a checkpoint commits it)."""
        try:
            with self.env.begin(write=True, db=self._paged) as txn:
                txn.put(_EPOCH.pack(epoch) + tile_key(tile), blob)
        except lmdb.Error as exc:
            raise StoreWriteError(f"{self.path}: could not page out tile {tile}: {exc}") from exc

    def discard_paged(self) -> int:
        """Drop every paged entry (a writer opening the store: they are newer than its checkpoint)."""
        with self.env.begin(write=True) as txn:
            n = txn.stat(self._paged)["entries"]
            if n:
                txn.drop(self._paged, delete=False)
        if n:
            logger.info("%s: discarded %d tiles paged out after the last checkpoint", self.path, n)
        return int(n)

    def committed_tiles(self) -> list[tuple[int, int, int]]:
        with self.env.begin(db=self._tiles) as txn:
            return [tile_of_key(bytes(k)) for k in txn.cursor().iternext(keys=True, values=False)]

    def iter_committed(self) -> Iterator[tuple[tuple[int, int, int], bytes]]:
        """Every committed tile with its blob, in key order (one read transaction)."""
        with self.env.begin(db=self._tiles) as txn:
            for k, v in txn.cursor():
                yield tile_of_key(bytes(k)), bytes(v)

    def commit(
        self,
        *,
        upto_epoch: int,
        blobs: dict[tuple[int, int, int], bytes],
        header: dict[str, Any],
        arrays: dict[str, np.ndarray],
        removed: list[tuple[int, int, int]] | None = None,
    ) -> None:
        """One checkpoint, atomically: the paged entries of epochs <= ``upto_epoch`` become
        committed tiles, then ``blobs`` (tiles as of the checkpoint) overwrite theirs, ``removed``
        tiles are deleted, and the header and arrays replace the previous ones."""
        if self.readonly:
            raise MapFormatError(f"{self.path}: the store is open read-only")
        header = dict(header)
        header["codec"] = self.codec_name
        header["arrays"] = {n: {"shape": list(a.shape), "dtype": a.dtype.str, "crc32": _crc(a)} for n, a in arrays.items()}
        try:
            self._commit(upto_epoch, blobs, header, arrays, removed)
        except lmdb.Error as exc:
            raise StoreWriteError(f"{self.path}: checkpoint not written: {exc}") from exc

    def _commit(self, upto_epoch: int, blobs: dict[tuple[int, int, int], bytes], header: dict[str, Any],
                arrays: dict[str, np.ndarray], removed: list[tuple[int, int, int]] | None) -> None:
        with self.env.begin(write=True) as txn:
            moved: list[bytes] = []
            cur = txn.cursor(db=self._paged)
            best: dict[bytes, bytes] = {}
            for k, v in cur:
                k = bytes(k)
                epoch = _EPOCH.unpack_from(k)[0]
                if epoch <= upto_epoch:
                    best[k[_EPOCH.size :]] = bytes(v)  # keys sort by epoch: the newest wins
                    moved.append(k)
            for key, v in best.items():
                txn.put(key, v, db=self._tiles)
            for k in moved:
                txn.delete(k, db=self._paged)
            for tile, blob in blobs.items():
                txn.put(tile_key(tile), blob, db=self._tiles)
            for tile in removed or ():
                txn.delete(tile_key(tile), db=self._tiles)
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
            with TileStore(tmp) as copy:  # writable open drops the paged entries of the copy
                copy.env.sync(True)
            install_store(tmp, target)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return target


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
    _fsync_dir(target.parent)
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


def _fsync_dir(folder: Path) -> None:
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
