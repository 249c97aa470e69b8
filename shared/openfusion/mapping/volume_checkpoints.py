"""Arrays and checkpoints of the semantic volume: every block as plain arrays (save, load) and the
steps of :func:`openfusion.mapping.mapstore.checkpoint` (a part of
:class:`~openfusion.mapping.volume.SemanticVolume`, split from ``volume.py``; the rules of what a
checkpoint writes are :mod:`.paging`'s)."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

import numpy as np

from openfusion.mapping.paging import Snapshot, TilePager
from openfusion.mapping.storage import VoxelStorage
from openfusion.mapping.volume_locks import locked as _locked
from openfusion.mapping.volume_locks import read_out as _read_out


class VolumeCheckpoints:
    """The arrays and checkpoint half of the volume (mixed into it)."""

    _lock: threading.RLock
    _storage: VoxelStorage
    _pager: TilePager
    # and the volume's _settle_growth() (its grid's background growth settled)

    # ------------------------------------------------------------------ arrays (save / load)
    @_read_out
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Every block (resident and paged out) as plain arrays (``key`` holds real keys, -1 = none)."""
        arrays = self._storage.to_arrays()
        if not self._pager.stored_blocks:
            return arrays
        parts = [arrays, *self._pager.stored_arrays()]
        return {name: np.concatenate([p[name] for p in parts]) for name in arrays}

    def unshared_arrays(self) -> dict[str, np.ndarray]:
        """:meth:`to_arrays` on the calling thread, not as a read-out job: only for a volume no other
        thread can reach yet (a loaded map being moved into another volume by a caller that
        holds a service's lock, which a job may not be asked for under)."""
        with self._lock:
            return VolumeCheckpoints.to_arrays.__wrapped__(self)  # type: ignore[attr-defined]

    @property
    def num_blocks_total(self) -> int:
        """Blocks of the whole map: resident and paged out."""
        return self._storage.num_blocks + sum(self._pager.stored_blocks.values())

    # ------------------------------------------------------------------ checkpoints (tile store)
    # The steps of :func:`openfusion.mapping.mapstore.checkpoint` (the rules: :mod:`.paging`).
    @_locked
    def checkpoint_plan(self, *, every_tile: bool = False) -> list[list[tuple[int, int, int]]]:
        """Slices of the resident tiles a checkpoint must write (``every_tile``: all)."""
        self._settle_growth()
        return self._pager.precopy_plan(every_tile=every_tile)

    @_locked
    def checkpoint_copy(self, tiles: list[tuple[int, int, int]]) -> tuple[dict, dict]:
        """Raw copies of one slice's tiles (still to be written) and their versions."""
        return self._pager.copy_tiles(tiles)

    @_locked
    def checkpoint_slice_written(self, versions: dict[tuple[int, int, int], int]) -> None:
        self._pager.slice_written(versions)

    @_locked
    def checkpoint_end(self) -> Snapshot:
        """A checkpoint's last step (:meth:`~openfusion.mapping.paging.TilePager.end_snapshot`)."""
        self._settle_growth()
        snap = self._pager.end_snapshot()
        snap.tile_index = self._tile_index()
        return snap

    @_locked
    def tile_index(self) -> np.ndarray:
        """int32 (T, 4): every tile of the map (x, y, z, block count)."""
        return self._tile_index()

    def _tile_index(self) -> np.ndarray:
        groups = self._pager._resident_groups()
        rows = [(*t, len(g[1])) for t, g in groups.items()] + [
            (*t, n) for t, n in self._pager.stored_blocks.items()
        ]
        return np.array(sorted(rows), np.int32).reshape(-1, 4)

    @_locked
    def checkpoint_committed(self, snap: Snapshot) -> None:
        """``snap``'s generation is durable in the store (bookkeeping of what is dirty)."""
        self._pager.committed(snap)

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """Hold the volume's lock (nothing changes the map meanwhile): a save into a new store."""
        with self._lock:
            yield
