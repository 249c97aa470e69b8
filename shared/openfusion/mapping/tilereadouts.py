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
  Parts speak key *slots* (:mod:`openfusion.mapping.keyslots`): the slot reads the surviving key
  of a merge when parts are added up; a cleared key drops the parts holding its slots (their
  points are labelled by the fill from other voxels now), a key compaction all. The read-out's
  vote (:func:`openfusion.mapping.readout.vote_labels`) counts a point's neighbours by key, so a
  chunk votes by the slots' keys at its copy, and a part also lists the slots its vote read
  (``seen``: the slots of the neighbours its points near another region counted): a merge drops
  the parts that hold or read one of the merged-away slots (their points may vote otherwise now),
  a cleared key likewise. A point whose neighbourhood holds one region only is not voted on, so
  no relabelling changes it (every point around it changes alike).
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

Where the code is: the parts, their encoding and adding them up in :mod:`.tileparts`; one chunk's
read-out outside the lock in :mod:`.chunkreadouts`; here the bookkeeping (which parts are stale,
paged-out tiles' parts, merges and cleared keys) and the refresh that drives the chunks (the
names of the other two are re-exported here).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from openfusion.mapping import readout_worker
from openfusion.mapping.chunkreadouts import KEEP_MIN as KEEP_MIN  # re-exported, as the parts' names
from openfusion.mapping.chunkreadouts import KEEP_SHARE as KEEP_SHARE
from openfusion.mapping.chunkreadouts import (
    ChunkCopy,
    Scratch,
    count_contacts_chunk,
    next_to_chunk,
    summarise_chunk,
)
from openfusion.mapping.chunkreadouts import keep_for as keep_for
from openfusion.mapping.heap import release_freed_memory
from openfusion.mapping.paging import TilePager
from openfusion.mapping.partstore import MemoryParts, open_part_store
from openfusion.mapping.storage import ATTR_NAMES, VoxelStorage
from openfusion.mapping.tileparts import (
    ContactPart,
    StoredPart,
    SummaryPart,
    Tile,
    part_arrays,
    part_of,
    relabel_contacts,
    stored_index,
)
from openfusion.mapping.tileparts import combine_contacts as combine_contacts
from openfusion.mapping.tileparts import combine_summaries as combine_summaries
from openfusion.mapping.tiles import NEIGHBOUR_OFFSETS

logger = logging.getLogger(__name__)

#: Blocks of one chunk read out at once (4 MiB of compact voxels, plus the halo; measured on the
#: 10-room building: +69 MiB of RssAnon while a chunk is read out at 1,024 blocks, +122 MiB at
#: 2,048; on a 3-room map loaded lazily a summaries read-out peaked +87-93 MiB at 1,024 and +72-75
#: at 512, 1.25x the time): one job of the read-out worker holds one chunk.
CHUNK_BLOCKS = 512
_NEIGHBOURS = [tuple(int(v) for v in o) for o in NEIGHBOUR_OFFSETS]


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
            parts[tile] = stored_index(kind, part)
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
        summary parts speak slots: those holding a cleared slot are dropped, and with the read-out's
        vote (``label_vote_radius_m``) every part whose vote a merged slot took part in (a point of
        it voted, or it was among a point's voters); a merge moves no other point."""
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
                        self.contacts[t] = stored_index("contacts", new)
                    else:
                        self.contacts[t] = new
        changed = np.asarray(changed_slots, np.int64)
        gone = self.storage.slots.key1[changed] <= 0
        cleared = changed[gone]  # its points are labelled anew (the fill) and stop voting
        merged = changed[~gone] if self.storage.params.label_vote_radius_m > 0 else changed[:0]
        if len(cleared) or len(merged):
            for t, part in [(t, p) for t, p in self.summaries.items()
                            if (len(cleared) and p.holds(cleared)) or (len(merged) and p.votes_on(merged))]:
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
                    sel = next_to_chunk(coords, chunk_set, self.pager.grid.tile_blocks)
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
                kept[t] = stored_index(kind, part)
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
