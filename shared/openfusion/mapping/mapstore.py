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

import logging
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

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


def _summary_arrays(volume: SemanticVolume, regions: RegionTable | None, summary: bool) -> dict[str, np.ndarray]:
    if regions is None and summary:
        surface = volume.extract_points()
        regions = RegionTable.of_points(surface.keys, surface.points)
    if not summary or regions is None:
        return {}
    return {f"summary_{n}": np.ascontiguousarray(getattr(regions, n)) for n in SUMMARY_ARRAYS}


def checkpoint(
    volume: SemanticVolume,
    dictionary: RegionDictionary,
    meta: dict[str, Any],
    *,
    regions: RegionTable | None = None,
    summary: bool = False,
    on_snapshot: Any = None,
) -> dict[str, Any]:
    """An incremental checkpoint into ``volume.store`` (module docstring). ``on_snapshot``: called
    right after the tiles were copied (under the volume's lock), e.g. to release the caller's lock.
    Returns what was written (``tiles``, ``bytes``, ``paged_moved``)."""
    store = volume.store
    if store is None:
        raise ValueError("this volume has no tile store of its own to checkpoint into")
    summaries = _summary_arrays(volume, regions, summary)
    header, arrays = _header(volume, dictionary, meta)
    snap = volume.checkpoint_snapshot()
    if callable(on_snapshot):
        on_snapshot()
    blobs = volume.pager.encode(snap)
    arrays.update(summaries)
    arrays["key_slots"] = snap.slot_table  # type: ignore[assignment]
    arrays["tile_index"] = snap.tile_index  # type: ignore[assignment]
    header["tile_blocks"] = volume.params.tile_blocks
    store.commit(upto_epoch=snap.epoch, blobs=blobs, header=header, arrays=arrays)
    volume.checkpoint_committed(snap)
    written = {"tiles": len(blobs), "bytes": sum(len(b) for b in blobs.values())}
    del snap, blobs
    release_freed_memory()
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
    header, arrays = _header(volume, dictionary, meta)
    header["tile_blocks"] = volume.params.tile_blocks
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=folder))
    try:
        with TileStore(tmp) as store:
            snap = volume.checkpoint_snapshot(full=True)
            blobs = {t: encode_tile(store.codec, c, raw, volume.params.block_resolution) for t, (c, raw) in snap.tiles.items()}
            pager = volume.pager
            for t in list(pager.stored_blocks):  # paged-out tiles: their blobs as they are
                blob, codec_name = pager.blob_of(t)
                if codec_name != store.codec_name:
                    coords, raw = decode_tile(make_codec(codec_name), blob, f"tile {t}")
                    blob = encode_tile(store.codec, coords, raw, volume.params.block_resolution)
                blobs[t] = blob
            arrays.update(summaries)
            arrays["key_slots"] = snap.slot_table  # type: ignore[assignment]
            arrays["tile_index"] = snap.tile_index  # type: ignore[assignment]
            store.commit(upto_epoch=-1, blobs=blobs, header=header, arrays=arrays)
            store.env.sync(True)
        install_store(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def read_header(store: TileStore) -> dict[str, Any]:
    header = store.read_header()
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
    from openfusion.mapping.keyslots import KeySlots
    from openfusion.mapping.volume import SemanticVolume

    header = read_header(store)
    names = dict_names() + ["key_slots", "tile_index"] + summary_names(header)
    arrays = store.read_arrays(names, header)
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
        for t, (coords, raw) in _iter_tiles(store, tiles):
            if len(coords) != tiles[t]:
                raise MapFormatError(f"{store.path}: tile {t} holds {len(coords)} blocks, the index says {tiles[t]}")
            if len(coords) and (raw["key"].shape[1:] != (res, res, res)):
                raise MapFormatError(f"{store.path}: tile {t} has blocks of another resolution")
            volume._storage.write_raw_blocks(coords, raw)
            if own:
                pager.location[t] = -1
        pager.sync_resident()
    return volume, header, arrays


def _iter_tiles(store: TileStore, tiles: dict[tuple[int, int, int], int]) -> Any:
    seen = 0
    for t, blob in store.iter_committed():
        if t not in tiles:
            continue  # a tile of no checkpoint's index (never happens with one writer)
        seen += 1
        yield t, decode_tile(store.codec, blob, f"{store.path} tile {t}")
    if seen != len(tiles):
        raise MapFormatError(f"{store.path}: {len(tiles) - seen} tiles of the index are missing from the store")
