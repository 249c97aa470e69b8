"""Tile blobs: one tile's blocks as bytes, encoded by a named codec, and back.

The value of a tile in the tile store (:mod:`openfusion.mapping.tilestore`) and of a page-out
(:mod:`openfusion.mapping.paging`). A blob names its own format; the codec (:data:`CODECS`) is
named by the store's header, so a store can change codec without touching the mapping code. Why
zstd at level 6 over lz4 (and LMDB over SQLite): :mod:`openfusion.mapping.tilestore`, measured
by ``bench/bench_tilestore.py`` and ``bench/bench_codec_layout.py``.

Tile blob: ``OFZT`` magic, format byte, block resolution, block count, then the codec's frame of
the tile's arrays, each byte-shuffled. Blob format 2 (written since issue 33's map-size work) holds
the block coordinates (int32), the weights (uint16, every voxel), a bit per *observed* voxel
(weight > 0) saying whether its TSDF is exactly 1.0 (free space in front of a surface), the TSDF
of the other observed voxels (float32), the colours of the observed voxels, and every voxel's
key slot and confidence: an unobserved voxel's TSDF and colour are 0 (Open3D zero-fills blocks;
paging zeroes freed ones), so leaving them out loses nothing. Measured on the 4-room walk of the
synthetic building (``bench/bench_codec_layout.py``): 10.7 % smaller than format 1 (every
attribute of every voxel) and 30 % faster to encode. A tile where an unobserved voxel holds a
value (none seen in practice) is written in format 1, which is still read. zstd and lz4 frames
carry a content checksum, so a flipped byte fails to decode (:class:`~openfusion.mapping.errors.MapFormatError`).
"""

from __future__ import annotations

import struct
import threading
from typing import Any

import numpy as np

from openfusion.mapping.errors import MapFormatError

_BLOB = struct.Struct(">4sBBI")  # magic, blob format, block resolution, block count
_MAGIC = b"OFZT"
_DENSE_FORMAT = 1  # every attribute of every voxel (still read; written when format 2 cannot hold a tile)
_OBSERVED_FORMAT = 2  # unobserved voxels' TSDF and colour left out (module docstring)


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


def encode_tile(codec: Any, coords: np.ndarray, raw: dict[str, np.ndarray], res: int, *, dense: bool = False) -> bytes:
    """One tile's blob: ``coords`` (n, 3) block coordinates and ``raw`` stored values of those blocks
    (blob format 2, or 1 when an unobserved voxel holds a TSDF or colour: module docstring;
    ``dense``: format 1 always, what ``bench/bench_codec_layout.py`` compares with)."""
    n = len(coords)
    weight = np.asarray(raw["weight"], np.uint16).reshape(-1)
    tsdf = np.asarray(raw["tsdf"], np.float32).reshape(-1)
    color = np.asarray(raw["color"], np.uint16).reshape(-1, 3)
    observed = weight > 0
    if dense or tsdf[~observed].any() or color[~observed].any():
        parts = [_shuffle(np.asarray(coords, np.int32))]
        for name, dtype, _ in TILE_ATTRS:
            parts.append(_shuffle(np.asarray(raw[name], dtype)))
        return _BLOB.pack(_MAGIC, _DENSE_FORMAT, res, n) + codec.compress(b"".join(parts))
    seen_tsdf = tsdf[observed]
    free = seen_tsdf == np.float32(1.0)
    parts = [
        _shuffle(np.asarray(coords, np.int32)),
        _shuffle(weight),
        np.packbits(free).tobytes(),
        _shuffle(seen_tsdf[~free]),
        _shuffle(color[observed]),
        _shuffle(np.asarray(raw["key"], np.uint16)),
        _shuffle(np.asarray(raw["conf"], np.uint16)),
    ]
    return _BLOB.pack(_MAGIC, _OBSERVED_FORMAT, res, n) + codec.compress(b"".join(parts))


def decode_tile(codec: Any, blob: bytes, where: str = "tile") -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``(coords (n, 3) int32, raw arrays)`` of a blob; :class:`MapFormatError` when it is corrupt."""
    if len(blob) < _BLOB.size:
        raise MapFormatError(f"{where}: truncated tile ({len(blob)} bytes)")
    magic, fmt, res, n = _BLOB.unpack_from(blob)
    if magic != _MAGIC or fmt not in (_DENSE_FORMAT, _OBSERVED_FORMAT):
        raise MapFormatError(f"{where}: not a tile of this format (magic {magic!r}, format {fmt})")
    try:
        payload = memoryview(codec.decompress(bytes(blob[_BLOB.size :])))
    except Exception as exc:  # every codec raises its own error class for a corrupt frame
        raise MapFormatError(f"{where}: corrupt tile ({type(exc).__name__}: {exc})") from exc
    if fmt == _DENSE_FORMAT:
        return _decode_dense(payload, res, n, where)
    return _decode_observed(payload, res, n, where)


def _decode_dense(payload: memoryview, res: int, n: int, where: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
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


class _Reader:
    """Consecutive arrays of a payload, each checked against what is left."""

    def __init__(self, payload: memoryview, where: str) -> None:
        self.payload, self.where, self.off = payload, where, 0

    def take(self, nbytes: int) -> memoryview:
        if self.off + nbytes > len(self.payload):
            raise MapFormatError(f"{self.where}: tile is truncated ({len(self.payload)} bytes)")
        out = self.payload[self.off : self.off + nbytes]
        self.off += nbytes
        return out

    def array(self, dtype: type, count: int) -> np.ndarray:
        return _unshuffle(self.take(count * np.dtype(dtype).itemsize), dtype, count)


def _decode_observed(payload: memoryview, res: int, n: int, where: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    nvox = n * res**3
    r = _Reader(payload, where)
    coords = r.array(np.int32, n * 3).reshape(n, 3)
    weight = r.array(np.uint16, nvox)
    observed = weight > 0
    seen = int(observed.sum())
    free = np.unpackbits(np.frombuffer(r.take((seen + 7) // 8), np.uint8), count=seen).astype(bool)
    tsdf = np.zeros(nvox, np.float32)
    seen_tsdf = np.ones(seen, np.float32)
    seen_tsdf[~free] = r.array(np.float32, seen - int(free.sum()))
    tsdf[observed] = seen_tsdf
    color = np.zeros((nvox, 3), np.uint16)
    color[observed] = r.array(np.uint16, seen * 3).reshape(seen, 3)
    key = r.array(np.uint16, nvox)
    conf = r.array(np.uint16, nvox)
    if r.off != len(payload):
        raise MapFormatError(f"{where}: tile holds {len(payload)} bytes, expected {r.off} for {n} blocks")
    shape = (n, res, res, res)
    return coords, {"tsdf": tsdf.reshape(shape), "weight": weight.reshape(shape), "color": color.reshape(shape + (3,)),
                    "key": key.reshape(shape), "conf": conf.reshape(shape)}
