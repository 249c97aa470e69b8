"""One chunk's read-out: its blocks copied under the lock, its parts read out outside it.

:class:`~openfusion.mapping.tilereadouts.TileReadouts` copies a chunk of stale tiles with their
halo (every block of a neighbour tile that lies next to a chunk tile) into a :class:`ChunkCopy`
under the volume's lock; the functions here read only that copy, so integration never waits for
them (:mod:`openfusion.mapping.tilereadouts`, "Cost and memory"): :func:`summarise_chunk` reads the
chunk's surface points out in a :class:`Scratch` grid and keeps each tile's :class:`SummaryPart`
(``keep_for`` values per axis and side), :func:`count_contacts_chunk` counts each tile's
:class:`ContactPart` from the key slots alone. Stored tiles of a copy are decoded here, outside the
lock, their far blocks dropped at once.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from openfusion.mapping import readout
from openfusion.mapping.keyslots import KeySlots
from openfusion.mapping.merging import contact_counts
from openfusion.mapping.storage import ATTR_NAMES, VoxelStorage
from openfusion.mapping.tilecodec import decode_tile
from openfusion.mapping.tileparts import ContactPart, SummaryPart, Tile
from openfusion.mapping.tiles import NEIGHBOUR_OFFSETS, pack_coords, unpack_coords

#: Values a summary part keeps per axis and side at least, and as a share of its points.
KEEP_MIN = 64
KEEP_SHARE = 0.02


@dataclass
class ChunkCopy:
    """What one chunk's read-out needs, copied under the lock: resident blocks (raw), stored tiles
    (blobs, decoded outside the lock), the slot table and the versions' clock."""

    tiles: list[Tile]
    clock: int
    resident: list[tuple[np.ndarray, dict[str, np.ndarray]]]
    stored: list[tuple[Tile, bytes, Any, int]]  # (tile, blob, codec, its blocks)
    key1: np.ndarray  # the slot table (key + 1 per slot) at the copy
    keep: dict[tuple[Tile, int], int]


def next_to_chunk(coords: np.ndarray, chunk: set[Tile], tile_blocks: int) -> np.ndarray:
    """Rows of ``coords`` (blocks of a tile outside ``chunk``) with a block of a chunk tile among
    their 26 neighbours' places."""
    if not len(coords):
        return np.zeros(0, bool)
    chunk_keys = pack_coords(np.array(sorted(chunk), np.int64))
    near = (np.asarray(coords, np.int64)[:, None, :] + NEIGHBOUR_OFFSETS[None]).reshape(-1, 3)
    hit = np.isin(pack_coords(np.floor_divide(near, tile_blocks)), chunk_keys).reshape(len(coords), -1)
    return hit.any(axis=1)


def _parts_of(copy: ChunkCopy, tile_blocks: int, names: tuple[str, ...]) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """The blocks of a chunk copy part by part (stored tiles decoded now, their far blocks left
    out); each resident part is let go of as it is handed out."""
    chunk_set = set(copy.tiles)
    while copy.resident:
        c, r = copy.resident.pop()
        yield c, {k: r[k] for k in names}
    while copy.stored:
        t, blob, codec, _ = copy.stored.pop()
        c, raw = decode_tile(codec, blob, f"tile {t}")
        if t not in chunk_set:
            sel = next_to_chunk(c, chunk_set, tile_blocks)
            c, raw = c[sel], {k: v[sel] for k, v in raw.items()}
        yield c, {k: raw[k] for k in names}


def _blocks_of(copy: ChunkCopy, tile_blocks: int, names: tuple[str, ...]) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Every block of a chunk copy in one array per attribute (the key slots, for contacts)."""
    parts = list(_parts_of(copy, tile_blocks, names))
    if not parts:
        return np.zeros((0, 3), np.int32), {}
    return (np.concatenate([c for c, _ in parts]).astype(np.int32),
            {k: np.concatenate([r[k] for _, r in parts]) for k in names})


def _identity_slots(key1: np.ndarray) -> KeySlots:
    """A slot table under which every labelled slot reads its own number (a read-out's keys are
    then slots) and every other slot reads none."""
    table = KeySlots(len(key1) - 1)
    table.key1 = np.where(key1 > 0, np.arange(len(key1), dtype=np.int64) + 1, 0).astype(np.int32)
    table.key1[0] = 0
    return table


class Scratch:
    """A grid to read chunks out in, reused from chunk to chunk (made again when a chunk needs more)."""

    def __init__(self, storage: VoxelStorage) -> None:
        self.params = storage.params.with_changes(memory_budget_mb=None)
        self.device = storage.device
        self.grid: VoxelStorage | None = None

    def load(self, copy: ChunkCopy, tile_blocks: int) -> VoxelStorage | None:
        """The chunk's blocks in the grid; None when the chunk holds none. Stored tiles are decoded
        first (their far blocks dropped at once, so the grid is sized by the blocks it gets, not
        by whole neighbour tiles), then every part is written and let go of."""
        parts = [(c, r) for c, r in _parts_of(copy, tile_blocks, ATTR_NAMES) if len(c)]
        count = sum(len(c) for c, _ in parts)
        if count == 0:
            return None
        if self.grid is None or self.grid.capacity_blocks < count:
            self.grid = None  # the old one is freed before the new one is made
            self.grid = VoxelStorage(self.params, self.device, capacity=count + count // 8)
        else:
            c_old, b_old = self.grid.active_blocks()
            self.grid.erase_blocks(c_old, b_old)
        while parts:
            coords, raw = parts.pop()
            self.grid.write_raw_blocks(np.asarray(coords, np.int32), raw)
        return self.grid


def summarise_chunk(copy: ChunkCopy, scratch: Scratch, tile_blocks: int) -> dict[Tile, SummaryPart]:
    """The summary parts of a chunk's tiles (outside the lock: reads only the copy)."""
    out = {t: _empty_summary(copy.clock) for t in copy.tiles}
    grid = scratch.load(copy, tile_blocks)
    if grid is None:
        return out
    grid.slots = _identity_slots(copy.key1)
    surface = readout.surface_points(grid)
    if surface is None:
        return out
    points_all, _, normals = surface
    slot, conf = readout.semantics_at_points(grid, points_all, normals, vote=False)
    p = grid.params
    owner = np.floor_divide(np.floor(points_all.astype(np.float64) / p.voxel_size_m + 1e-4).astype(np.int64), p.block_resolution)
    tile_of = np.floor_divide(owner, tile_blocks)
    seen: dict[Tile, np.ndarray] = {}
    if p.label_vote_radius_m > 0:  # the whole map's vote, by the slots' keys at the copy
        classes = np.where(slot >= 0, copy.key1[np.maximum(slot, 0)].astype(np.int64) - 1, -1)
        pairs = readout.vote_neighbours(points_all, slot, p.label_vote_radius_m, normals, classes=classes)
        seen = _seen_slots(np.concatenate([tile_of[pairs[0]], tile_of[pairs[0]]]),
                           np.concatenate([slot[pairs[1]], slot[pairs[0]]]).astype(np.int64))
        readout.vote_labels(points_all, slot, conf, p.label_vote_radius_m, normals, classes=classes, neighbours=pairs)
    slot = slot.astype(np.int64)
    labelled = slot > 0
    points, tile_of, slot = points_all[labelled], tile_of[labelled], slot[labelled]
    for t in copy.tiles:
        out[t].seen = seen.get(t, out[t].seen)
    if not len(points):
        return out
    tkey = pack_coords(tile_of)
    wanted = {int(pack_coords(np.array([t]))[0]): t for t in copy.tiles}
    inside = np.isin(tkey, np.fromiter(wanted, np.int64))
    points, tkey, slot = points[inside], tkey[inside], slot[inside]
    if not len(points):  # the chunk's labelled points all belong to halo blocks of other tiles
        return out
    order = np.lexsort((slot, tkey))
    points, tkey, slot = points[order], tkey[order], slot[order]
    starts = np.flatnonzero(np.r_[True, (tkey[1:] != tkey[:-1]) | (slot[1:] != slot[:-1])])
    ends = np.r_[starts[1:], len(order)]
    by_tile: dict[Tile, list[tuple[int, np.ndarray]]] = {}
    for a, b in zip(starts, ends, strict=True):
        by_tile.setdefault(wanted[int(tkey[a])], []).append((int(slot[a]), points[a:b]))
    for t, groups in by_tile.items():
        out[t] = _summary_part(copy.clock, groups, {s: copy.keep.get((t, s), 0) for s, _ in groups})
        out[t].seen = seen.get(t, out[t].seen)
    return out


def _seen_slots(tiles: np.ndarray, slots: np.ndarray) -> dict[Tile, np.ndarray]:
    """Per tile, the slots whose keys decide its points' votes (``tiles``: the tile of the voting
    point, ``slots``: a slot before the vote): of the neighbours its points counted and of those
    points themselves. A point with no other class around does not vote, and a merge cannot give it
    one, so only a merge of one of these slots makes the tile's part stale; a cleared key, every
    slot the part holds too (:meth:`~openfusion.mapping.tilereadouts.TileReadouts.relabelled`)."""
    if not len(slots):
        return {}
    tkey = pack_coords(tiles)
    order = np.lexsort((slots, tkey))
    tkey, slots = tkey[order], slots[order]
    first = np.r_[True, (tkey[1:] != tkey[:-1]) | (slots[1:] != slots[:-1])]
    tkey, slots = tkey[first], slots[first]
    starts = np.flatnonzero(np.r_[True, tkey[1:] != tkey[:-1]])
    ends = np.r_[starts[1:], len(tkey)]
    out: dict[Tile, np.ndarray] = {}
    for a, b, t in zip(starts, ends, unpack_coords(tkey[starts]).tolist(), strict=True):
        out[(int(t[0]), int(t[1]), int(t[2]))] = slots[a:b].copy()
    return out


def _empty_summary(clock: int) -> SummaryPart:
    z = np.zeros(0, np.int64)
    return SummaryPart(clock, z, z.copy(), np.zeros((0, 3)))


def keep_for(n: int, wanted: int = 0) -> int:
    """Values a part keeps per axis and side for a slot with ``n`` points (module docstring)."""
    return min(n, max(KEEP_MIN, math.ceil(KEEP_SHARE * n), wanted))


def _lowest(values: np.ndarray, k: int) -> np.ndarray:
    if k >= len(values):
        return np.sort(values)
    return np.sort(np.partition(values, k - 1)[:k])


def _summary_part(clock: int, groups: list[tuple[int, np.ndarray]], wanted: dict[int, int]) -> SummaryPart:
    part = SummaryPart(clock, np.array([s for s, _ in groups], np.int64),
                       np.array([len(p) for _, p in groups], np.int64),
                       np.stack([p.astype(np.float64).sum(axis=0) for _, p in groups]))
    for s, pts in groups:
        k = keep_for(len(pts), wanted.get(s, 0))
        part.low.append([_lowest(pts[:, a], k) for a in range(3)])
        part.high.append([_lowest(-pts[:, a], k) for a in range(3)])
    return part


def count_contacts_chunk(copy: ChunkCopy, tile_blocks: int, res: int, radius_vox: int) -> dict[Tile, ContactPart]:
    """The contact parts of a chunk's tiles (outside the lock: reads only the copy)."""
    coords, raw = _blocks_of(copy, tile_blocks, ("key",))
    out: dict[Tile, ContactPart] = {}
    z = np.zeros(0, np.int64)
    for t in copy.tiles:
        out[t] = ContactPart(copy.clock, z, z.copy(), z.copy(), z.copy(), z.copy())
    if not len(coords):
        return out
    slots = raw["key"].reshape(len(coords), -1)
    keep = (slots > 0).any(axis=1)
    coords, slots = coords[keep].astype(np.int64), slots[keep]
    if not len(coords):
        return out
    keys = (copy.key1[slots.astype(np.intp)].astype(np.int32) - 1).reshape(-1, res, res, res)
    tiles = np.floor_divide(coords, tile_blocks)
    index = {t: i for i, t in enumerate(copy.tiles)}
    group = np.array([index.get((int(a), int(b), int(c)), -1) for a, b, c in tiles], np.int64)
    counts = contact_counts(coords, keys, radius_vox=radius_vox, group=group)
    for i, t in enumerate(copy.tiles):
        s = counts.surface_group == i
        q = counts.pair_group == i
        out[t] = ContactPart(copy.clock, counts.surface_key[s], counts.surface_count[s], counts.pair_owner[q],
                             counts.pair_other[q], counts.pair_count[q])
    return out
