"""Growing the grid without a whole-grid copy under the lock integration waits on.

Open3D grows a ``VoxelBlockGrid`` inside ``integrate`` when the blocks in use plus the blocks it is
given exceed its capacity: it doubles the hash map and copies every block while the caller waits
(about 0.5 s for 16k blocks of 28 B voxels on two cores; the ScanNet office floor of issue 33 did
three such doublings, 16k -> 128k blocks, and integration fell to 3 frames/s). Without a memory
budget the map must grow, so :class:`GridGrower` grows it *ahead* of need, in the background:

1. When the grid is half full (:data:`START_AT`), a thread takes a snapshot under the volume's lock
   (the active blocks, and the tile clock of :class:`~openfusion.mapping.tiles.TileVersions`),
   then, without the lock, allocates a grid of twice the capacity, activates the snapshot's blocks
   there and copies their values chunk by chunk while integration goes on in the old grid.
2. When the copy is done, :meth:`GridGrower.finish` (called by the volume, under its lock, before
   the next frame) copies again only what changed meanwhile: the blocks of tiles touched after the
   snapshot (integration, semantic updates) and blocks created after it, then swaps the grids.
   The lock is held for what changed during the copy, not for the map.

The old grid must not be rehashed by Open3D while the thread reads it (its buffers would move): a
frame that would fill the old grid waits for the copy to end first (``stats.waits``; with the copy
started at half full, a map has to double its blocks within one copy for that to happen). Key slots
need nothing: the slot table is the storage's, shared by both grids.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from openfusion.mapping.storage import ATTR_NAMES, VoxelStorage
from openfusion.mapping.tiles import TileGrid, TileVersions, pack_coords

logger = logging.getLogger(__name__)

START_AT = 0.5  # start growing when this share of the capacity is in use
#: Past this capacity (blocks) the first growth also says, once, what a grid this large costs every
#: render: Open3D 0.20's CPU ray cast copies the grid's whole block hash map on every call, so a
#: render of a 90,000-block map costs about 10x one of a room's (docs/EVAL.md, "Scoring cost
#: against the gt encoder"); a memory budget keeps the grid small.
RENDER_COST_HINT_BLOCKS = 65536
_CHUNK = 4096  # blocks copied per step


@dataclass
class GrowthStats:
    grows: int = 0
    waits: int = 0  # frames that waited for a copy to end (the old grid would have filled)
    sync_grows: int = 0  # frames that overflowed the grid at once: Open3D grew it under the lock
    last_copy_s: float = 0.0  # the background copy
    last_swap_s: float = 0.0  # the part under the lock


class GridGrower:
    """Background growth of one storage's grid (module docstring). The owner calls
    :meth:`before_integrate` under its lock before every integration."""

    def __init__(self, storage: VoxelStorage, versions: TileVersions, grid: TileGrid) -> None:
        self.storage = storage
        self.versions = versions
        self.grid = grid
        self.stats = GrowthStats()
        self._thread: threading.Thread | None = None
        # A flag, not "the growth that crosses the threshold": Open3D may have grown the grid past it
        # itself (a frame that overflowed it, ``sync_grows``), and then no background growth crosses it.
        self._render_hint_given = False
        self._done = threading.Event()
        self._new = None
        self._snap_coords = np.zeros((0, 3), np.int32)
        self._snap_clock = 0
        self._error: BaseException | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None

    def settle(self) -> None:
        """Under the owner's lock: swap in a copy that has finished (so a map that stops growing
        does not keep two grids), without waiting for one that has not."""
        if self._thread is not None and self._done.is_set():
            self._finish()

    def before_integrate(self, blocks_given: int) -> None:
        """Under the owner's lock: swap in a finished copy; wait for one that must finish before
        this frame (the old grid would fill); start one when the grid is half full."""
        s = self.storage
        if self._thread is not None:
            if self._done.is_set():
                self._finish()
            elif s.num_blocks + blocks_given > s.capacity_blocks:
                self.stats.waits += 1
                self._done.wait()
                self._finish()
        need = s.num_blocks + blocks_given
        if need > s.capacity_blocks:
            # This frame alone overflows the grid: Open3D grows it now (a copy under the lock, counted);
            # no copy may read the grid meanwhile, so the next one starts with the next frame.
            self.stats.sync_grows += 1
            return
        if self._thread is None and need > START_AT * s.capacity_blocks:
            self._start()

    def _start(self) -> None:
        s = self.storage
        coords, buf = s.active_blocks()
        self._snap_coords = coords.copy()
        snap_buf = buf.copy()
        self._snap_clock = self.versions.clock
        self._snap_compactions = s.compactions
        self._done.clear()
        self._error = None
        capacity = 2 * s.capacity_blocks
        self._thread = threading.Thread(
            target=self._copy, args=(s.vbg, self._snap_coords, snap_buf, capacity), name="grid-grow", daemon=True
        )
        self._started_at = time.perf_counter()
        self._thread.start()

    def _copy(self, old_vbg: object, coords: np.ndarray, buf: np.ndarray, capacity: int) -> None:
        try:
            new = self.storage.new_grid(capacity)
            old, tmp = _view(self.storage, old_vbg), _view(self.storage, new)
            for i in range(0, len(coords), _CHUNK):
                _write_raw(tmp, coords[i : i + _CHUNK], old.read_raw_blocks(buf[i : i + _CHUNK]))
            self._new = new
        except BaseException as exc:  # reported on the owner's thread by _finish
            self._error = exc
        finally:
            self._done.set()

    def _finish(self) -> None:
        thread, self._thread = self._thread, None
        assert thread is not None
        thread.join()
        copy_s = time.perf_counter() - self._started_at
        if self._error is not None or self._new is None:
            logger.warning("background grid growth failed (%s); Open3D grows the grid when it fills", self._error)
            self._new = None
            return
        t0 = time.perf_counter()
        s = self.storage
        new = self._new
        self._new = None
        coords, buf = s.active_blocks()
        # Blocks to copy again: those of tiles changed after the snapshot, and blocks made since.
        changed_tiles = [t for t, v in self.versions._version.items() if v > self._snap_clock]
        in_snap = np.isin(pack_coords(coords), pack_coords(self._snap_coords))
        redo = ~in_snap
        if s.compactions != self._snap_compactions:  # every key slot was rewritten meanwhile
            redo[:] = True
        if changed_tiles:
            tiles = self.grid.tiles_of_blocks(coords)
            redo |= np.isin(pack_coords(tiles), pack_coords(np.array(changed_tiles, np.int64)))
        tmp = _view(s, new)
        new_blocks = coords[~in_snap]
        if len(new_blocks):
            _activate(tmp, new_blocks)
        idx = np.flatnonzero(redo)
        for i in range(0, len(idx), _CHUNK):
            sel = idx[i : i + _CHUNK]
            _write_existing(tmp, coords[sel], s.read_raw_blocks(buf[sel]))
        s.replace_grid(new)
        capped = s.clamp_weights()  # a cap that ran on the old grid during the copy may have been missed
        if len(capped):
            self.versions.touch(self.grid.tiles_of_blocks(s.block_coords_of_buf(capped)))
        self.stats.grows += 1
        self.stats.last_copy_s = copy_s
        self.stats.last_swap_s = time.perf_counter() - t0
        logger.info("grid grown to %d blocks in the background (copy %.2f s, %d blocks copied again under the "
                    "lock in %.3f s)", s.capacity_blocks, copy_s, len(idx), self.stats.last_swap_s)
        if s.capacity_blocks >= RENDER_COST_HINT_BLOCKS and not self._render_hint_given:
            self._render_hint_given = True
            logger.info("the grid holds %d blocks with no memory budget: every render of the map (the semantic "
                        "service's scoring and update renders) now costs in proportion to them (Open3D's CPU ray "
                        "cast copies the grid's block hash map on every call); a memory budget "
                        "(geometry.memory_budget_mb) bounds it", s.num_blocks)

    def close(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
            self._new = None


def _view(storage: VoxelStorage, vbg: object) -> VoxelStorage:
    """A shallow copy of ``storage`` over another grid (reads and writes of raw blocks only; the
    storage itself is never touched from the copying thread)."""
    view = VoxelStorage.__new__(VoxelStorage)
    view.__dict__.update(storage.__dict__)
    view.vbg = vbg  # type: ignore[assignment]
    view._capacity = vbg.hashmap().capacity()  # type: ignore[attr-defined]
    return view


def _activate(storage: VoxelStorage, coords: np.ndarray) -> None:
    import open3d.core as o3c

    storage.vbg.hashmap().activate(o3c.Tensor(np.ascontiguousarray(coords, np.int32), device=storage.device))


def _write_raw(storage: VoxelStorage, coords: np.ndarray, raw: dict[str, np.ndarray]) -> None:
    _activate(storage, coords)
    _write_existing(storage, coords, raw)


def _write_existing(storage: VoxelStorage, coords: np.ndarray, raw: dict[str, np.ndarray]) -> None:
    import open3d.core as o3c

    buf = storage.find_blocks(coords)
    if (buf < 0).any():
        raise RuntimeError("grid growth: a block to copy is missing from the new grid")
    idx = o3c.Tensor(buf, device=storage.device)
    for name in ATTR_NAMES:
        arr = np.ascontiguousarray(raw[name])
        if name != "color":
            arr = arr[..., None]
        if storage.use_numpy_views:
            storage.vbg.attribute(name).numpy()[buf] = arr
        else:
            storage.vbg.attribute(name)[idx] = o3c.Tensor(arr, device=storage.device)
