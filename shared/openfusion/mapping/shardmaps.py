"""A map saved by geometry shards: one part per shard, read back as one map.

Layout (docs/SHARDS.md): each geometry shard ``I/N`` checkpoints and saves only its own tiles, into
``{map folder}/shard-{I}of{N}/`` -- an ordinary map folder (tile store, dictionary, summaries of
its part). Why a store per shard and not one store: shards run on different hosts, each with its
own disk; an LMDB store has one writer process on one host; and a part is exactly what a shard
restarted on its host loads back (resume works per shard, as for one geometry). The price is the
merge on read, done here:

- :func:`load_sharded` (what :func:`openfusion.mapping.load_map` does for such a folder): the
  parts' tiles are disjoint, so their blocks are copied into one volume (region keys carried
  through each part's key-slot table); the dictionary is the most advanced part's (every shard
  follows the same deltas); ``last_frame_id`` is the smallest of the parts' (every part holds it).
- :func:`load_sharded_summary`: the parts' region summaries merged
  (:func:`openfusion.mapping.shards.merge_region_tables`), without reading a volume.

A folder with some parts missing or of two shard counts is refused (:class:`MapFormatError`
naming what is missing): a map with a hole is never read as if whole.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from openfusion.mapping.errors import MapFormatError
from openfusion.wire.keys import ShardId

logger = logging.getLogger(__name__)

_PART = re.compile(r"^shard-([0-9]+)of([0-9]+)(?:-r([0-9]+))?$")


def shard_dir_name(shard: ShardId) -> str:
    """The subfolder of a map folder where shard ``shard`` keeps its part (a replica R > 0: its
    own, ``…-rR``, so two replicas sharing a disk never write one store)."""
    return f"shard-{shard.index}of{shard.count}" + (f"-r{shard.replica}" if shard.replica else "")


def _newest(folder: Path) -> float:
    """When the part in ``folder`` was last written (its files' newest modification time)."""
    return max((f.stat().st_mtime for f in folder.rglob("*") if f.is_file()), default=0.0)


def shard_parts(path: str | Path) -> list[Path] | None:
    """The parts (ordered by shard) of a sharded map folder, None for a folder that is not one;
    MapFormatError when a part is missing or parts of different shard counts are present."""
    p = Path(path)
    if not p.is_dir():
        return None
    found: dict[int, dict[int, Path]] = {}
    for child in sorted(p.iterdir()):
        m = _PART.match(child.name)
        if m and child.is_dir():
            # Replicas of a part (a save goes to one of them, checkpoints to each): the newest.
            parts = found.setdefault(int(m.group(2)), {})
            index = int(m.group(1))
            if index not in parts or _newest(child) > _newest(parts[index]):
                parts[index] = child
    if not found:
        return None
    if len(found) > 1:
        raise MapFormatError(f"{p}: parts of {sorted(found)} shards; a map folder holds the parts of one split")
    (count, parts), = found.items()
    missing = [f"{i}/{count}" for i in range(count) if i not in parts]
    if missing:
        raise MapFormatError(f"{p}: the part of shard {', '.join(missing)} is missing (a map split {count} ways "
                             f"needs all {count} parts)")
    return [parts[i] for i in range(count)]


def _merged_meta(metas: list[dict[str, Any]], count: int) -> dict[str, Any]:
    meta = dict(metas[0])
    lasts = [m.get("last_frame_id") for m in metas]
    meta["last_frame_id"] = None if any(v is None for v in lasts) else min(int(v) for v in lasts)
    meta["frames_integrated"] = max(int(m.get("frames_integrated") or 0) for m in metas)
    meta["geometry_shards"] = count
    return meta


def load_sharded(parts: list[Path], load_map: Callable[..., Any], *, device: str | None = None,
                 memory_budget_mb: float | None | str = None) -> Any:
    """One :class:`~openfusion.mapping.mapfile.LoadedMap` of the parts (module docstring), each
    read with ``load_map`` (:func:`openfusion.mapping.load_map`): every tile in one resident
    volume of shard 0/1; with a budget (``memory_budget_mb``: MiB, or ``"map"``, the parts' own)
    the parts are merged into one scratch tile store read under it (:mod:`.shardstore`)."""
    from openfusion.mapping import shardstore
    from openfusion.mapping.mapstore import header_meta
    from openfusion.mapping.shards import owned_blocks
    from openfusion.mapping.volume import SemanticVolume

    if memory_budget_mb is not None and shardstore.parts_are_stores(parts):
        headers = shardstore.part_headers(parts)  # read once: the budget and the merged meta
        budget = shardstore.budget_of(headers) if memory_budget_mb == "map" else float(memory_budget_mb)
        if budget is not None:
            metas = [header_meta(h) for h in headers]
            return shardstore.load_budgeted(parts, load_map, merged_meta=_merged_meta(metas, len(parts)),
                                            memory_budget_mb=budget, device=device)
    loaded = [load_map(part, device=device, memory_budget_mb=None) for part in parts]
    try:
        params = loaded[0].volume.params.with_changes(shard="0/1", memory_budget_mb=None)
        merged = SemanticVolume(params)
        storage = merged._storage
        blocks = []
        for i, part in enumerate(loaded):
            coords, buf = part.volume._storage.active_blocks()
            # Only the part's own tiles: the blocks of other tiles it holds are ghosts (shards.py).
            mine = owned_blocks(coords, params.tile_blocks, ShardId(i, len(parts)))
            coords, buf = coords[mine], buf[mine]
            raw = part.volume._storage.read_raw_blocks(buf)
            key1 = part.volume._storage.slots.key1_of(raw["key"])
            raw["key"] = storage.slots.slots_for(key1).astype(raw["key"].dtype).reshape(raw["key"].shape)
            blocks.append((coords, raw))
        total = sum(len(c) for c, _ in blocks)
        if total > storage.capacity_blocks:
            storage.reset(capacity=total, keep_slots=True)
        for coords, raw in blocks:
            storage.write_raw_blocks(coords, raw)
        merged.pager.sync_resident()
        dictionary = max((p.dictionary for p in loaded), key=lambda d: (d.version, len(d)))
        meta = _merged_meta([p.meta for p in loaded], len(parts))
        logger.info("loaded sharded map %s: %d parts, %d blocks, %d regions", parts[0].parent, len(parts), total,
                    len(dictionary))
        return type(loaded[0])(merged, dictionary, meta, parts[0].parent, loaded[0].relevancy)
    finally:
        for part in loaded:
            part.volume.close()


def load_sharded_summary(parts: list[Path], load_map_summary: Callable[[Path], Any]) -> Any:
    """One :class:`~openfusion.mapping.mapfile.MapSummary` of the parts, each read with
    ``load_map_summary`` (None when a part has no summaries: read the map with :func:`load_sharded`)."""
    from openfusion.mapping.shards import merge_region_tables
    from openfusion.mapping.summaries import RegionTable

    summaries = [load_map_summary(part) for part in parts]
    if any(s is None for s in summaries):
        return None
    tables = [s.regions for s in summaries]  # type: ignore[union-attr]
    keys, num, lo, hi, cen = merge_region_tables([(t.keys, t.num_points, t.bbox_min, t.bbox_max, t.centroid)
                                                 for t in tables])
    first = summaries[0]
    dictionary = max((s.dictionary for s in summaries), key=lambda d: (d.version, len(d)))  # type: ignore[union-attr]
    meta = _merged_meta([s.meta for s in summaries], len(parts))  # type: ignore[union-attr]
    params = first.volume_params.with_changes(shard="0/1")  # type: ignore[union-attr]
    return type(first)(dictionary, RegionTable(keys, num, cen, lo, hi), params, meta, first.relevancy)  # type: ignore[union-attr]


def has_parts(path: str | Path) -> bool:
    """Whether ``path`` is a map folder of shard parts (complete or not)."""
    p = Path(path)
    return p.is_dir() and any(_PART.match(c.name) and c.is_dir() for c in p.iterdir())


__all__ = ["has_parts", "load_sharded", "load_sharded_summary", "shard_dir_name", "shard_parts"]
