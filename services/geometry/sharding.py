"""The geometry service as one shard of a map split by tile (docs/SHARDS.md).

Shard ``I/N`` (``geometry.shard``, ``--shard I/N``; :class:`~openfusion.wire.keys.ShardId`) is the
same service with three differences, kept here so the service shell stays today's for ``0/1``:

- its volume integrates only the blocks of its own tiles (``VolumeParams.shard``,
  :mod:`openfusion.mapping.shards`);
- it answers its endpoints under its own key segment (:meth:`Endpoint.shard_key`,
  ``…/geometry/render/geometry-0of2``) and is named ``geometry-0of2`` in health, liveliness and
  its acknowledgements (``GeometryProgress.shard``): readers merge the shards' answers through
  :mod:`openfusion.shard_client`, and the bridge waits for every shard's acknowledgement;
- its checkpoints and saves go to the subfolder ``shard-{I}of{N}`` of the map folder
  (:func:`part_path`): each shard writes only its own tiles, and
  :func:`openfusion.mapping.load_map` of the map folder merges the parts into one map.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from openfusion.bus import ServiceRunner
from openfusion.mapping.shardmaps import shard_dir_name
from openfusion.wire.endpoints import Endpoint
from openfusion.wire.keys import ShardId


def part_path(map_path: Path, shard: ShardId) -> Path:
    """Where shard ``shard`` keeps its part of the map folder ``map_path`` (the folder itself for
    an unsharded map)."""
    return map_path if not shard.sharded and not shard.replica else Path(map_path) / shard_dir_name(shard)


def checkpoint_dir(map_path: Path, shard: ShardId) -> Path:
    """The checkpoint folder of ``shard`` in the map folder ``map_path`` (``map_dir/map_id``)."""
    return part_path(map_path, shard)


def serve(runner: ServiceRunner, endpoint: Endpoint, handler: Callable[[Any], Any], shard: ShardId,
          **options: Any) -> None:
    """Answer ``endpoint`` at this shard's key (the plain key for an unsharded map); a replica
    answers its shard's keys (Zenoh gives a query to one of them). ``options`` go to the
    :class:`~openfusion.bus.Queryable` (``workers``)."""
    if not shard.sharded:
        runner.queryable(endpoint, handler, **options)
        return
    runner.queryable_at(endpoint.shard_key(runner.keys, shard), endpoint.request, endpoint.reply, handler, **options)
