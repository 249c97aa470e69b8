"""A map saved by geometry shards, read under a memory budget: its parts merged into one tile store.

:func:`openfusion.mapping.shardmaps.load_sharded` without a budget reads every part's tiles into
one resident volume. A building split across shards is read on a smaller host too (``openfusion
query --map-dir``, ``eval``, mesh export), so with a budget (the parts' own, ``"map"``, or the
caller's) the parts are merged here instead:

- every tile a part *owns* (:func:`~openfusion.mapping.shards.shard_of_tiles`; a part's other
  tiles hold only its ghosts) is written, one tile at a time, into one scratch tile store with one
  key-slot table (:mod:`openfusion.mapping.keyslots`): a tile whose slots mean the same in the
  merged table (the first part's table is the merged table's start) is copied as its blob; any
  other is decoded, its slots rewritten, and encoded again;
- the header is the first part's with the merged meta (``last_frame_id`` the parts' smallest,
  ``geometry_shards``), the dictionary of the most advanced part (every shard follows the same
  deltas), the merged key slots and tile index, and the parts' region summaries merged
  (:func:`~openfusion.mapping.shards.merge_region_tables`) when every part has them;
- the store is then read as any map under a budget (:mod:`openfusion.mapping.mapstore`): no tile
  is read at load; tiles page in when a read-out reaches them.

Memory while merging: one tile's blocks (and the tile index and key tables). Disk: about the parts'
size, in a temporary folder (``TMPDIR``) removed when the volume is collected or the process ends.
Written by hand because it is the tile store's own format (no library merges LMDB stores with
a key-slot rewrite); the reading and writing themselves are :mod:`openfusion.mapping.tilestore`'s.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import Any

import numpy as np

from openfusion.mapping.errors import MapFormatError
from openfusion.mapping.keyslots import KeySlots
from openfusion.mapping.mapstore import check_header, dict_names, summary_names
from openfusion.mapping.shards import merge_region_tables, shard_of_tiles
from openfusion.mapping.tilestore import STORE_DIR_NAME, TileStore, decode_tile, encode_tile, is_store

logger = logging.getLogger(__name__)

__all__ = ["budget_of", "merge_parts_into_store", "part_headers", "parts_are_stores"]


def parts_are_stores(parts: list[Path]) -> bool:
    """Every part is a tile-store map folder (what a budgeted merge reads)."""
    return all(is_store(Path(p) / STORE_DIR_NAME) for p in parts)


def part_headers(parts: list[Path]) -> list[dict[str, Any]]:
    """Each part's checked map header (no tile read), in the parts' order."""
    headers = []
    for part in parts:
        with TileStore(Path(part) / STORE_DIR_NAME, readonly=True) as store:
            headers.append(check_header(store, store.read_header()))
    return headers


def budget_of(headers: list[dict[str, Any]]) -> float | None:
    """The memory budget (MiB) the parts were written with (the largest; None: none had one)."""
    budgets = [float(b) for h in headers if (b := h.get("volume_params", {}).get("memory_budget_mb")) is not None]
    return max(budgets) if budgets else None


def _names(header: dict[str, Any] | None) -> list[str]:
    return dict_names() + ["key_slots", "tile_index"] + (summary_names(header) if header is not None else [])


def merge_parts_into_store(parts: list[Path], target: Path, *, merged_meta: dict[str, Any],
                           memory_budget_mb: float | None) -> Path:
    """Write the parts (ordered by shard, map folders of tile stores) as one map's tile store at
    ``target`` (a folder; the store is ``target/map.ofz``) with ``merged_meta`` as its meta and
    ``memory_budget_mb`` in its volume parameters; returns the store's path. MapFormatError when
    a part is unreadable or of another block layout than the first."""
    count = len(parts)
    stores = [TileStore(Path(p) / STORE_DIR_NAME, readonly=True) for p in parts]
    try:
        first_header: dict[str, Any] | None = None
        slots: KeySlots | None = None
        index_rows: list[np.ndarray] = []
        summaries: list[tuple[np.ndarray, ...]] = []
        dictionary: tuple[tuple[int, int], dict[str, Any], dict[str, np.ndarray]] | None = None
        out_path = Path(target) / STORE_DIR_NAME
        with TileStore(out_path) as out:
            for i, store in enumerate(stores):
                header, arrays, committed = store.read_committed(_names)
                try:
                    header = check_header(store, header)
                    params = header["volume_params"]
                    if first_header is None:
                        first_header = header
                        slots = KeySlots.from_array(arrays["key_slots"])
                    elif (params.get("block_resolution"), params.get("tile_blocks"), params.get("voxel_size_m")) != (
                            first_header["volume_params"].get("block_resolution"),
                            first_header["volume_params"].get("tile_blocks"),
                            first_header["volume_params"].get("voxel_size_m")):
                        raise MapFormatError(f"{store.path}: a part of another block layout than {stores[0].path}")
                    assert slots is not None
                    remap = _slot_remap(KeySlots.from_array(arrays["key_slots"]), slots, len(arrays["key_slots"]))
                    identity = np.array_equal(remap, np.arange(len(remap)))
                    index = np.asarray(arrays["tile_index"], np.int64).reshape(-1, 4)
                    owned = shard_of_tiles(index[:, :3], count) == i if count > 1 else np.ones(len(index), bool)
                    mine = {tuple(int(v) for v in r[:3]) for r in index[owned]}
                    index_rows.append(index[owned])
                    res = int(params["block_resolution"])
                    for tile, blob in committed:
                        if tile not in mine:
                            continue  # a tile of another shard: this part holds only ghosts of it
                        if not identity:
                            coords, raw = decode_tile(store.codec, blob, f"{store.path} tile {tile}")
                            raw["key"] = remap[np.asarray(raw["key"], np.intp)].astype(raw["key"].dtype)
                            blob = encode_tile(out.codec, coords, raw, res)
                        elif store.codec_name != out.codec_name:
                            coords, raw = decode_tile(store.codec, blob, f"{store.path} tile {tile}")
                            blob = encode_tile(out.codec, coords, raw, res)
                        out.put(tile, blob)
                    version = (int(header["dictionary"]["version"]), len(arrays["dict_keys"]))
                    if dictionary is None or version > dictionary[0]:
                        dictionary = (version, header["dictionary"], {n: arrays[n] for n in dict_names()})
                    if all(f"summary_{n}" in arrays for n in ("keys", "num_points", "bbox_min", "bbox_max")):
                        summaries.append((arrays["summary_keys"], arrays["summary_num_points"],
                                          arrays["summary_bbox_min"], arrays["summary_bbox_max"],
                                          arrays.get("summary_centroid")))
                finally:
                    committed.close()  # type: ignore[attr-defined]
            assert first_header is not None and slots is not None and dictionary is not None
            header = {k: v for k, v in first_header.items() if k not in ("arrays", "codec", "generation")}
            header["volume_params"] = {**first_header["volume_params"], "shard": "0/1",
                                       "memory_budget_mb": memory_budget_mb}
            header["dictionary"] = dictionary[1]
            header["meta"] = merged_meta
            arrays_out: dict[str, np.ndarray] = dict(dictionary[2])
            arrays_out["key_slots"] = slots.to_array()
            arrays_out["tile_index"] = np.concatenate(index_rows) if index_rows else np.zeros((0, 4), np.int64)
            if len(summaries) == count:
                keys, num, lo, hi, cen = merge_region_tables(summaries)
                arrays_out.update(summary_keys=keys, summary_num_points=num, summary_bbox_min=lo,
                                  summary_bbox_max=hi, summary_centroid=cen)
            out.commit(blobs={}, header=header, arrays=arrays_out)
        return out_path
    finally:
        for store in stores:
            store.close()


def _slot_remap(part: KeySlots, merged: KeySlots, size: int) -> np.ndarray:
    """uint16 (size,): the merged table's slot for each of ``part``'s slots (same key; slot 0 and
    keyless slots -> 0), allocating merged slots for keys it does not have yet."""
    key1 = part.key1_of(np.arange(size))
    return merged.slots_for(key1)


def load_budgeted(parts: list[Path], load_map: Any, *, merged_meta: dict[str, Any], memory_budget_mb: float,
                  device: str | None = None) -> Any:
    """The parts as one :class:`~openfusion.mapping.mapfile.LoadedMap` under ``memory_budget_mb``
    (module docstring); the scratch folder goes when the volume is collected or the process ends."""
    folder = Path(tempfile.mkdtemp(prefix="openfusion-merged-"))
    try:
        store = merge_parts_into_store(parts, folder, merged_meta=merged_meta, memory_budget_mb=memory_budget_mb)
        loaded = load_map(store, device=device, memory_budget_mb=memory_budget_mb)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    weakref.finalize(loaded.volume, shutil.rmtree, str(folder), True)
    logger.info("loaded sharded map %s under a budget of %.0f MiB: %d parts merged into %s", Path(parts[0]).parent,
                memory_budget_mb, len(parts), store)
    return type(loaded)(loaded.volume, loaded.dictionary, merged_meta, Path(parts[0]).parent, loaded.relevancy)
