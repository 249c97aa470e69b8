"""Tiles: the unit of scale of the map (design.md section 10). Coordinates, keys, which tiles a view
touches, and which tiles changed since a mark.

A *tile* is a fixed cube of ``tile_blocks``\\ :sup:`3` voxel blocks, named by its integer
coordinates ``(tx, ty, tz) = floor(block / tile_blocks)``. At the default 8 blocks of 8 voxels of
2 cm a tile is 1.28 m on a side. Everything past one room speaks tiles: what is resident and what
is paged out under the memory budget (:mod:`openfusion.mapping.paging`), what a checkpoint writes
(only tiles changed since the last one), what the map on disk holds
(:mod:`openfusion.mapping.tilestore`: tile key -> compressed bytes), and later which geometry shard
owns which part of the map. This module is plain numpy (no Open3D, no store), so a shard router
or a fleet's map merger can use it without the volume.

Vocabulary (after nvblox's blocks and dirty sets)

- :class:`TileGrid` -- tile coordinates of blocks, tile keys (12 bytes, ordered like the
  coordinates, so a store's range scan walks tiles in x, y, z order), tile boxes in metres, the
  tiles a camera view can reach (:meth:`TileGrid.tiles_in_view`).
- :class:`TileVersions` -- a version counter per tile, bumped by every change (integration, a
  semantic update); "dirty since a mark" is ``version > written``. A checkpoint takes the
  versions it writes at one instant and marks exactly those written when it commits, so a change
  made while it writes is still dirty afterwards (never lost between two checkpoints).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

_KEY = struct.Struct(">III")
_BIAS = 1 << 31  # int32 -> uint32 keeping the order (big-endian bytes then sort like the integers)


def tile_key(tile: Iterable[int]) -> bytes:
    """12-byte key of a tile: its coordinates as biased big-endian uint32 (byte order = numeric order)."""
    x, y, z = (int(v) for v in tile)
    return _KEY.pack(x + _BIAS, y + _BIAS, z + _BIAS)


def tile_of_key(key: bytes) -> tuple[int, int, int]:
    """Inverse of :func:`tile_key`; ``ValueError`` for anything but 12 bytes."""
    if len(key) != _KEY.size:
        raise ValueError(f"a tile key is {_KEY.size} bytes, got {len(key)}")
    x, y, z = _KEY.unpack(key)
    return x - _BIAS, y - _BIAS, z - _BIAS


_PACK_BIAS = 1 << 20  # block/tile coordinates within +-1,048,576 (at 16 cm blocks: +-167 km)
#: The 27 offsets of a cell (block, tile) and its 26 neighbours, (0, 0, 0) among them.
NEIGHBOUR_OFFSETS = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)], np.int64)


def pack_coords(coords: np.ndarray) -> np.ndarray:
    """One int64 per integer coordinate triple (N, 3) within +-2**20 per axis (a cheap 1-D key
    for ``np.unique`` / ``np.isin`` over block or tile coordinates)."""
    c = np.asarray(coords, np.int64).reshape(-1, 3) + _PACK_BIAS
    return (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]


def unpack_coords(packed: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_coords`."""
    p = np.asarray(packed, np.int64)
    mask = (1 << 21) - 1
    return np.stack([(p >> 42) & mask, (p >> 21) & mask, p & mask], axis=1) - _PACK_BIAS


@dataclass(frozen=True)
class TileGrid:
    """Tile geometry of a volume: ``tile_blocks`` blocks per tile edge, blocks of ``block_size_m``."""

    tile_blocks: int
    block_size_m: float

    def __post_init__(self) -> None:
        if self.tile_blocks < 1:
            raise ValueError(f"tile_blocks must be >= 1, got {self.tile_blocks}")
        if not self.block_size_m > 0:
            raise ValueError(f"block_size_m must be > 0, got {self.block_size_m}")

    @property
    def tile_size_m(self) -> float:
        return self.tile_blocks * self.block_size_m

    def tiles_of_blocks(self, block_coords: np.ndarray) -> np.ndarray:
        """Tile coordinates (int64 (N, 3)) of block coordinates (int (N, 3))."""
        return np.floor_divide(np.asarray(block_coords, np.int64).reshape(-1, 3), self.tile_blocks)

    def group_blocks(self, block_coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(tiles (T, 3) int64 sorted, inverse (N,))``: the distinct tiles of the blocks and
        each block's row in ``tiles``."""
        tiles = self.tiles_of_blocks(block_coords)
        if len(tiles) == 0:
            return np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
        uniq, inverse = np.unique(pack_coords(tiles), return_inverse=True)  # sorted like (x, y, z)
        return unpack_coords(uniq), inverse.reshape(-1)

    def tile_centers_m(self, tiles: np.ndarray) -> np.ndarray:
        """World coordinates (float64 (T, 3)) of tile centres."""
        return (np.asarray(tiles, np.float64).reshape(-1, 3) + 0.5) * self.tile_size_m

    def tiles_in_view(
        self,
        tiles: np.ndarray,
        T_world_cam: np.ndarray,
        *,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width_px: int,
        height_px: int,
        depth_max_m: float,
    ) -> np.ndarray:
        """Bool mask over ``tiles``: those whose bounding sphere reaches the view frustum of a
        pinhole camera at ``T_world_cam`` (camera-to-world, OpenCV axes) up to ``depth_max_m``.
        Conservative (a tile near a frustum corner may be kept); never drops a tile the view sees."""
        tiles = np.asarray(tiles, np.int64).reshape(-1, 3)
        if len(tiles) == 0:
            return np.zeros(0, bool)
        radius = self.tile_size_m * math.sqrt(3.0) / 2.0
        pc = (self.tile_centers_m(tiles) - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
        z = pc[:, 2]
        keep = (z > -radius) & (z < depth_max_m + radius)
        # The sphere reaches the frustum when it reaches any side plane's inner half-space.
        for focal, centre, size, axis in ((fx, cx, width_px, 0), (fy, cy, height_px, 1)):
            for edge_px in (0.0, float(size)):
                # Plane through the camera centre and the image edge u = edge_px (or v).
                slope = (edge_px - centre) / focal
                n = np.zeros(3)
                n[axis], n[2] = (1.0, -slope) if edge_px > centre else (-1.0, slope)
                n /= np.linalg.norm(n)
                keep &= pc @ n <= radius  # outside this plane by more than the radius: invisible
        return keep


class TileVersions:
    """Per-tile change counters and what was last written (module docstring)."""

    def __init__(self) -> None:
        self._version: dict[tuple[int, int, int], int] = {}
        self._written: dict[tuple[int, int, int], int] = {}
        self._clock = 0

    @staticmethod
    def _as_tuples(tiles: np.ndarray | Iterable[Iterable[int]]) -> list[tuple[int, int, int]]:
        arr = np.asarray(tiles, np.int64).reshape(-1, 3)
        return [tuple(int(v) for v in row) for row in arr]  # type: ignore[misc]

    @property
    def clock(self) -> int:
        """The version the latest change got (a mark: tiles with a larger version changed after it)."""
        return self._clock

    def touch(self, tiles: np.ndarray | Iterable[Iterable[int]]) -> None:
        """Record a change of ``tiles`` (int (T, 3))."""
        self._clock += 1
        for t in self._as_tuples(tiles):
            self._version[t] = self._clock

    def dirty(self) -> dict[tuple[int, int, int], int]:
        """Tiles changed since they were last written, with their current version."""
        return {t: v for t, v in self._version.items() if v > self._written.get(t, 0)}

    def version(self, tile: tuple[int, int, int]) -> int:
        """The version of ``tile`` (0: never changed)."""
        return self._version.get(tile, 0)

    def is_dirty(self, tile: tuple[int, int, int]) -> bool:
        return self._version.get(tile, 0) > self._written.get(tile, 0)

    def mark_written(self, versions: dict[tuple[int, int, int], int]) -> None:
        """The tiles of ``versions`` were written as they were at those versions."""
        for t, v in versions.items():
            if v > self._written.get(t, 0):
                self._written[t] = v

    def mark_clean(self, tile: tuple[int, int, int]) -> None:
        """``tile`` now equals its stored copy (just read back, or written)."""
        self._written[tile] = self._version.get(tile, 0)

    def forget(self, tile: tuple[int, int, int]) -> None:
        self._version.pop(tile, None)
        self._written.pop(tile, None)

    def clear(self) -> None:
        self._version.clear()
        self._written.clear()
