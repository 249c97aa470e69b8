"""What a replica's copy of its peer's checkpoint shows (docs/SHARDS.md, "Replicas"): run.json's
per-shard counts include every live replica of the run's shards and its peer-copy counts, and
``openfusion health`` prints a table of the geometries that copied or served a checkpoint (none:
no table). Bad input tried: a stats entry of another split and of another service (left out)."""

from __future__ import annotations

from openfusion.app.bus_cmds import peer_copy_table
from openfusion.app.shard_run import shard_health
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.schemas import HealthStats


def _stats(name: str, **counters: float) -> HealthStats:
    return HealthStats(service=name, map_id="m", pid=1, uptime_s=1.0, fps=0.0, latency_ms_p50=0.0,
                       latency_ms_p99=0.0, drops=0, errors=0, counters=counters)


def test_run_json_and_health_show_peer_copies() -> None:
    stats = {
        "geometry-0of2": _stats("geometry-0of2", frames_integrated=40, peer_snapshots_served=1, peer_bytes_served=3e6),
        "geometry-1of2": _stats("geometry-1of2", frames_integrated=40),
        "geometry-0of2-r1": _stats("geometry-0of2-r1", frames_integrated=40, peer_copies=1, peer_copy_failures=1,
                                   peer_copy_tiles=120, peer_copy_bytes=3e6, peer_copy_frame_id=17, peer_copy_s=0.4),
        "geometry-0of3-r1": _stats("geometry-0of3-r1", peer_copies=1),  # another split: not this run's
        "semantic": _stats("semantic", peer_copies=5),  # not a geometry
    }
    shards = shard_health(stats, 2)
    assert list(shards) == ["geometry-0of2", "geometry-1of2", "geometry-0of2-r1"]
    replica = shards["geometry-0of2-r1"]
    assert replica[GeometryCounter.PEER_COPIES] == 1 and replica[GeometryCounter.PEER_COPY_TILES] == 120
    assert replica[GeometryCounter.PEER_COPY_BYTES] == 3e6 and replica[GeometryCounter.PEER_COPY_FAILURES] == 1
    assert shards["geometry-0of2"][GeometryCounter.PEER_SNAPSHOTS_SERVED] == 1
    table = peer_copy_table(stats).splitlines()
    assert table[0].split() == ["geometry", "copied", "failed", "tiles", "MB", "up_to_frame", "copy_s", "served",
                                "MB_served"]
    rows = {line.split()[0]: line.split() for line in table[1:]}
    assert set(rows) == {"geometry-0of2", "geometry-0of2-r1", "geometry-0of3-r1"}
    assert rows["geometry-0of2-r1"][1:7] == ["1", "1", "120", "3.0", "17", "0.40"]
    assert rows["geometry-0of2"][1:3] == ["0", "0"] and rows["geometry-0of2"][7:] == ["1", "3.0"]
    assert peer_copy_table({"geometry": _stats("geometry", frames_integrated=3)}) == ""
