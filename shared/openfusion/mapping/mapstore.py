"""Map files, format version 2: a map folder holding a tile store (:mod:`openfusion.mapping.tilestore`).

A map folder ``DIR`` holds ``DIR/map.ofz/`` (an LMDB environment: ``data.mdb``, ``lock.mdb``). Its
committed state is one checkpoint: the header (format ``openfusion-z-map``, ``format_version`` 2,
volume parameters, dictionary scalars, the caller's meta, the relevancy calibration, the codec),
the dictionary arrays (``dict_keys``, ``dict_mean_embeddings``, ``dict_counts``), the key-slot
table (``key_slots``, :mod:`openfusion.mapping.keyslots`), the tile index (``tile_index``: every
tile and its block count), the region summaries (``summary_*``, optional as in version 1) and the
tiles. :func:`openfusion.mapping.mapfile.load_map_summary` reads the header, dictionary and
summaries only (no tile, no Open3D).

Writing
    :func:`checkpoint` -- into the volume's own store, incrementally: only the tiles changed since
    the last checkpoint are encoded and written, plus the tiles paged out since (moved, not
    re-encoded), in one LMDB transaction with the header, so its cost follows what changed, not
    the size of the map. A crash (``kill -9``) at any instant leaves the previous checkpoint whole.
    :func:`save_store` -- to another folder: a checkpoint of the volume's own store (when it has
    one) copied with ``Environment.copy`` (consistent, compacted), else every tile written into a
    new store; either way written beside the target and renamed into place
    (:func:`~openfusion.mapping.tilestore.install_store`).

Reading (:func:`load_store`)
    Without a memory budget every tile is read into the grid (as version 1 maps are). With one
    (``memory_budget_mb`` of the map's parameters or the caller's), no tile is read at load: the
    tiles stay in the store and are paged in when a frame, a render or a read-out reaches them.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from openfusion.mapping import readout_worker
from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.errors import MapFormatError
from openfusion.mapping.heap import release_freed_memory
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.queries import RegionTable
from openfusion.mapping.relevancy import calibration_for
from openfusion.mapping.tilestore import (
    STORE_DIR_NAME,
    TileStore,
    decode_tile,
    encode_tile,
    install_store,
    make_codec,
)

if TYPE_CHECKING:
    from openfusion.mapping.volume import SemanticVolume

logger = logging.getLogger(__name__)

FORMAT_NAME = "openfusion-z-map"
STORE_FORMAT_VERSION = 2
_DICT_ARRAYS = ("keys", "mean_embeddings", "counts")
SUMMARY_ARRAYS = ("keys", "num_points", "centroid", "bbox_min", "bbox_max")


def _header(volume: SemanticVolume, dictionary: RegionDictionary, meta: dict[str, Any]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    snap = dictionary.snapshot()
    header = {
        "format": FORMAT_NAME,
        "format_version": STORE_FORMAT_VERSION,
        "created_unix_s": time.time(),
        "volume_params": volume.params.to_dict(),
        "dictionary": {
            "embedding_space": snap.embedding_space,
            "dim": snap.dim,
            "version": snap.version,
            "next_key": snap.next_key,
            "labels": [label or None for label in snap.labels],
        },
        "meta": meta,
        "relevancy": calibration_for(snap.embedding_space).to_dict(),
    }
    arrays = {
        "dict_keys": snap.keys.astype(np.int64),
        "dict_mean_embeddings": snap.embeddings.astype(np.float32),
        "dict_counts": snap.counts.astype(np.int64),
    }
    return header, arrays


def _summary_arrays(volume: SemanticVolume, regions: RegionTable | None, summary: bool, lock: Any = None) -> dict[str, np.ndarray]:
    if regions is None and summary:
        regions = volume.region_table(lock=lock)  # per tile, cached: only changed tiles are read out
    if not summary or regions is None:
        return {}
    return {f"summary_{n}": np.ascontiguousarray(getattr(regions, n)) for n in SUMMARY_ARRAYS}


#: Passes over the changed tiles before a checkpoint's last step (each copies again what the
#: camera changed during the one before); more (up to :data:`PRECOPY_PASSES_MAX`) only while each
#: pass leaves fewer tiles than the one before. The last step copies what is left under the lock,
#: and encodes it tile by tile when more than a slice is left (a checkpoint of 561 tiles on the
#: 10-room walk through the services had left +220 MiB of copies to it). Up to 6 passes made
#: checkpoints on a 40 MiB budget take 5-7 s instead of 1.5-3.5 (the camera changes a slice's worth
#: again during each pass): kept at 3, the tile-by-tile last step bounds the memory.
PRECOPY_PASSES = 3
PRECOPY_PASSES_MAX = 3

HeaderState = Callable[[], tuple[RegionDictionary, dict[str, Any]]]


def checkpoint(
    volume: SemanticVolume,
    dictionary: RegionDictionary | None,
    meta: dict[str, Any] | None,
    *,
    regions: RegionTable | None = None,
    summary: bool = False,
    lock: Any = None,
    state: HeaderState | None = None,
) -> dict[str, Any]:
    """An incremental checkpoint into ``volume.store`` (module docstring; the slices and the last
    step: :mod:`openfusion.mapping.paging`). ``lock``: a context manager held, with the volume's
    own lock, while tiles are copied and during the last step (a service's lock, so the
    checkpoint's instant is one of its states too); ``state``: called in the last step, returns
    ``(dictionary, meta)`` as of that instant (else ``dictionary`` and ``meta`` are used).
    Returns what was written (``tiles``, ``bytes``, ``slices``)."""
    store = volume.store
    if store is None:
        raise ValueError("this volume has no tile store of its own to checkpoint into")
    readout_worker.check_caller("checkpoint")
    guard = lock if lock is not None else contextlib.nullcontext()
    summaries = _summary_arrays(volume, regions, summary, lock=lock)
    pager = volume.pager
    written = {"tiles": 0, "bytes": 0, "slices": 0}

    def one_slice(tiles: list[tuple[int, int, int]]) -> tuple[int, int]:
        """Copy (under the locks), encode and write one slice (a read-out job)."""
        with guard:
            copies, versions = volume.checkpoint_copy(tiles)
        if not copies:
            return 0, 0
        blobs = pager.encode(copies)
        del copies
        n = pager.write_slice(blobs, versions)
        nbytes = sum(len(b) for b in blobs.values())
        del blobs
        volume.checkpoint_slice_written(versions)
        return n, nbytes

    def last_step() -> tuple[int, int]:
        """The checkpoint's instant (under the locks), then its encoding and commit (a read-out job)."""
        nonlocal dictionary, meta
        with guard:
            if state is not None:
                dictionary, meta = state()
            header, arrays = _header(volume, dictionary or RegionDictionary("none", 1), meta or {})
            snap = volume.checkpoint_end()
        blobs = pager.encode(snap.tiles)
        blobs.update(snap.blobs)
        snap.tiles.clear()
        snap.blobs.clear()
        arrays.update(summaries)
        arrays["key_slots"] = snap.slot_table  # type: ignore[assignment]
        arrays["tile_index"] = snap.tile_index  # type: ignore[assignment]
        header["tile_blocks"] = volume.params.tile_blocks
        store.commit(generation=snap.generation, blobs=blobs, header=header, arrays=arrays)
        volume.checkpoint_committed(snap)
        got = (len(blobs), sum(len(b) for b in blobs.values()))
        del snap, blobs
        release_freed_memory()
        return got

    # Every slice and the last step is one job on the read-out worker (one chunk in hand in the
    # process at a time: openfusion.mapping.readout_worker); the caller holds no lock meanwhile.
    left = None
    for n in range(PRECOPY_PASSES_MAX):
        with guard:
            plan = volume.checkpoint_plan()
        if not plan or (n > 0 and len(plan) == 1):
            break  # what is left is small: the last step copies it
        tiles_left = sum(len(s) for s in plan)
        if n >= PRECOPY_PASSES and left is not None and tiles_left >= left:
            break  # the passes no longer catch up: the last step encodes what is left tile by tile
        left = tiles_left
        for tiles in plan:
            n_tiles, n_bytes = readout_worker.run("checkpoint", one_slice, tiles)
            if n_tiles or n_bytes:
                written["tiles"] += n_tiles
                written["bytes"] += n_bytes
                written["slices"] += 1
    n_tiles, n_bytes = readout_worker.run("checkpoint", last_step)
    written["tiles"] += n_tiles
    written["bytes"] += n_bytes
    return written


def save_store(
    folder: str | os.PathLike[str],
    volume: SemanticVolume,
    dictionary: RegionDictionary,
    meta: dict[str, Any],
    *,
    regions: RegionTable | None = None,
    summary: bool = True,
) -> Path:
    """Write the map to ``folder/map.ofz`` (module docstring, "Writing"); returns that path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / STORE_DIR_NAME
    own = volume.store
    if own is not None and os.path.realpath(own.path) == os.path.realpath(target):
        checkpoint(volume, dictionary, meta, regions=regions, summary=summary)
        return target
    if own is not None:
        checkpoint(volume, dictionary, meta, regions=regions, summary=summary)
        return own.copy_to(target)
    summaries = _summary_arrays(volume, regions, summary)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=folder))
    try:
        readout_worker.run("save", _write_new_store, tmp, volume, dictionary, meta, summaries)
        install_store(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    release_freed_memory()
    return target


def _write_new_store(tmp: Path, volume: SemanticVolume, dictionary: RegionDictionary, meta: dict[str, Any],
                     summaries: dict[str, np.ndarray]) -> None:
    """Every tile of ``volume`` into a new store at ``tmp`` (a read-out job: :func:`save_store`)."""
    with TileStore(tmp) as store, volume.locked():
        # The volume is locked throughout (nothing changes); tiles are copied, encoded and
        # written a slice at a time, so the save never holds the map twice.
        header, arrays = _header(volume, dictionary, meta)
        header["tile_blocks"] = volume.params.tile_blocks
        res = volume.params.block_resolution
        pager = volume.pager
        for tiles in volume.checkpoint_plan(every_tile=True):
            copies = pager.copy_tiles(tiles, every_tile=True)[0]
            store.put_many({t: encode_tile(store.codec, c, raw, res) for t, (c, raw) in copies.items()})
            del copies
        stored = sorted(pager.stored_blocks)
        for i in range(0, len(stored), 64):  # paged-out tiles: their blobs as they are
            blobs = {}
            for t in stored[i : i + 64]:
                blob, codec_name = pager.blob_of(t)
                if codec_name != store.codec_name:
                    coords, raw = decode_tile(make_codec(codec_name), blob, f"tile {t}")
                    blob = encode_tile(store.codec, coords, raw, res)
                blobs[t] = blob
            store.put_many(blobs)
        arrays.update(summaries)
        arrays["key_slots"] = volume._storage.slots.to_array()
        arrays["tile_index"] = volume.tile_index()
        store.commit(blobs={}, header=header, arrays=arrays)
        store.env.sync(True)


def header_meta(header: dict[str, Any]) -> dict[str, Any]:
    """The caller's meta a map header holds, with the map's ``created_unix_s``."""
    meta = dict(header.get("meta", {}))
    meta.setdefault("created_unix_s", header.get("created_unix_s"))
    return meta


def read_header(store: TileStore) -> dict[str, Any]:
    return check_header(store, store.read_header())


def check_header(store: TileStore, header: dict[str, Any] | None) -> dict[str, Any]:
    """``header`` when it is one of a map this build reads; :class:`MapFormatError` else."""
    if header is None:
        raise MapFormatError(f"{store.path}: the tile store holds no checkpoint yet")
    if header.get("format") != FORMAT_NAME:
        raise MapFormatError(f"{store.path}: format {header.get('format')!r} is not {FORMAT_NAME!r}")
    if header.get("format_version") != STORE_FORMAT_VERSION:
        raise MapFormatError(
            f"{store.path}: map format version {header.get('format_version')} is not supported "
            f"(this build reads 1 and {STORE_FORMAT_VERSION})"
        )
    return header


def summary_names(header: dict[str, Any]) -> list[str]:
    names = [f"summary_{n}" for n in SUMMARY_ARRAYS]
    return names if any(n in header.get("arrays", {}) for n in names) else []


def dict_names() -> list[str]:
    return [f"dict_{n}" for n in _DICT_ARRAYS]


def load_store(
    store: TileStore, *, device: str | None = None, memory_budget_mb: float | None | str = "map"
) -> tuple[SemanticVolume, dict[str, Any], dict[str, np.ndarray]]:
    """``(volume, header, arrays)`` of a store's last checkpoint (module docstring, "Reading").

    ``memory_budget_mb``: ``"map"`` keeps the map's own; a number or None replaces it. A writable
    ``store`` becomes the volume's own (checkpoints go there); a read-only one is read from only."""
    def names(header: dict[str, Any] | None) -> list[str]:
        check_header(store, header)
        return dict_names() + ["key_slots", "tile_index"] + summary_names(header)  # type: ignore[arg-type]

    # Header, arrays and (without a budget) every tile from one read transaction: a writer
    # committing meanwhile (a running geometry's own store) changes none of them.
    header, arrays, committed = store.read_committed(names)
    header = check_header(store, header)
    try:
        return _load(store, header, arrays, committed, device, memory_budget_mb)
    finally:
        committed.close()


def _load(store: TileStore, header: dict[str, Any], arrays: dict[str, np.ndarray], committed: Any,
          device: str | None, memory_budget_mb: float | None | str) -> tuple[SemanticVolume, dict[str, Any], dict[str, np.ndarray]]:
    from openfusion.mapping.keyslots import KeySlots
    from openfusion.mapping.volume import SemanticVolume

    try:
        params = VolumeParams.from_dict(header["volume_params"])
        changes: dict[str, Any] = {}
        if device is not None:
            changes["device"] = device
        if memory_budget_mb != "map":
            changes["memory_budget_mb"] = memory_budget_mb
        if changes:
            params = params.with_changes(**changes)
        slots = KeySlots.from_array(arrays["key_slots"])
    except (ValueError, KeyError, TypeError) as exc:
        raise MapFormatError(f"{store.path}: inconsistent map header ({exc})") from exc
    index = arrays["tile_index"]
    if index.ndim != 2 or index.shape[1] != 4:
        raise MapFormatError(f"{store.path}: tile index must be (T, 4), got {index.shape}")
    tiles = {(int(r[0]), int(r[1]), int(r[2])): int(r[3]) for r in index}
    own = not store.readonly
    volume = SemanticVolume(params, store=store if own else None)
    volume._storage.slots = slots
    pager = volume.pager
    if params.memory_budget_mb is not None:
        pager.adopt_store(store, tiles, as_base=not own)
    else:
        total = sum(tiles.values())
        if total > volume._storage.capacity_blocks:
            volume._storage.reset(capacity=total, keep_slots=True)
        res = params.block_resolution
        for t, (coords, raw) in _iter_tiles(store, tiles, committed):
            if len(coords) != tiles[t]:
                raise MapFormatError(f"{store.path}: tile {t} holds {len(coords)} blocks, the index says {tiles[t]}")
            if len(coords) and (raw["key"].shape[1:] != (res, res, res)):
                raise MapFormatError(f"{store.path}: tile {t} has blocks of another resolution")
            volume._storage.write_raw_blocks(coords, raw)
            if own:
                pager.location[t] = "own"
        pager.sync_resident()
    return volume, header, arrays


def _iter_tiles(store: TileStore, tiles: dict[tuple[int, int, int], int], committed: Any) -> Any:
    seen = 0
    for t, blob in committed:
        if t not in tiles:
            continue  # a tile of no checkpoint's index (never happens with one writer)
        seen += 1
        yield t, decode_tile(store.codec, blob, f"{store.path} tile {t}")
    if seen != len(tiles):
        raise MapFormatError(f"{store.path}: {len(tiles) - seen} tiles of the index are missing from the store")
