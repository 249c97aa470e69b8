"""Where the geometry service keeps its map: the tile store in its checkpoint folder, loading it,
and incremental checkpoints (the library calls are in :mod:`openfusion.mapping.mapstore`).

- The volume of a service with a checkpoint folder (``map_dir``/``map_id``) is made with the store
  ``map_dir/map_id/map.ofz`` as its own: tiles paged out under ``memory_budget_mb`` go there,
  and every checkpoint commits into it only the tiles changed since the one before.
- On start it loads that store writable (no tile is read when a memory budget is set: tiles come
  back as frames reach them). An older checkpoint (``map.ofz.npz``, format version 1) is loaded
  as before and the store is attached afterwards; the first checkpoint then writes every tile.
- ``control/load`` of another map folder copies that map's store into the checkpoint folder
  first (a consistent LMDB copy), so the service never writes into a map a user named.
- ``control/reset`` starts a new, empty store.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from openfusion.mapping import SemanticVolume, load_latest_map, load_map
from openfusion.mapping.mapfile import MAP_FILE_NAME, LoadedMap, previous_map_path
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.tilestore import STORE_DIR_NAME, TileStore, find_store

logger = logging.getLogger("openfusion.services.geometry.service")


def store_path(checkpoint_dir: Path) -> Path:
    return checkpoint_dir / STORE_DIR_NAME


def _committed_store(path: Path) -> bool:
    store = find_store(path)
    if store is None:
        return False
    with TileStore(store, readonly=True) as s:
        return s.read_header() is not None


def has_checkpoint(path: Path) -> bool:
    """A loadable map (a committed tile store, or a version-1 file or its ``.prev``) is at ``path``."""
    if _committed_store(path):
        return True
    return (path / MAP_FILE_NAME).is_file() or previous_map_path(path).exists()


def new_volume(params: VolumeParams, checkpoint_dir: Path | None, *, fresh: bool = False) -> SemanticVolume:
    """An empty volume, with the checkpoint folder's store as its own (``fresh``: emptied first)."""
    if checkpoint_dir is None:
        return SemanticVolume(params)
    path = store_path(checkpoint_dir)
    if fresh and path.exists():
        shutil.rmtree(path)
    return SemanticVolume(params, store=TileStore(path))


def load_own(checkpoint_dir: Path, params: VolumeParams, *, fallback: bool) -> LoadedMap:
    """The service's own checkpoint, writable, with this service's device and memory budget."""
    if _committed_store(checkpoint_dir):
        return load_map(checkpoint_dir, device=params.device, writable=True, memory_budget_mb=params.memory_budget_mb)
    # A version-1 checkpoint (an older build): load it, then give the volume its store.
    v1 = checkpoint_dir / MAP_FILE_NAME
    loaded = (load_latest_map if fallback else load_map)(v1, device=params.device)
    loaded.volume = _with_store(loaded.volume, params, checkpoint_dir)
    return loaded


def load_other(path: Path, params: VolumeParams, checkpoint_dir: Path | None) -> LoadedMap:
    """A map a user named: copied into the checkpoint folder first when it is a tile store."""
    source = find_store(path)
    if source is None or checkpoint_dir is None:
        loaded = load_map(path, device=params.device, memory_budget_mb=params.memory_budget_mb
                          if source is not None else "map")
        if checkpoint_dir is not None:
            loaded.volume = _with_store(loaded.volume, params, checkpoint_dir)
        return loaded
    target = store_path(checkpoint_dir)
    with TileStore(source, readonly=True) as store:
        store.copy_to(target)
    return load_own(checkpoint_dir, params, fallback=False)


def _with_store(volume: SemanticVolume, params: VolumeParams, checkpoint_dir: Path) -> SemanticVolume:
    """``volume``'s blocks in a new volume whose own store is the checkpoint folder's (emptied)."""
    arrays = volume.unshared_arrays()  # a volume only this thread knows: no read-out job (the caller holds locks)
    volume.close()
    fresh = new_volume(params, checkpoint_dir, fresh=True)
    if len(arrays["block_coords"]):
        loaded = SemanticVolume.from_arrays(params.with_changes(memory_budget_mb=None), arrays)
        fresh._storage.slots = loaded._storage.slots
        raw_coords, raw_buf = loaded._storage.active_blocks()
        raw = loaded._storage.read_raw_blocks(raw_buf)
        if fresh.budget_blocks is not None and len(raw_coords) > fresh.budget_blocks:
            fresh._storage.reset(capacity=len(raw_coords), keep_slots=True)
        fresh._storage.write_raw_blocks(raw_coords, raw)
        fresh.pager.sync_resident()
        loaded.close()
    return fresh


def validate(path: Path) -> None:
    """Raise :class:`~openfusion.mapping.MapFormatError` unless ``path`` holds a readable map (a
    store's header and arrays, without reading its tiles; a version-1 file whole)."""
    loaded = load_map(path, memory_budget_mb=64.0) if find_store(path) is not None else load_map(path)
    loaded.volume.close()


def reopen(params: VolumeParams, checkpoint_dir: Path | None) -> SemanticVolume:
    """After a failed load: the last committed checkpoint of the folder, or an empty map."""
    if checkpoint_dir is not None and _committed_store(checkpoint_dir):
        return load_own(checkpoint_dir, params, fallback=False).volume
    return new_volume(params, checkpoint_dir)
