"""``openfusion run --geometry-shards N``: the run's geometry as N shard processes (docs/SHARDS.md).

The launcher starts ``geometry-{I}of{N}`` (``openfusion service geometry --shard I/N``) for each
shard instead of one ``geometry``, and everything that follows the run (progress, the end of
playback, run.json) reads one combined ``geometry`` view of the shards' health
(:func:`combined_geometry`): a frame counts as integrated when every shard took it (the smallest
count), sizes and busy times add up, and the checkpointed frame is the oldest any shard holds.
run.json keeps ``geometry_shards`` and each shard's own counts (:func:`shard_health`).
"""

from __future__ import annotations

from typing import Any

from openfusion.wire.counters import GeometryCounter
from openfusion.wire.keys import ShardId
from openfusion.wire.schemas import HealthStats

#: Counters of the whole map's progress: every shard counts every frame it takes, so the map has
#: what the slowest shard has.
_SLOWEST = {
    GeometryCounter.FRAMES_INTEGRATED, GeometryCounter.UPDATES_APPLIED, GeometryCounter.CHECKPOINTS,
    GeometryCounter.CHECKPOINT_LAST_FRAME_ID, GeometryCounter.LAST_FRAME_ID, GeometryCounter.LAST_UPDATE_FRAME_ID,
    GeometryCounter.FRAMES_DUPLICATE, GeometryCounter.FRAMES_OUT_OF_ORDER, GeometryCounter.SAVES,
}
#: Counters that say "at least one shard is busy with it".
_ANY = {GeometryCounter.SAVING}


def geometry_names(count: int) -> list[str]:
    """The service (and process) names of a run's geometry split ``count`` ways."""
    return [shard.service for shard in ShardId.all(count)]


def combined_geometry(stats: dict[str, HealthStats]) -> dict[str, HealthStats]:
    """``{"geometry": one view of the shards}`` when the stats hold every shard of a split (the
    shards' replica-0 services, ``geometry-IofN``); nothing for an unsharded map or while a shard's
    stats are missing (the run waits for them as for any service)."""
    split = {s.count for s in (ShardId.of_service(n) for n in stats) if s is not None and s.sharded and not s.replica}
    if len(split) != 1:
        return {}
    parts = [stats.get(name) for name in geometry_names(split.pop())]
    if any(p is None for p in parts):
        return {}
    shards: list[HealthStats] = parts  # type: ignore[assignment]
    names = set().union(*(p.counters for p in shards))
    counters: dict[str, float] = {}
    for name in names:
        values = [p.counter(name) for p in shards]
        counters[name] = min(values) if name in _SLOWEST else max(values) if name in _ANY else sum(values)
    first = shards[0]
    view = first.model_copy(update={
        "service": "geometry", "counters": counters, "errors": sum(p.errors for p in shards),
        "drops": sum(p.drops for p in shards), "fps": min(p.fps for p in shards),
    })
    return {"geometry": view}


#: Each shard's (and replica's) own counts in run.json: progress, size, its view load (ray casts
#: and frame selection's probes, with their time) and its copy of a peer's checkpoint
#: (docs/SHARDS.md, "Replicas").
SHARD_COUNTERS = (
    GeometryCounter.FRAMES_INTEGRATED, GeometryCounter.NUM_BLOCKS, GeometryCounter.INTEGRATE_BUSY_S,
    GeometryCounter.RENDERS, GeometryCounter.RENDER_BUSY_S, GeometryCounter.PROBES, GeometryCounter.PROBE_BUSY_S,
    GeometryCounter.UPDATES_APPLIED, GeometryCounter.CHECKPOINT_LAST_FRAME_ID, GeometryCounter.RSS_PEAK_MB,
    GeometryCounter.PEER_COPIES, GeometryCounter.PEER_COPY_FAILURES, GeometryCounter.PEER_COPY_TILES,
    GeometryCounter.PEER_COPY_BYTES, GeometryCounter.PEER_SNAPSHOTS_SERVED,
)


def shard_health(stats: dict[str, Any], count: int) -> dict[str, dict[str, float]]:
    """Each shard's own counts for run.json (what ``openfusion health`` shows per shard), and each
    replica's of those shards that is live (``geometry-0of2-r1``)."""
    out: dict[str, dict[str, float]] = {}
    replicas = sorted(n for n in stats if (s := ShardId.of_service(n)) is not None and s.replica and s.count == count)
    for name in [*geometry_names(count), *replicas]:
        s = stats.get(name)
        if s is None:
            continue
        out[name] = {str(k): s.counter(k) for k in SHARD_COUNTERS}
    return out


def start_geometry(cluster: Any, count: int) -> list[str]:
    """Start the run's geometry (one service, or one process per shard); their names."""
    if count == 1:
        cluster.start("geometry")
        return ["geometry"]
    for shard in ShardId.all(count):
        cluster.start(shard.service, ["--shard", str(shard)], service="geometry")
    return geometry_names(count)


def geometry_alive(cluster: Any, count: int) -> bool:
    """Every geometry process of the run is alive."""
    procs = [cluster.processes.get(name) for name in geometry_names(count)]
    return all(p is not None and p.alive() for p in procs)
