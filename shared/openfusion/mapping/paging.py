"""The memory budget: which tiles are resident, paging tiles out to the tile store and back in, and
the snapshots incremental checkpoints are made of.

Resident is a working set (design.md section 10). With ``VolumeParams.memory_budget_mb`` the
volume's Open3D grid is created once with room for ``budget_blocks`` blocks (the budget over 8 KiB,
a compact block: :mod:`openfusion.mapping.storage`) and never grows; Open3D touches the whole
buffer when it creates a grid, so the grid's resident memory *is* that number from the start
(measured: 40,000 blocks -> 312.8 MiB of RSS for 312.5 MiB of values).

Which tiles leave (:meth:`TilePager.make_room`)
    The least recently *observed* tile first (a tile's clock is the frame counter of the last
    integration, update or render that touched it); among tiles last seen in the same frame, the one
    farthest from the camera. Recency is what predicts the next frames of a robot that turns
    round (a distance rule would drop the room behind it, seen a second ago); distance only breaks
    ties. The tiles the current frame touches are never chosen. A room is left for good when the
    robot walks on, so its tiles age out together. Room is made down to 90 % of the budget, so a
    burst of page-outs happens every few frames, not one tile per frame.

Paging out (:meth:`TilePager.make_room`)
    A tile that changed since it was last written is encoded and written into the store's
    generation being built (:mod:`openfusion.mapping.tilestore`: committed by the next
    checkpoint); an unchanged one is dropped (the store holds it).
    Its blocks are zeroed and erased from the grid.

Paging in (:meth:`TilePager.ensure_resident`)
    Before a frame is integrated, every stored tile among the tiles it touches is read back (the
    revisited room is integrated into its old surface, never into blank blocks that would later
    overwrite it); before a render, every stored tile whose box reaches the view frustum.

Checkpoints (:mod:`openfusion.mapping.mapstore` drives them; the pager keeps the books)
    Written in slices, never copied whole: the changed resident tiles are copied a slice of
    :data:`SLICE_BLOCKS` blocks at a time under the volume's lock (:meth:`TilePager.copy_tiles`),
    encoded and written into the store's generation being built outside it
    (:meth:`TilePager.write_slice`), a tile the camera changed meanwhile being copied again in a
    later pass. The checkpoint's instant is its last step, under the lock
    (:meth:`TilePager.end_snapshot`): the tiles changed since they were written (few: what the
    camera saw during the passes) are copied, the slot table and tile index taken and a new
    generation begun for page-outs; the last transaction commits the generation. So a checkpoint
    holds a slice, not the map's changes, in memory, and its cost follows what changed since
    the last one, whatever the size of the map. When more than a slice is left for the last step
    (the passes fell behind a camera changing much), it copies and encodes one tile at a time
    under the lock: memory stays bounded, the lock is held longer. Each slice and the last step
    is one job of the read-out worker (:mod:`openfusion.mapping.readout_worker`). A paged-out
    tile's read-out parts go to disk with it (:attr:`TilePager.on_page_out`).

    A slice and a page-out can race for one tile (the slice copied it, then the camera changed it
    and it was paged out, both writing into the same generation): :meth:`TilePager.write_slice`
    writes a tile only when no newer version of it was written meanwhile, decided inside the
    store's write transaction, which serialises the two writers.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from openfusion.mapping.errors import CapacityError, MapFormatError
from openfusion.mapping.heap import release_freed_memory
from openfusion.mapping.storage import VoxelStorage, logical_arrays
from openfusion.mapping.tiles import TileGrid, TileVersions
from openfusion.mapping.tilestore import TileStore, decode_tile, encode_tile

logger = logging.getLogger(__name__)

Tile = tuple[int, int, int]
#: Page-outs make room down to this share of the budget (hysteresis).
ROOM_TARGET = 0.9


def budget_blocks(memory_budget_mb: float, bytes_per_block: int) -> int:
    """Blocks a budget of ``memory_budget_mb`` MiB holds (at least one)."""
    return max(1, int(memory_budget_mb * 1024 * 1024) // int(bytes_per_block))


@dataclass
class PagerStats:
    tiles_paged_out: int = 0
    tiles_written_out: int = 0  # of those, the ones that had changed (encoded and stored)
    tiles_paged_in: int = 0
    bytes_written: int = 0


#: Blocks a checkpoint copies under the lock at once (16 MiB of compact voxels), then encodes and
#: writes outside it before the next slice.
SLICE_BLOCKS = 2048


@dataclass
class Snapshot:
    """A checkpoint's last step (:meth:`TilePager.end_snapshot`): what its last transaction writes."""

    generation: int
    versions: dict[Tile, int]
    tiles: dict[Tile, tuple[np.ndarray, dict[str, np.ndarray]]] = field(default_factory=dict)
    #: Tiles encoded at the last step already (more than a slice was left: copied and encoded one
    #: tile at a time under the lock, so the step holds one tile's copy, not all of them).
    blobs: dict[Tile, bytes] = field(default_factory=dict)
    slot_table: np.ndarray | None = None
    tile_index: np.ndarray | None = None  # int32 (T, 4): every tile of the map and its block count


class TilePager:
    """Tile residency of one :class:`~openfusion.mapping.storage.VoxelStorage` (module docstring).

    ``store`` holds paged-out tiles (and the checkpoints); ``budget_blocks`` None: nothing is paged
    out (tiles are still tracked, so checkpoints stay incremental). Not locked: the volume
    serialises every call, except :meth:`write_slice`'s store transaction (module docstring)."""

    def __init__(self, storage: VoxelStorage, grid: TileGrid, store: TileStore | None, budget_blocks: int | None) -> None:
        self.storage = storage
        self.grid = grid
        self.store = store
        self.budget_blocks = budget_blocks
        self.versions = TileVersions()
        self.clock = 0
        self.last_used: dict[Tile, int] = {}  # resident tiles -> clock of their last use
        #: Tiles with a copy in a store: ``"own"`` (:attr:`store`, committed or in the generation
        #: being built) or ``"base"`` (the read-only map this volume was loaded from).
        self.location: dict[Tile, str] = {}
        self.base: TileStore | None = None
        self.stored_blocks: dict[Tile, int] = {}  # tiles *not* resident -> their block count
        #: Key slots present in a stored tile's voxels (sorted), recorded at page-out and rewritten
        #: by a key compaction, so a read-out for some regions' keys reads only the tiles that hold
        #: them (:func:`openfusion.mapping.wholemap.extract_points` with keys: a query's points).
        #: Absent for a tile loaded from a map and not read since: unknown, read to find out.
        self.stored_slots: dict[Tile, np.ndarray] = {}
        #: Version of the copy of each tile written into the store's generation being built (a
        #: slice of a checkpoint skips a tile a page-out wrote newer: module docstring).
        self._written_version: dict[Tile, int] = {}
        self.stats = PagerStats()
        self.camera_m = np.zeros(3)
        #: Called with a tile after it was paged out (under the volume's lock): the read-out parts
        #: of it go to disk (:meth:`openfusion.mapping.tilereadouts.TileReadouts.paged_out`).
        self.on_page_out: Callable[[Tile], None] | None = None
        storage.on_compact_keys = self._compact_stored_keys

    # ------------------------------------------------------------------ bookkeeping
    @property
    def res(self) -> int:
        return self.storage.params.block_resolution

    def resident_tiles(self) -> list[Tile]:
        return list(self.last_used)

    def stored_tiles(self) -> list[Tile]:
        """Tiles that are not resident (paged out, or loaded from a map but not read yet)."""
        return list(self.stored_blocks)

    def all_tiles(self) -> list[Tile]:
        return sorted(set(self.last_used) | set(self.stored_blocks))

    def tick(self, camera_m: np.ndarray | None = None) -> int:
        self.clock += 1
        if camera_m is not None:
            self.camera_m = np.asarray(camera_m, np.float64)
        return self.clock

    def touched(self, block_coords: np.ndarray, *, changed: bool) -> list[Tile]:
        """The blocks ``block_coords`` were used now (and ``changed``); returns their tiles."""
        tiles_arr, _ = self.grid.group_blocks(block_coords)
        tiles = [tuple(int(v) for v in t) for t in tiles_arr]
        for t in tiles:
            self.last_used[t] = self.clock  # type: ignore[index]
        if changed and tiles:
            self.versions.touch(tiles_arr)
        return tiles  # type: ignore[return-value]

    def touched_voxels(self, flat_index: np.ndarray) -> None:
        """Voxels at flat indices changed (a semantic update): their tiles are dirty."""
        if len(flat_index) == 0:
            return
        buf = np.unique(np.asarray(flat_index, np.int64) // self.storage.voxels_per_block)
        self.touched(self.storage.block_coords_of_buf(buf), changed=True)

    def _resident_groups(self) -> dict[Tile, tuple[np.ndarray, np.ndarray]]:
        """Resident tiles -> (block coords, buffer indices), cached while the grid is unchanged."""
        st = self.storage
        key = (st.geometry_version, st.generation, id(st.vbg))
        cached = getattr(self, "_groups_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        coords, buf = self.storage.active_blocks()
        tiles, inverse = self.grid.group_blocks(coords)
        order = np.argsort(inverse, kind="stable")
        bounds = np.searchsorted(inverse[order], np.arange(len(tiles) + 1))
        out: dict[Tile, tuple[np.ndarray, np.ndarray]] = {}
        for i, t in enumerate(tiles):
            sel = order[bounds[i] : bounds[i + 1]]
            out[tuple(int(v) for v in t)] = (coords[sel], buf[sel])  # type: ignore[index]
        self._groups_cache = (key, out)
        return out

    def sync_resident(self) -> None:
        """Register every resident block's tile (after a load or a reset)."""
        for t in self._resident_groups():
            self.last_used.setdefault(t, self.clock)

    # ------------------------------------------------------------------ paging
    def ensure_resident(self, tiles: list[Tile], *, extra_blocks: int = 0) -> int:
        """Page in the stored tiles among ``tiles`` (making room first, never evicting ``tiles``);
        ``extra_blocks``: blocks the caller will add besides (a frame's new blocks). Returns the
        tiles paged in."""
        wanted = [t for t in tiles if t in self.stored_blocks]
        need = extra_blocks + sum(self.stored_blocks[t] for t in wanted)
        if self.budget_blocks is not None:
            self.make_room(need, protect=set(tiles))
            if self.storage.num_blocks + need > self.budget_blocks:
                free = max(self.budget_blocks - self.storage.num_blocks, 0)
                raise CapacityError(
                    f"{need} more blocks must be resident at once but the memory budget has room for {free} "
                    f"({self.budget_blocks} blocks of {self.storage.bytes_per_block} B)",
                    blocks_needed=need, blocks_free=free,
                )
        for t in wanted:
            self._page_in(t)
        return len(wanted)

    def make_room(self, blocks_needed: int, *, protect: set[Tile]) -> int:
        """Page out least recently observed tiles (module docstring) until ``blocks_needed`` more
        blocks fit the budget; returns the tiles paged out."""
        if self.budget_blocks is None:
            return 0
        limit = self.budget_blocks
        if self.storage.num_blocks + blocks_needed <= limit:
            return 0
        target = max(int(limit * ROOM_TARGET) - blocks_needed, 0)
        groups = self._resident_groups()
        candidates = [t for t in groups if t not in protect]
        if not candidates:
            return 0
        centers = self.grid.tile_centers_m(np.array(candidates, np.int64))
        dist = np.linalg.norm(centers - self.camera_m, axis=1)
        order = sorted(range(len(candidates)), key=lambda i: (self.last_used.get(candidates[i], 0), -dist[i]))
        n_out = 0
        resident = self.storage.num_blocks
        for i in order:
            if resident <= target:
                break
            t = candidates[i]
            coords, buf = groups[t]
            self._page_out(t, coords, buf)
            resident -= len(buf)
            n_out += 1
        if n_out:
            release_freed_memory()
        return n_out

    def _needs_writing(self, tile: Tile) -> bool:
        """A resident tile whose page-out must write it (changed, or no usable stored copy)."""
        where = self.location.get(tile)
        return self.versions.is_dirty(tile) or where is None or (where == "base" and self.base is None)

    def _page_out(self, tile: Tile, coords: np.ndarray, buf: np.ndarray) -> None:
        if self.store is None:
            raise RuntimeError("paging out needs a tile store")
        if self._needs_writing(tile):
            raw = self.storage.read_raw_blocks(buf)
            self.stored_slots[tile] = np.unique(raw["key"])
            blob = encode_tile(self.store.codec, coords, raw, self.res)
            # Recorded before the write: a checkpoint's slice that copied this tile earlier then
            # skips it (module docstring).
            self._written_version[tile] = self.versions.version(tile)
            self.store.put(tile, blob)
            self.location[tile] = "own"
            self.versions.mark_clean(tile)
            self.stats.tiles_written_out += 1
            self.stats.bytes_written += len(blob)
        else:
            self.stored_slots[tile] = np.unique(self.storage.read_raw_blocks(buf, names=("key",))["key"])
        self.storage.erase_blocks(coords, buf)
        self.last_used.pop(tile, None)
        self.stored_blocks[tile] = len(buf)
        self.stats.tiles_paged_out += 1
        if self.on_page_out is not None:
            self.on_page_out(tile)

    def _store_of(self, tile: Tile) -> TileStore:
        store = self.base if self.location.get(tile) == "base" else self.store
        if store is None:
            raise MapFormatError(f"tile {tile} is not resident and there is no tile store")
        return store

    def _read(self, tile: Tile) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        store = self._store_of(tile)
        blob = store.get(tile)
        if blob is None:
            raise MapFormatError(f"{store.path}: tile {tile} is missing from the store")
        return decode_tile(store.codec, blob, f"{store.path} tile {tile}")

    def read_stored(self, tile: Tile) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The blocks of a non-resident tile, decoded from its store (read-outs stream them)."""
        return self._read(tile)

    def blob_of(self, tile: Tile) -> tuple[bytes, str]:
        """The stored blob of a non-resident tile and its codec's name (a save copies it as it is)."""
        store = self._store_of(tile)
        blob = store.get(tile)
        if blob is None:
            raise MapFormatError(f"{store.path}: tile {tile} is missing from the store")
        return blob, store.codec_name

    def _page_in(self, tile: Tile) -> None:
        coords, raw = self._read(tile)
        self.storage.write_raw_blocks(coords, raw)
        del self.stored_blocks[tile]
        self.stored_slots.pop(tile, None)
        self.last_used[tile] = self.clock
        self.versions.mark_clean(tile)
        self.stats.tiles_paged_in += 1

    def iter_stored(self) -> Iterator[tuple[Tile, np.ndarray, dict[str, np.ndarray]]]:
        """Every non-resident tile's blocks, read from the store one tile at a time."""
        for t in sorted(self.stored_blocks):
            coords, raw = self._read(t)
            yield t, coords, raw

    def stored_arrays(self) -> Iterator[dict[str, np.ndarray]]:
        """Plain arrays (:meth:`VoxelStorage.to_arrays` form) of every non-resident tile."""
        for _, coords, raw in self.iter_stored():
            yield logical_arrays(coords, raw, self.storage.slots)

    def adopt_store(self, store: TileStore, tiles: dict[Tile, int], *, as_base: bool = False) -> None:
        """The map's tiles are in ``store``'s committed generation and none is resident (a load);
        ``as_base``: a read-only map (page-outs of changed tiles go to this pager's own store)."""
        if as_base:
            self.base = store
        else:
            self.store = store
        for t, n in tiles.items():
            self.location[t] = "base" if as_base else "own"
            self.stored_blocks[t] = n
            self.stored_slots.pop(t, None)  # unknown until read

    # ------------------------------------------------------------------ checkpoints
    def precopy_plan(self, *, every_tile: bool = False) -> list[list[Tile]]:
        """The resident tiles changed since they were last written (``every_tile``: all of them),
        in slices of about :data:`SLICE_BLOCKS` blocks (the tiles least recently used first: the
        camera's own tiles, likeliest to change again, come last)."""
        groups = self._resident_groups()
        chosen = [t for t in groups if every_tile or self._needs_writing(t)]
        chosen.sort(key=lambda t: self.last_used.get(t, 0))
        slices: list[list[Tile]] = []
        size = 0
        for t in chosen:
            n = len(groups[t][1])
            if not slices or (size + n > SLICE_BLOCKS and slices[-1]):
                slices.append([])
                size = 0
            slices[-1].append(t)
            size += n
        return slices

    def copy_tiles(self, tiles: list[Tile], *, every_tile: bool = False) -> tuple[dict[Tile, tuple[np.ndarray, dict[str, np.ndarray]]], dict[Tile, int]]:
        """Raw copies of those ``tiles`` still resident and still to be written (``every_tile``:
        resident), with their versions (under the volume's lock)."""
        groups = self._resident_groups()
        out: dict[Tile, tuple[np.ndarray, dict[str, np.ndarray]]] = {}
        versions: dict[Tile, int] = {}
        for t in tiles:
            if t in groups and (every_tile or self._needs_writing(t)):
                coords, buf = groups[t]
                out[t] = (coords.copy(), self.storage.read_raw_blocks(buf))
                versions[t] = self.versions.version(t)
        return out, versions

    def encode(self, tiles: dict[Tile, tuple[np.ndarray, dict[str, np.ndarray]]]) -> dict[Tile, bytes]:
        """Blobs of raw tile copies (outside the volume's lock: reads only the copies)."""
        if self.store is None:
            raise RuntimeError("a checkpoint needs a tile store")
        codec = self.store.codec
        return {t: encode_tile(codec, c, raw, self.res) for t, (c, raw) in tiles.items()}

    def write_slice(self, blobs: dict[Tile, bytes], versions: dict[Tile, int]) -> int:
        """Write a slice's blobs into the generation being built (outside the volume's lock),
        skipping a tile a page-out wrote newer meanwhile; returns the tiles written. Call
        :meth:`slice_written` under the lock afterwards."""
        if self.store is None:
            raise RuntimeError("a checkpoint needs a tile store")

        def keep(t: Tile) -> bool:
            if self._written_version.get(t, -1) >= versions[t]:
                return False
            self._written_version[t] = versions[t]
            return True

        return self.store.put_many(blobs, keep=keep)

    def slice_written(self, versions: dict[Tile, int]) -> None:
        """Under the volume's lock: the slice's tiles that did not change since they were copied
        are clean now (their stored copy is current; a page-out drops them)."""
        for t, v in versions.items():
            if self.versions.version(t) == v and self._written_version.get(t, -1) >= v:
                self.versions.mark_written({t: v})
                self.location[t] = "own"

    def end_snapshot(self) -> Snapshot:
        """A checkpoint's last step, under the volume's lock: copies of the resident tiles still to
        be written (changed during the passes), the slot table, and a new generation begun for the
        writes that follow; :meth:`committed` once the returned generation is committed."""
        if self.store is None:
            raise RuntimeError("a checkpoint needs a tile store")
        groups = self._resident_groups()
        left = [t for t in groups if self._needs_writing(t)]
        if sum(len(groups[t][1]) for t in left) <= SLICE_BLOCKS:
            tiles, versions = self.copy_tiles(left)
            snap = Snapshot(self.store.begin_generation(), versions, tiles)
        else:  # the passes did not catch up (a camera changing much): bounded memory, a longer lock
            snap = Snapshot(self.store.begin_generation(), {})
            for t in left:
                one, version = self.copy_tiles([t])
                snap.blobs.update(self.encode(one))
                snap.versions.update(version)
                del one
        self._written_version = {}
        snap.slot_table = self.storage.slots.to_array()
        return snap

    def committed(self, snap: Snapshot) -> None:
        """The snapshot's generation is durable: its tiles are clean at the versions copied."""
        self.versions.mark_written(snap.versions)
        for t in snap.versions:  # (snap.tiles is emptied once encoded: its keys were never set here)
            self.location[t] = "own"

    # ------------------------------------------------------------------ key compaction
    def _compact_stored_keys(self, remap: np.ndarray) -> np.ndarray:
        """Rewrite the key slots of every stored tile through ``remap`` (into the generation being
        built: the committed tiles keep the slots the committed table names); returns slots in use."""
        used: list[np.ndarray] = [np.zeros(1, np.int64)]
        if self.store is None:
            return used[0]
        for t in sorted(self.stored_blocks):
            coords, raw = self._read(t)
            raw["key"] = remap[raw["key"]]
            self.stored_slots[t] = np.unique(raw["key"])
            used.append(self.stored_slots[t].astype(np.int64))
            self._written_version[t] = self.versions.version(t)
            self.store.put(t, encode_tile(self.store.codec, coords, raw, self.res))
            self.location[t] = "own"
        self.versions.touch(np.array(list(self.last_used) or np.zeros((0, 3)), np.int64))  # new slots: rewrite
        return np.unique(np.concatenate(used))


def camera_center(T_world_cam: np.ndarray) -> np.ndarray:
    return np.asarray(T_world_cam, np.float64)[:3, 3]


