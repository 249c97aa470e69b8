"""A replica on a new host (an empty map folder) joins mid-run, copies its peer's checkpoint, follows,
and carries on when the peer is killed (docs/SHARDS.md, "Replicas"; real processes).

Host 1 (this network namespace): the router, the bridge and the geometry service (``--map-dir``
host1). Host 2 (a namespace of its own, joined by a veth pair): the replica (``--replica 1``,
``--map-dir`` host2, empty), started once the primary has integrated a third of the playback. It
copies the primary's checkpoint over Zenoh (the primary checkpoints first), loads it as a restart
would, and the bridge replays only the frames after the copy's last one (not the playback from its
start). Then the primary is killed with SIGKILL: the playback completes on the replica, which holds
every frame exactly once, and its map (its checkpoint at shutdown) has the surface of one volume
of the same frames within 1 %.

Skipped with the reason when namespaces cannot be created (not root, no iproute2)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from openfusion.app.launcher import Cluster, wait_for_services
from openfusion.bus import collect_health, live_services, open_session
from openfusion.bus import free_loopback_port as free_port
from openfusion.client import OpenFusionClient
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.testing.bus import subprocess_env, unique_map_id, wait_until
from openfusion.wire.counters import BridgeCounter, GeometryCounter

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
N = 48
SOURCE = f"synthetic:seed=1,frames={N},width=320,height=240"
RATE_HZ = 3

pytestmark = [pytest.mark.netns, pytest.mark.slow, pytest.mark.timeout(600)]


def _counter(client: OpenFusionClient, service: str, name: str) -> float:
    stats = collect_health(client.session, client.keys, timeout_s=1.5).get(service)
    return float(stats.counters.get(name, 0.0)) if stats else 0.0


def test_a_replica_on_a_new_host_copies_its_peer_follows_and_carries_on(netns, tmp_path: Path) -> None:  # noqa: ANN001
    map_id = unique_map_id("peercopy2h")
    port = free_port()
    local, remote = f"tcp/127.0.0.1:{port}", f"tcp/{netns.host_addr}:{port}"
    router = open_session(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(
        mode="router", listen=[local, remote], multicast_scouting=False)))
    cluster = Cluster(map_id, local, tmp_path / "logs")
    client = OpenFusionClient.from_config(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(
        mode="client", connect=[local], multicast_scouting=False)), timeout_s=20)
    env = subprocess_env(HF_HUB_OFFLINE="1")
    replica: subprocess.Popen[bytes] | None = None
    log = (tmp_path / "geometry-r1-netns.log").open("wb")
    try:
        cluster.start("geometry", ["--map-dir", str(tmp_path / "host1"), "--checkpoint-period-s", "0"], env=env)
        wait_for_services(client, cluster, {"geometry"}, 240)
        cluster.start("bridge", ["--source", SOURCE, "--rate-hz", str(RATE_HZ)], env=env)
        wait_until(lambda: _counter(client, "geometry", GeometryCounter.FRAMES_INTEGRATED) >= N // 3, timeout_s=240)

        # A new host: an empty folder. It copies the primary's checkpoint before it takes frames.
        replica = subprocess.Popen(
            ["ip", "netns", "exec", netns.name, sys.executable, "-m", "openfusion.app.cli", "service", "geometry",
             "--map", map_id, "--mode", "client", "--connect", remote, "--no-multicast",
             "--map-dir", str(tmp_path / "host2"), "--checkpoint-period-s", "0", "--replica", "1"],
            stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
        wait_until(lambda: "geometry-r1" in live_services(client.session, client.keys), timeout_s=240)
        wait_until(lambda: _counter(client, "geometry-r1", GeometryCounter.PEER_COPIES) >= 1, timeout_s=30)
        copied = int(_counter(client, "geometry-r1", GeometryCounter.PEER_COPY_FRAME_ID))
        assert copied >= N // 3 - 1
        assert _counter(client, "geometry-r1", GeometryCounter.PEER_COPY_FAILURES) == 0
        assert _counter(client, "geometry-r1", GeometryCounter.PEER_COPY_TILES) > 0
        assert _counter(client, "geometry", GeometryCounter.PEER_SNAPSHOTS_SERVED) == 1

        # The replica follows; then, mid-run, the primary dies (SIGKILL: no checkpoint, no goodbye).
        wait_until(lambda: _counter(client, "geometry-r1", GeometryCounter.FRAMES_INTEGRATED) >= copied + 5,
                   timeout_s=240)
        assert _counter(client, "bridge", BridgeCounter.PLAYBACK_DONE) == 0
        killed_at = _counter(client, "geometry", GeometryCounter.LAST_FRAME_ID)
        primary = cluster.processes.pop("geometry")
        os.kill(primary.proc.pid, signal.SIGKILL)
        primary.proc.wait(timeout=20)
        wait_until(lambda: _counter(client, "bridge", BridgeCounter.PLAYBACK_DONE) >= 1, timeout_s=240)
        wait_until(lambda: _counter(client, "geometry-r1", GeometryCounter.FRAMES_INTEGRATED) >= N, timeout_s=120)
        assert _counter(client, "geometry-r1", GeometryCounter.FRAMES_INTEGRATED) == N  # each frame once
        # Replayed for the replica: the frames after its copy's last one, never the playback from its start.
        replayed = _counter(client, "bridge", BridgeCounter.FRAMES_REPLAYED)
        assert replayed <= N - 1 - copied, (replayed, copied)

        replica.send_signal(signal.SIGTERM)  # its checkpoint at shutdown: the map it holds
        assert replica.wait(60) == 0
        from openfusion.mapping import SemanticVolume, VolumeParams, load_map
        from openfusion.services.geometry.sharding import checkpoint_dir
        from openfusion.sources import open_source
        from openfusion.wire.keys import ShardId

        held = load_map(checkpoint_dir(tmp_path / "host2" / map_id, ShardId(replica=1)))
        whole = SemanticVolume(VolumeParams())
        for frame in open_source(SOURCE):
            whole.integrate(frame)
        got, ref = len(held.volume.extract_points()), len(whole.extract_points())
        print(f"surface points: replica {got}, one volume {ref}; copied up to frame {copied}, {replayed:.0f} replayed, "
              f"primary killed after frame {killed_at:.0f} of {N}")
        assert abs(got - ref) <= 0.01 * ref, (got, ref)
    finally:
        if replica is not None and replica.poll() is None:
            replica.kill()
            replica.wait(20)
        log.close()
        cluster.stop()
        client.close()
        router.close()
