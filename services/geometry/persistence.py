"""Saves, checkpoints and loads of the geometry service's map (a part of
:class:`~openfusion.services.geometry.service.GeometryService`, apart from its frames and
requests; the state it works on, ``_lock``, ``_swap_lock``, ``volume``, ``replica``, ``robots``,
``_runner``..., is the service's).

Checkpoints go to the tile store ``{map_dir}/{map_id}/map.ofz`` (:mod:`.checkpoints`,
:mod:`openfusion.mapping.mapstore`): the tiles changed since the last one are copied under the
lock, then encoded and committed in one LMDB transaction while integration goes on; the
checkpoint's meta (``frames_integrated``, ``last_frame_id``, each robot's chain) describes the
instant of its last step. A checkpoint that fails with an ``OSError`` is logged in one line, counted
(``checkpoint_failures``) and raised as :class:`CheckpointFailed`; the map stays in memory. A load
refuses a bad map before the current one is let go. The service's module docstring has the whole
story (periodic checkpoints, ``control/save``, the shutdown checkpoint, resume).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

from openfusion.bus import RequestError
from openfusion.mapping import RegionDictionary, SemanticVolume, readout_worker, save_map
from openfusion.mapping.mapfile import resolve_map_path
from openfusion.mapping.mapstore import checkpoint as checkpoint_store
from openfusion.mapping.queries import RegionTable
from openfusion.mapping.tilestore import STORE_DIR_NAME
from openfusion.services.geometry import checkpoints
from openfusion.services.geometry.parts import ServiceParts, logger
from openfusion.services.geometry.section import SummaryCache
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.schemas.base import DEFAULT_ROBOT

if TYPE_CHECKING:
    pass


NO_EMBEDDING_SPACE = "none"
NO_FRAME_ID = -1  # the checkpoint_last_frame_id counter when no checkpoint records one


class CheckpointFailed(RequestError):
    """A checkpoint could not be written (``OSError``: disk full, read-only folder); already
    logged and counted. The in-memory map is unchanged."""

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__("checkpoint_failed", f"checkpoint to {path} failed: {reason}; the map is kept in memory")
        self.path = path


def has_checkpoint(path: Path) -> bool:
    """A checkpoint (a committed tile store, or a version-1 file or the one before it) is at ``path``."""
    return checkpoints.has_checkpoint(path)


class MapPersistence(ServiceParts):
    """The save and load half of the geometry service (mixed into it)."""

    _swap_lock: threading.Lock
    checkpoint_dir: Path | None
    checkpoint_last_frame_id: int | None
    checkpoint_failures: int
    map_version: int
    saving: bool
    _key_horizon: int
    _summary: SummaryCache | None
    _last_checkpoint: float
    # and the service's helpers (parts.py)

    def _load(self, path: Path, *, fallback: bool = False, restore_counts: bool = False) -> None:
        """Load a map file; ``fallback``: a checkpoint of ours, the ``.prev`` one when the newest is bad;
        ``restore_counts``: (a restart) take ``frames_integrated`` and ``integrate_busy_s`` from it."""
        params = self.section.volume_params()
        own = self.checkpoint_dir is not None and Path(path).resolve() == self.checkpoint_dir.resolve()
        if not own:
            checkpoints.validate(path)  # a bad map is refused before the current one is let go
        with self._lock:
            # The checkpoint folder's store is reopened (own) or replaced (a copy of the other map).
            self.volume.close()
            try:
                loaded = (checkpoints.load_own(path, params, fallback=fallback) if own
                          else checkpoints.load_other(path, params, self.checkpoint_dir))
            except BaseException:
                self.volume = checkpoints.reopen(params, self.checkpoint_dir)
                self._map_changed(reset_keys=True)
                raise
        if restore_counts:
            self.frames_integrated = int(loaded.meta.get("frames_integrated") or 0)
            self.integrate_busy_s = float(loaded.meta.get("integrate_busy_s") or 0.0)
        with self._lock:
            if self.volume is not loaded.volume:
                self.volume.close()
            self.volume = loaded.volume
            has_semantics = loaded.dictionary.embedding_space != NO_EMBEDDING_SPACE
            self.replica.reset(loaded.dictionary if has_semantics else None)
            self.robots.restore(loaded.meta, default_robot=DEFAULT_ROBOT)
            first = self._first_robot()
            self.checkpoint_last_frame_id = None if first is None else first.map_last_frame_id
            self._map_changed(reset_keys=True)
            self._dirty = False
        self._set_checkpoint_frame()
        logger.info(
            "geometry: loaded map %s (%d blocks, %d regions, last frame %s)",
            loaded.path or path,
            self.volume.num_blocks,
            len(loaded.dictionary) if loaded.dictionary is not None else 0,
            "none" if self.checkpoint_last_frame_id is None else self.checkpoint_last_frame_id,
        )

    def save(self, path: Path | None = None, *, summary: bool = True) -> Path:
        """Save the map to ``path`` or checkpoint it into the checkpoint folder's store. ``summary=False``
        (the periodic checkpoints) leaves out the region summaries unless they are at hand for this
        map version; a save asked for on ``control/save`` stores them (kept per tile: only tiles
        changed since they were last read out are read again, :mod:`openfusion.mapping.tilereadouts`).
        Integration goes on while a checkpoint writes: the lock is held for a slice's copy and the
        checkpoint's last step (:mod:`openfusion.mapping.mapstore`), whose instant the checkpoint's
        meta (``last_frame_id``...) describes."""
        target = path or self.checkpoint_dir
        if target is None:
            raise RequestError(
                "no_map_dir", "no path given and the geometry service has no map_dir configured"
            )
        own = self.checkpoint_dir is not None and Path(target).resolve() == self.checkpoint_dir.resolve()
        started = time.monotonic()
        captured: dict[str, int | None] = {}

        def state() -> tuple[RegionDictionary, dict[str, object]]:
            """The checkpoint's instant (called holding the lock): what it holds, and the map clean."""
            first = self._first_robot()
            # The map's chain for readers from before robots: its first robot's.
            last = None if first is None else first.map_last_frame_id
            captured["last"] = last
            self._dirty = False  # a change after this sets it again
            meta = {
                "map_id": self.config.map_id,
                "frames_integrated": self.frames_integrated,
                "integrate_busy_s": self.integrate_busy_s,
                "last_frame_id": last,
                "playback": "" if first is None else first.map_playback,
                **self.robots.to_meta(),  # each robot's chain and transform, in the same snapshot
            }
            # A geometry-only map (semantics off) is saved with an empty placeholder dictionary.
            return self.replica.dictionary or RegionDictionary(NO_EMBEDDING_SPACE, 1), meta

        with self._swap_lock:  # a load or reset waits for the save (the volume stays the same)
            self._set_saving(True)
            try:
                with self._lock:
                    volume, version = self.volume, self.map_version
                regions = self._regions_for_save(volume, version, compute=summary)
                tiles = 0
                store = volume.store
                if store is not None and (own or Path(target).suffix != ".npz"):
                    info = checkpoint_store(volume, None, None, regions=regions, summary=regions is not None,
                                            lock=self._lock, state=state)
                    tiles = int(info["tiles"])
                    written = store.path if own else store.copy_to(Path(target) / STORE_DIR_NAME)
                else:  # no store of its own (no map_dir), or a version-1 file named: under the lock, one read-out job
                    def save_locked() -> Path:
                        with self._lock:
                            dictionary, meta = state()
                            return save_map(target, volume, dictionary, meta=meta, regions=regions,
                                            summary=regions is not None)

                    written = readout_worker.run("save", save_locked)
            except OSError as exc:
                # Disk full, read-only folder...: the store (or file) is as it was before; the map
                # stays in memory and the next period tries again.
                self._dirty = True
                self._last_checkpoint = time.monotonic()
                self.checkpoint_failures += 1
                self._count(GeometryCounter.CHECKPOINT_FAILURES)
                failed = resolve_map_path(target)
                reason = exc.strerror or str(exc)
                logger.error("geometry: checkpoint to %s failed: %s; the map is kept in memory", failed, reason)
                raise CheckpointFailed(failed, reason) from exc
            except BaseException:
                self._dirty = True  # not saved: the next period tries again
                raise
            finally:
                self._set_saving(False)
        last = captured.get("last")
        self.checkpoint_last_frame_id = last
        self._last_checkpoint = time.monotonic()
        self._count(GeometryCounter.CHECKPOINTS)
        self._set_checkpoint_frame()
        if self._runner is not None:
            self._runner.stats.set(GeometryCounter.CHECKPOINT_LAST_S, self._last_checkpoint - started)
            self._runner.stats.set(GeometryCounter.CHECKPOINT_LAST_TILES, tiles)
        logger.info("geometry: saved map to %s (last frame %s, %d tiles written, %.2f s)", written,
                    "none" if last is None else last, tiles, self._last_checkpoint - started)
        return Path(written)

    def _regions_for_save(self, volume: SemanticVolume, version: int, *, compute: bool) -> RegionTable | None:
        """The region table a save stores: the cached one of this map version, else (``compute``)
        the volume's, kept as the cache (the queries after a save, e.g. the end of ``openfusion
        run``, are answered from it)."""
        cached = self._summary
        if cached is not None and cached.map_version == version:
            return cached.table
        if not compute:
            return None
        table = volume.region_table(lock=self._lock)
        horizon = max(self._key_horizon, int(table.keys[-1]) + 1 if len(table) else 0)
        with self._lock:
            if self.volume is volume:
                self._summary = SummaryCache(version, horizon, table)
        return table

    def _set_saving(self, saving: bool) -> None:
        self.saving = saving
        if self._runner is not None:
            self._runner.stats.set(GeometryCounter.SAVING, 1 if saving else 0)

    def _set_checkpoint_frame(self) -> None:
        if self._runner is not None:
            last = self.checkpoint_last_frame_id
            self._runner.stats.set(GeometryCounter.CHECKPOINT_LAST_FRAME_ID, NO_FRAME_ID if last is None else last)

