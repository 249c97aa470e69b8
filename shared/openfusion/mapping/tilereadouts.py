"""Region summaries and region contacts of the whole map, kept per tile and recomputed only where
the map changed.

Why: a save's region summaries (what ``openfusion query --map-dir`` and the query service rank
with) and a merge pass's region contacts were computed from the whole map at once: every surface
point of a floor held together (the 10-room building: 6.4 million points, the final save's
resident memory 1.3 GiB with a 300 MiB budget, 50-150 s per save on a loaded 2-core box) and the
key slots of every labelled block copied at every merge pass. Both are sums over the map's
voxels, so they are kept *per tile* and added up:

- **Summaries** (:meth:`TileReadouts.summary_parts`): a tile's part holds, per key slot of the surface
  points its blocks own (the read-out's rule: every point belongs to exactly one block,
  :mod:`openfusion.mapping.wholemap`), the point count, the coordinate sums (centroid) and the
  lowest and highest values per axis: enough to combine the robust box of
  :func:`openfusion.mapping.queries.region_summaries` (1st-99th percentile per axis) exactly.
  A tile keeps ``max(64, 2 %)`` of its values per axis and side; when the combined percentile of
  a region needs more of one tile (a region reaching far past that tile, e.g. a corridor wall
  whose end lies in it), the check below finds it and the tile is read out again keeping enough.
  Parts speak key *slots* (:mod:`openfusion.mapping.keyslots`): a merge changes no part (the slot
  reads the surviving key when parts are added up); a cleared key drops the parts holding its
  slots (their points are labelled by the fill from other voxels now), a key compaction all.
- **Contacts** (:meth:`TileReadouts.contact_parts`): a tile's part holds
  :func:`openfusion.mapping.merging.contact_counts` of its blocks' voxels (labelled voxels per
  key, voxels of one key touching another), counted with the tile's neighbouring blocks as halo.
  Parts speak keys: a merge or a cleared key drops the parts that hold one of its keys.

Exact, not approximate: the table combined from parts equals :meth:`RegionTable.of_points` of the
whole map's surface points (tests/unit/test_mapping_tilereadouts.py), and the contacts equal
:func:`~openfusion.mapping.merging.block_contacts` of every labelled block. The percentile check:
for a region of ``N`` points the box needs the ``K`` lowest values per axis (``K`` the rank the
percentile interpolates at, plus one); the candidate is the ``K``-th lowest of the values the parts
kept, and it is exact when every part that kept fewer values than it has points kept values up to
at least the candidate (its other values are all above it). A part that fails is read out again
keeping ``1.25 K + 16`` values.

When a part is stale: a tile's part depends on its blocks and the blocks around it (zero
crossings, normals and the label fill read one block of neighbours), so it is stale once the tile
or one of its 26 neighbour tiles changed after the part's blocks were copied
(:class:`~openfusion.mapping.tiles.TileVersions`). Paging a tile in or out changes nothing.

Cost and memory: a refresh reads out only stale tiles, in chunks of :data:`CHUNK_BLOCKS` blocks with
their halo, copied under the volume's lock (and the caller's: a service's) and read out in a
scratch grid outside it, so integration waits for a copy, never for a read-out, and the memory it
needs is one chunk's, whatever the size of the map. Each chunk is one job of the read-out worker
(:mod:`openfusion.mapping.readout_worker`): one chunk in hand in the process at a time, whatever
else reads the map. The parts themselves are small (a few percent of the surface points'
coordinates, 4 bytes each, and a few numbers per region and tile), but they grow with the area:
a paged-out tile's parts go to disk with it (:mod:`openfusion.mapping.partstore`; memory keeps
:class:`StoredPart`, an index of slots, counts and sums), and adding the summaries up is streamed
(:func:`combine_summaries` reads the stored parts one at a time and keeps, per region, axis and
side, only the lowest values its percentile's rank needs), so neither holds every part at once.
A merge rewrites a contact part that holds the merged-away key but not the surviving one
(:func:`relabel_contacts`: exact), so its tile is not counted again.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from openfusion.mapping import readout, readout_worker
from openfusion.mapping.heap import release_freed_memory
from openfusion.mapping.keyslots import KeySlots
from openfusion.mapping.merging import RegionContacts, contact_counts, contacts_of_counts
from openfusion.mapping.paging import TilePager
from openfusion.mapping.partstore import MemoryParts, open_part_store
from openfusion.mapping.storage import ATTR_NAMES, VoxelStorage
from openfusion.mapping.summaries import BBOX_PERCENTILE, RegionTable
from openfusion.mapping.tiles import pack_coords
from openfusion.mapping.tilestore import decode_tile

logger = logging.getLogger(__name__)

Tile = tuple[int, int, int]
#: Blocks of one chunk read out at once (4 MiB of compact voxels, plus the halo; measured on the
#: 10-room building: +69 MiB of RssAnon while a chunk is read out at 1,024 blocks, +122 MiB at
#: 2,048; on a 3-room map loaded lazily a summaries read-out peaked +87-93 MiB at 1,024 and +72-75
#: at 512, 1.25x the time): one job of the read-out worker holds one chunk.
CHUNK_BLOCKS = 512
#: Values a summary part keeps per axis and side at least, and as a share of its points.
KEEP_MIN = 64
KEEP_SHARE = 0.02
_OFFSETS = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)], np.int64)
_NEIGHBOURS = [tuple(int(v) for v in o) for o in _OFFSETS]


@dataclass
class SummaryPart:
    """One tile's surface points, per key slot (module docstring). ``low[i][a]``: the lowest values
    of slot ``i`` along axis ``a``, ascending; ``high[i][a]``: the highest, negated, ascending."""

    clock: int
    slots: np.ndarray  # (S,) int64
    count: np.ndarray  # (S,) int64
    sums: np.ndarray  # (S, 3) float64
    low: list[list[np.ndarray]] = field(default_factory=list)
    high: list[list[np.ndarray]] = field(default_factory=list)


@dataclass
class ContactPart:
    """One tile's contact counts, in keys (module docstring)."""

    clock: int
    keys: np.ndarray  # (R,) int64
    surface: np.ndarray  # (R,) int64
    owner: np.ndarray  # (P,) int64
    other: np.ndarray  # (P,) int64
    count: np.ndarray  # (P,) int64

    def holds(self, keys: np.ndarray) -> bool:
        return bool(np.isin(self.keys, keys).any() or np.isin(self.other, keys).any())


@dataclass
class StoredPart:
    """A paged-out tile's part, kept in the part store (:mod:`openfusion.mapping.partstore`): in
    memory only its clock and what a merge or a cleared key must know (the slots of a summary part;
    the keys, owners and others of a contact part)."""

    clock: int
    present: np.ndarray  # (n,) int64, sorted
    #: A summary part's slots, point counts and coordinate sums (what adding parts up reads first).
    slots: np.ndarray | None = None
    count: np.ndarray | None = None
    sums: np.ndarray | None = None

    def holds(self, keys: np.ndarray) -> bool:
        return bool(np.isin(self.present, keys).any())


def _stored(kind: str, part: SummaryPart | ContactPart) -> StoredPart:
    if isinstance(part, SummaryPart):
        return StoredPart(part.clock, _present(kind, part), part.slots, part.count, part.sums)
    return StoredPart(part.clock, _present(kind, part))


def part_arrays(part: SummaryPart | ContactPart) -> dict[str, np.ndarray]:
    """A part as flat arrays (the part store's encoding)."""
    if isinstance(part, ContactPart):
        return {"clock": np.array([part.clock], np.int64), "keys": part.keys, "surface": part.surface,
                "owner": part.owner, "other": part.other, "count": part.count}
    lows = [v for per in part.low for v in per]
    highs = [v for per in part.high for v in per]
    return {"clock": np.array([part.clock], np.int64), "slots": part.slots, "count": part.count, "sums": part.sums,
            "low_n": np.array([len(v) for v in lows], np.int64), "high_n": np.array([len(v) for v in highs], np.int64),
            "low": np.concatenate(lows) if lows else np.zeros(0, np.float32),
            "high": np.concatenate(highs) if highs else np.zeros(0, np.float32)}


def part_of(kind: str, a: dict[str, np.ndarray]) -> SummaryPart | ContactPart:
    """The inverse of :func:`part_arrays`."""
    clock = int(a["clock"][0])
    if kind == "contacts":
        return ContactPart(clock, a["keys"], a["surface"], a["owner"], a["other"], a["count"])
    part = SummaryPart(clock, a["slots"], a["count"], a["sums"])
    for name, out in (("low", part.low), ("high", part.high)):
        values = np.split(a[name], np.cumsum(a[f"{name}_n"])[:-1]) if len(a[f"{name}_n"]) else []
        for i in range(len(part.slots)):
            out.append(list(values[3 * i : 3 * i + 3]))
    return part


def _present(kind: str, part: SummaryPart | ContactPart) -> np.ndarray:
    if isinstance(part, ContactPart):
        return np.unique(np.concatenate([part.keys, part.owner, part.other]).astype(np.int64))
    return np.unique(part.slots.astype(np.int64))


def relabel_contacts(part: ContactPart, mapping: dict[int, int]) -> ContactPart | None:
    """A contact part after keys were merged (``{b: a}``) or cleared (``{b: -1}``), exactly, or None
    when it must be counted again. Contacts count, per (owner, other) key pair, the owner's voxels
    touching at least one voxel of the other: renaming ``b`` to ``a`` is exact when the part holds
    ``b`` and not ``a`` (no two counts merge into one), clearing ``b`` drops its rows and pairs
    (the labelled voxels of other keys are unchanged). A part holding one of a merge's keys and
    another key the mapping names (both ``a`` and ``b``, or two of its entries) is counted again."""
    present = set(_present("contacts", part).tolist())
    named = {k for pair in mapping.items() for k in pair if k >= 0}
    hit = present & named
    sources = hit & set(mapping)
    if not sources:
        return part  # only merge targets (or nothing) here: no voxel of this part changed its key
    if len(hit) > 1:
        return None
    (b,) = sources
    a = mapping[b]
    if a < 0:
        keep_k = part.keys != b
        keep_p = (part.owner != b) & (part.other != b)
        return ContactPart(part.clock, part.keys[keep_k], part.surface[keep_k], part.owner[keep_p],
                           part.other[keep_p], part.count[keep_p])
    return ContactPart(part.clock, np.where(part.keys == b, a, part.keys), part.surface.copy(),
                       np.where(part.owner == b, a, part.owner), np.where(part.other == b, a, part.other),
                       part.count.copy())


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


class TileReadouts:
    """The per-tile parts of one volume (module docstring). Every method runs under the volume's
    lock except :func:`summarise_chunk` / :func:`count_contacts_chunk`, which read only a copy."""

    def __init__(self, storage: VoxelStorage, pager: TilePager) -> None:
        self.storage = storage
        self.pager = pager
        self.summaries: dict[Tile, SummaryPart] = {}
        self.contacts: dict[Tile, ContactPart] = {}
        self.contact_radius: int | None = None
        #: (tile, slot) -> values its summary part keeps per axis and side, above the default.
        self.keep: dict[tuple[Tile, int], int] = {}
        self._compactions = storage.compactions
        self.stats = {"summary_tiles_read": 0, "contact_tiles_read": 0, "parts_to_store": 0, "parts_from_store": 0,
                      "contact_parts_relabelled": 0}
        #: Stored parts found missing when parts were added up (dropped: their tiles are read again).
        self.missing = 0
        #: A geometry shard's: whether it owns a tile (only those are read out; the others' blocks
        #: it holds are ghosts, read as halo only: :mod:`openfusion.mapping.shards`).
        self.owns: Any = None
        #: Parts of paged-out tiles (:mod:`openfusion.mapping.partstore`), opened at the first page-out.
        self.part_store: MemoryParts | None = None
        pager.on_page_out = self.paged_out

    def close(self) -> None:
        if self.part_store is not None:
            self.part_store.close()
            self.part_store = None

    # ------------------------------------------------------------------ paged-out tiles' parts
    def _parts_of(self, kind: str) -> dict[Tile, Any]:
        return self.summaries if kind == "summaries" else self.contacts

    def paged_out(self, tile: Tile) -> None:
        """``tile`` left the grid (the pager's hook, under the volume's lock): its parts that are
        current go to the part store (only a small index stays in memory); stale ones are dropped
        (read again, once, by the next read-out that needs them)."""
        newest = None
        for kind in ("summaries", "contacts"):
            parts = self._parts_of(kind)
            part = parts.get(tile)
            if part is None or isinstance(part, StoredPart):
                continue
            newest = self._newest_around(tile) if newest is None else newest
            if newest > part.clock:
                del parts[tile]
                continue
            self._store().put(kind, tile, part_arrays(part))
            parts[tile] = _stored(kind, part)
            self.stats["parts_to_store"] += 1

    def _store(self) -> MemoryParts:
        if self.part_store is None:
            store = self.pager.store
            self.part_store = open_part_store(None if store is None else store.path)
        return self.part_store

    def _load(self, kind: str, tile: Tile, stored: StoredPart) -> SummaryPart | ContactPart | None:
        got = self.part_store.get(kind, tile) if self.part_store is not None else None
        if got is None:
            return None
        self.stats["parts_from_store"] += 1
        return part_of(kind, got)

    def _drop_stored(self, kind: str, tile: Tile) -> None:
        if self.part_store is not None:
            self.part_store.delete(kind, tile)

    # ------------------------------------------------------------------ invalidation
    def forget(self) -> None:
        """The map was replaced (a reset): drop every part."""
        self.summaries.clear()
        self.contacts.clear()
        self.keep.clear()
        if self.part_store is not None:
            self.part_store.clear()
        self._compactions = self.storage.compactions

    def relabelled(self, changed_slots: np.ndarray, mapping: dict[int, int]) -> None:
        """Keys were merged or cleared (``mapping``; ``changed_slots`` now read another key).
        Contact parts are rewritten where that is exact (:func:`relabel_contacts`), else dropped;
        summary parts speak slots: only those holding a cleared slot are dropped."""
        keys = np.array([k for pair in mapping.items() for k in pair if k >= 0], np.int64)
        if len(keys):
            for t, part in [(t, p) for t, p in self.contacts.items() if p.holds(keys)]:
                stored = isinstance(part, StoredPart)
                full = self._load("contacts", t, part) if stored else part
                new = relabel_contacts(full, mapping) if full is not None else None  # type: ignore[arg-type]
                if new is None:
                    del self.contacts[t]
                    if stored:
                        self._drop_stored("contacts", t)
                    continue
                if new is not full:
                    self.stats["contact_parts_relabelled"] += 1
                    if stored:
                        self.part_store.put("contacts", t, part_arrays(new))  # type: ignore[union-attr]
                        self.contacts[t] = _stored("contacts", new)
                    else:
                        self.contacts[t] = new
        cleared = np.asarray(changed_slots, np.int64)
        cleared = cleared[self.storage.slots.key1[cleared] <= 0] if len(cleared) else cleared
        if len(cleared):
            for t, part in [(t, p) for t, p in self.summaries.items()
                            if np.isin(p.present if isinstance(p, StoredPart) else p.slots, cleared).any()]:
                del self.summaries[t]
                if isinstance(part, StoredPart):
                    self._drop_stored("summaries", t)

    def _check_compaction(self) -> None:
        if self.storage.compactions != self._compactions:  # slots were renumbered
            for t, part in list(self.summaries.items()):
                if isinstance(part, StoredPart):
                    self._drop_stored("summaries", t)
            self.summaries.clear()
            self.keep.clear()
            self._compactions = self.storage.compactions

    # ------------------------------------------------------------------ what to read out
    def _tiles(self) -> dict[Tile, int]:
        groups = self.pager._resident_groups()
        out = {t: len(g[1]) for t, g in groups.items()}
        out.update(self.pager.stored_blocks)
        if self.owns is not None:
            out = {t: n for t, n in out.items() if self.owns(t)}
        return out

    def _newest_around(self, tile: Tile) -> int:
        version = self.pager.versions.version
        x, y, z = tile
        return max(version((x + dx, y + dy, z + dz)) for dx, dy, dz in _NEIGHBOURS)

    def stale(self, parts: dict[Tile, Any], *, settled_clock: int | None = None) -> list[list[Tile]]:
        """Chunks of the tiles whose part is missing or stale (``settled_clock``: only those whose
        neighbourhood last changed at or before that clock), dropping parts of vanished tiles."""
        self._check_compaction()
        tiles = self._tiles()
        for t in [t for t in parts if t not in tiles]:
            if isinstance(parts.pop(t), StoredPart):
                self._drop_stored("summaries" if parts is self.summaries else "contacts", t)
        chosen: list[Tile] = []
        for t in sorted(tiles):
            part = parts.get(t)
            newest = self._newest_around(t)
            if part is not None and newest <= part.clock:
                continue
            if settled_clock is not None and newest > settled_clock:
                continue
            chosen.append(t)
        chunks: list[list[Tile]] = []
        size = 0
        for t in chosen:
            if not chunks or (size + tiles[t] > CHUNK_BLOCKS and chunks[-1]):
                chunks.append([])
                size = 0
            chunks[-1].append(t)
            size += tiles[t]
        return chunks

    def copy_chunk(self, chunk: list[Tile], *, keys_only: bool = False) -> ChunkCopy:
        """Under the volume's lock: the chunk's blocks and every block of the tiles around it that
        lies next to the chunk's tiles (raw copies of resident ones, blobs of stored tiles)."""
        chunk_set = set(chunk)
        around = {(t[0] + dx, t[1] + dy, t[2] + dz) for t in chunk for dx, dy, dz in _NEIGHBOURS} - chunk_set
        groups = self.pager._resident_groups()
        names = ("key",) if keys_only else ATTR_NAMES
        resident: list[tuple[np.ndarray, dict[str, np.ndarray]]] = []
        stored: list[tuple[Tile, bytes, Any, int]] = []
        for t in sorted(chunk_set | around):
            if t in groups:
                coords, buf = groups[t]
                if t not in chunk_set:
                    sel = _next_to(coords, chunk_set, self.pager.grid.tile_blocks)
                    coords, buf = coords[sel], buf[sel]
                if len(buf):
                    raw = self.storage.read_raw_blocks(buf, names=names)
                    resident.append((coords.copy(), raw))
            elif t in self.pager.stored_blocks:
                blob, _ = self.pager.blob_of(t)
                stored.append((t, blob, self.pager._store_of(t).codec, self.pager.stored_blocks[t]))
        keep = {k: v for k, v in self.keep.items() if k[0] in chunk_set}
        return ChunkCopy(list(chunk), self.pager.versions.clock, resident, stored, self.storage.slots.key1.copy(), keep)

    # ------------------------------------------------------------------ results
    def _put(self, kind: str, parts: dict[Tile, Any]) -> None:
        """Read-out results (resident or stored tiles: a stored tile's part is written to the part
        store at once, so only its index stays in memory)."""
        kept = self._parts_of(kind)
        for t, part in parts.items():
            if isinstance(kept.get(t), StoredPart):
                self._drop_stored(kind, t)
            if t in self.pager.stored_blocks:
                self._store().put(kind, t, part_arrays(part))
                kept[t] = _stored(kind, part)
                self.stats["parts_to_store"] += 1
            else:
                kept[t] = part

    def put_summaries(self, parts: dict[Tile, SummaryPart]) -> None:
        self._put("summaries", parts)
        self.stats["summary_tiles_read"] += len(parts)

    def put_contacts(self, parts: dict[Tile, ContactPart], radius_vox: int) -> None:
        if self.contact_radius != radius_vox:
            for t, part in list(self.contacts.items()):
                if isinstance(part, StoredPart):
                    self._drop_stored("contacts", t)
            self.contacts.clear()
            self.contact_radius = radius_vox
        self._put("contacts", parts)
        self.stats["contact_tiles_read"] += len(parts)

    def _materialised(self, kind: str) -> list[tuple[Tile, Any]]:
        """Every tile's part, paged-out tiles' read from the part store (a part missing there is
        dropped: read out again next time)."""
        parts = self._parts_of(kind)
        out: list[tuple[Tile, Any]] = []
        for t, part in list(parts.items()):
            if isinstance(part, StoredPart):
                full = self._load(kind, t, part)
                if full is None:
                    logger.warning("the %s part of paged-out tile %s is missing from the part store; reading the tile again",
                                   kind, t)
                    del parts[t]
                    self.missing += 1
                    continue
                part = full
            out.append((t, part))
        return out

    def summary_parts(self) -> list[tuple[Tile, SummaryPart]]:
        return self._materialised("summaries")

    def summary_index(self) -> list[tuple[Tile, Any]]:
        """Every tile's summary part or, for a stored one, its index entry (slots, counts, sums:
        what :func:`combine_summaries` reads first, without reading the part store)."""
        return list(self.summaries.items())

    def iter_summary_parts(self) -> Iterator[tuple[Tile, SummaryPart]]:
        """Every tile's summary part, stored ones read from the part store one at a time (a part
        missing there is dropped and counted in :attr:`missing`: read out again next time)."""
        for t, part in list(self.summaries.items()):
            if isinstance(part, StoredPart):
                full = self._load("summaries", t, part)
                if full is None:
                    logger.warning("the summaries part of paged-out tile %s is missing from the part store; "
                                   "reading the tile again", t)
                    self.summaries.pop(t, None)
                    self.missing += 1
                    continue
                part = full
            yield t, part

    def contact_parts(self) -> list[ContactPart]:
        return [p for _, p in self._materialised("contacts")]


# ---------------------------------------------------------------------------- chunk read-outs
def _next_to(coords: np.ndarray, chunk: set[Tile], tile_blocks: int) -> np.ndarray:
    """Rows of ``coords`` (blocks of a tile outside ``chunk``) with a block of a chunk tile among
    their 26 neighbours' places."""
    if not len(coords):
        return np.zeros(0, bool)
    chunk_keys = pack_coords(np.array(sorted(chunk), np.int64))
    near = (np.asarray(coords, np.int64)[:, None, :] + _OFFSETS[None]).reshape(-1, 3)
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
            sel = _next_to(c, chunk_set, tile_blocks)
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
    pts = readout.extract_points(grid)
    p = grid.params
    owner = np.floor_divide(np.floor(pts.points.astype(np.float64) / p.voxel_size_m + 1e-4).astype(np.int64), p.block_resolution)
    tile_of = np.floor_divide(owner, tile_blocks)
    slot = pts.keys.astype(np.int64)
    labelled = slot > 0
    points, tile_of, slot = pts.points[labelled], tile_of[labelled], slot[labelled]
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


# ---------------------------------------------------------------------------- adding parts up
def combine_contacts(parts: list[ContactPart]) -> RegionContacts:
    """The whole map's contacts from every tile's part (sums)."""
    if not parts:
        return RegionContacts.empty()
    keys = np.concatenate([p.keys for p in parts])
    if not len(keys):
        return RegionContacts.empty()
    surface = np.concatenate([p.surface for p in parts])
    uk, inv = np.unique(keys, return_inverse=True)
    total = np.bincount(inv.reshape(-1), weights=surface, minlength=len(uk)).astype(np.int64)
    owner = np.concatenate([p.owner for p in parts])
    other = np.concatenate([p.other for p in parts])
    count = np.concatenate([p.count for p in parts])
    if len(owner):
        pairs, inv = np.unique(np.stack([owner, other], axis=1), axis=0, return_inverse=True)
        summed = np.bincount(inv.reshape(-1), weights=count, minlength=len(pairs)).astype(np.int64)
        owner, other, count = pairs[:, 0], pairs[:, 1], summed
    return contacts_of_counts(uk, total, owner, other, count)


@dataclass
class _Bound:
    """One percentile bound to find: ascending ranks ``r1 <= r2`` interpolated with weight ``w``."""

    r1: int
    r2: int
    w: float


def _bounds(n: int, percentile: float) -> tuple[_Bound, _Bound]:
    """The low and high bound of :func:`openfusion.mapping.queries.region_summaries` for ``n`` points
    (the high one in ranks of the negated values)."""
    q = float(percentile) / 100.0
    out = []
    for frac in (q, 1.0 - q):
        pos = frac * (n - 1)
        lo = int(math.floor(pos))
        hi = min(lo + 1, n - 1)
        out.append((lo, hi, pos - lo))
    (l1, l2, lw), (h1, h2, hw) = out
    # High side on negated values: ascending rank i of v is rank n - 1 - i of -v.
    return _Bound(l1, l2, lw), _Bound(n - 1 - h2, n - 1 - h1, hw)


def combine_summaries(parts: Any, key1: np.ndarray, percentile: float = BBOX_PERCENTILE, *,
                      index: Any = None) -> tuple[RegionTable, dict[tuple[Tile, int], int]]:
    """The whole map's region table from every tile's part, and the (tile, slot) parts that kept
    too few values for it to be exact, with how many they must keep (module docstring).

    Streamed, so adding up a floor's parts never holds them all: ``index`` (default: ``parts``)
    gives every tile's slots, counts and sums (the points and centroid per key, and so the ranks
    each box bound needs); ``parts`` (a list of ``(tile, part)``, or a callable returning an
    iterator over them, e.g. parts read from the part store one at a time) is then read once,
    keeping per key, side and axis only the lowest values the bound's rank needs."""
    first = index if index is not None else (parts() if callable(parts) else parts)
    counts: dict[int, int] = {}
    sums: dict[int, np.ndarray] = {}
    for _t, part in first:
        for i, s in enumerate(part.slots):
            key = int(key1[int(s)]) - 1
            if key >= 0:
                counts[key] = counts.get(key, 0) + int(part.count[i])
                sums[key] = sums.get(key, np.zeros(3)) + np.asarray(part.sums[i], np.float64)
    keys = sorted(counts)
    row_of = {k: r for r, k in enumerate(keys)}
    bounds = {k: _bounds(counts[k], percentile) for k in keys}
    lowest: dict[tuple[int, int, int], np.ndarray] = {}
    truncated: dict[tuple[int, int, int], list[tuple[Tile, int, float]]] = {}
    for t, part in (parts() if callable(parts) else parts):
        for i, s in enumerate(part.slots):
            key = int(key1[int(s)]) - 1
            if key < 0:
                continue
            n_i = int(part.count[i])
            for side, values in ((0, part.low[i]), (1, part.high[i])):
                k = bounds[key][side].r2 + 1
                for axis in range(3):
                    lst = values[axis]
                    at = (key, side, axis)
                    if len(lst) < n_i:
                        truncated.setdefault(at, []).append((t, int(s), float(lst[-1]) if len(lst) else -math.inf))
                    run = np.concatenate([lowest[at], lst]) if at in lowest else np.asarray(lst, np.float64)
                    if len(run) > k:
                        run = np.partition(run, k - 1)[:k]
                    lowest[at] = run.astype(np.float64, copy=False)
    n_keys = len(keys)
    count_arr = np.zeros(n_keys, np.int64)
    centroid = np.zeros((n_keys, 3), np.float32)
    bbox = np.zeros((2, n_keys, 3), np.float64)
    failing: dict[tuple[Tile, int], int] = {}
    for key in keys:
        row = row_of[key]
        n = counts[key]
        count_arr[row] = n
        centroid[row] = (sums[key] / max(n, 1)).astype(np.float32)
        for side in (0, 1):
            bound = bounds[key][side]
            k = bound.r2 + 1
            for axis in range(3):
                at = (key, side, axis)
                run = lowest.get(at, np.zeros(0))
                cut = float(run.max()) if len(run) >= k else None
                ok = True
                for t, slot, last in truncated.get(at, []):
                    if cut is None or last < cut:
                        failing[(t, slot)] = max(failing.get((t, slot), 0), int(1.25 * k) + 16)
                        ok = False
                if not ok or cut is None:
                    continue
                ordered = np.sort(run)
                v1, v2 = float(ordered[bound.r1]), float(ordered[bound.r2])
                if side == 1:  # ranks of negated values: v[h1] = -v2, v[h2] = -v1 (negation is exact)
                    v1, v2 = -v2, -v1
                bbox[side, row, axis] = v1 * (1.0 - bound.w) + v2 * bound.w
    table = RegionTable(np.array(keys, np.int32), count_arr, centroid, bbox[0].astype(np.float32),
                        bbox[1].astype(np.float32))
    return table, failing


# ---------------------------------------------------------------------------- driving a refresh
class _Both:
    """Enter ``outer`` then ``inner`` (a caller's lock, then the volume's: the order every thread takes them in)."""

    def __init__(self, outer: Any, inner: Any) -> None:
        self.outer, self.inner = outer, inner

    def __enter__(self) -> None:
        self.outer.__enter__()
        try:
            self.inner.__enter__()
        except BaseException:
            self.outer.__exit__(None, None, None)
            raise

    def __exit__(self, *exc: object) -> None:
        try:
            self.inner.__exit__(*exc)
        finally:
            self.outer.__exit__(*exc)


def both(lock: Any, volume_lock: Any) -> Any:
    """A context holding ``lock`` (None: nothing) and then the volume's lock."""
    return _Both(lock if lock is not None else contextlib.nullcontext(), volume_lock)


def refresh(
    volume_lock: Any,
    readouts: TileReadouts,
    *,
    what: str,
    lock: Any = None,
    settled_clock: int | None = None,
    radius_vox: int = 1,
    hold: bool = False,
    max_s: float | None = None,
) -> int:
    """Read out the stale tiles' parts (``what``: ``"summaries"`` or ``"contacts"``), a chunk at a
    time, each chunk one job on the read-out worker (:mod:`openfusion.mapping.readout_worker`: one
    chunk in hand in the process at a time): copied holding ``lock`` (the caller's, e.g. a
    service's) and the volume's lock, read out holding neither (``hold``: the whole refresh one
    job holding both throughout; both must be reentrant). The caller must hold neither lock
    (the worker's rule 1). ``max_s``: stop after the chunk that passes this many seconds (idle
    work). Returns the tiles read out."""
    if what not in ("summaries", "contacts"):
        raise ValueError(f"what must be 'summaries' or 'contacts', got {what!r}")
    readout_worker.check_caller(what)
    if hold:
        return readout_worker.run(what, functools.partial(
            _refresh, volume_lock, readouts, what=what, lock=lock, settled_clock=settled_clock, radius_vox=radius_vox,
            hold=True, max_s=max_s))
    return _refresh(volume_lock, readouts, what=what, lock=lock, settled_clock=settled_clock,
                    radius_vox=radius_vox, hold=False, max_s=max_s)


def _refresh(volume_lock: Any, readouts: TileReadouts, *, what: str, lock: Any, settled_clock: int | None,
             radius_vox: int, hold: bool, max_s: float | None) -> int:
    pager, storage = readouts.pager, readouts.storage
    res, tile_blocks = storage.params.block_resolution, pager.grid.tile_blocks
    done = 0
    with both(lock, volume_lock) if hold else contextlib.nullcontext():
        with both(lock, volume_lock):
            if what == "contacts" and readouts.contact_radius != radius_vox:
                readouts.contacts.clear()
                readouts.contact_radius = radius_vox
            parts = readouts.summaries if what == "summaries" else readouts.contacts
            chunks = readouts.stale(parts, settled_clock=settled_clock)

        def one(chunk: list[Tile]) -> None:
            """One chunk: copied under the locks, read out outside them, its parts kept."""
            with both(lock, volume_lock):
                copy = readouts.copy_chunk(chunk, keys_only=what == "contacts")
            if what == "summaries":  # a scratch grid of this chunk's size, freed with the job
                got_s = summarise_chunk(copy, Scratch(storage), tile_blocks)
                with volume_lock:
                    readouts.put_summaries(got_s)
            else:
                got_c = count_contacts_chunk(copy, tile_blocks, res, radius_vox)
                with volume_lock:
                    readouts.put_contacts(got_c, radius_vox)
            del copy
            release_freed_memory()  # the chunk's copies and read-out arrays: back to the OS

        started = time.monotonic()
        for chunk in chunks:
            if max_s is not None and done and time.monotonic() - started >= max_s:
                break
            readout_worker.run(what, one, chunk)
            done += len(chunk)
    return done
