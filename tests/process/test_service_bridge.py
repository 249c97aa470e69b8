"""Bridge service: a real ``openfusion service bridge`` process plays the synthetic scene onto the
bus; a subscriber in the test receives every frame intact (same ids, poses, depth), each frame's
instance image on ``sensor/instance`` (never inside the frame), and the bridge's health
reports what it read and published. Bad input tried: an unknown source scheme
(the process must exit with a one-line error, not a traceback)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from openfusion.bus import Subscriber, collect_health, open_session
from openfusion.config import ServiceConfig
from openfusion.sources import open_source
from openfusion.testing.bus import (
    ServiceProcess,
    free_port,
    loopback_args,
    loopback_config,
    subprocess_env,
    unique_map_id,
    wait_until,
)
from openfusion.wire.endpoints import SENSOR_INSTANCE, SENSOR_RGBD
from openfusion.wire.schemas import HealthStats, InstanceFrame, RgbdFrame

#: The repository root (deploy files, docs, the README's commands).
ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())


def test_bridge_publishes_every_frame_of_the_source_intact() -> None:
    map_id = unique_map_id("bridge")
    port = free_port()
    spec = "synthetic:seed=3,frames=6,width=160,height=120"
    expected = list(open_source(spec))
    session = open_session(loopback_config(map_id, listen=[port]))
    got: list[RgbdFrame] = []
    instances: dict[int, InstanceFrame] = {}
    try:
        keys = loopback_config(map_id).keys
        inst_sub = Subscriber(session, SENSOR_INSTANCE.key(keys), InstanceFrame,
                              lambda m: instances.__setitem__(m.frame_id, m), queue_size=64)
        sub = Subscriber(session, SENSOR_RGBD.key(keys), RgbdFrame, got.append, queue_size=64)
        args = ["service", "bridge", *loopback_args(map_id, connect=[port]), "--source", spec, "--rate-hz", "0"]
        with ServiceProcess("openfusion.app.cli", args) as proc:
            wait_until(lambda: len(got) >= len(expected) and len(instances) >= len(expected), timeout_s=60)

            def bridge_done() -> object:
                stats = collect_health(session, keys, timeout_s=1.0).get("bridge")
                return stats if stats is not None and stats.counters.get("playback_done") else None

            health = wait_until(bridge_done, timeout_s=30)
            proc.terminate()
            assert proc.wait(20) == 0, proc.output()
        sub.close()
        inst_sub.close()
    finally:
        session.close()
    assert [m.frame_id for m in got] == [f.frame_id for f in expected]
    for msg, frame in zip(got, expected, strict=True):
        np.testing.assert_array_equal(msg.depth, frame.depth)
        np.testing.assert_allclose(msg.T_world_cam, frame.T_world_cam)
        assert msg.instance is None and msg.instance_categories == {}  # not on the geometry path
        joined = msg.to_frame(instances[msg.frame_id])
        np.testing.assert_array_equal(joined.instance, frame.instance)
        assert joined.instance_categories == frame.instance_categories
    assert health.counters["frames_published"] == len(expected)
    assert health.counters["instances_published"] == len(expected)
    assert health.counters["frames_read"] == len(expected)


def test_bridge_with_unknown_source_exits_with_one_clear_line() -> None:
    map_id = unique_map_id("bridge-bad")
    result = subprocess.run(
        [sys.executable, "-m", "openfusion.app.cli", "service", "bridge", *loopback_args(map_id), "--source", "nosuch:/x"],
        capture_output=True, text=True, timeout=60, cwd=ROOT, env=subprocess_env(),
    )
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    assert "nosuch" in result.stderr


def test_playback_at_full_speed_loses_no_frame_to_geometrys_bounded_queue(tmp_path: Path) -> None:
    """A replay at --rate-hz 0 into a geometry service whose frame queue holds 4 frames: with flow
    control (at most 3 frames not yet acknowledged on geometry/progress) every frame is integrated
    and none dropped; with it off (--max-in-flight 0) the same replay overflows the queue, which is
    what flow control is for. Bad input tried: a publisher far faster than the consumer."""
    from openfusion.app.launcher import Cluster
    from openfusion.config import ZenohSettings
    from openfusion.sources.record import FrameRecorder

    n = 20
    recording = tmp_path / "frames.ofrec"
    with FrameRecorder(recording) as rec:
        for frame in open_source(f"synthetic:seed=2,frames={n},width=640,height=480"):
            rec.write(frame)
    map_id = unique_map_id("flow")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(mode="router", listen=[endpoint],
                                                                            multicast_scouting=False)))
    cluster = Cluster(map_id, endpoint, tmp_path / "logs")
    try:
        keys = loopback_config(map_id).keys

        def geometry() -> HealthStats | None:
            return collect_health(router, keys, timeout_s=1.0).get("geometry")

        def play(*extra: str) -> HealthStats:
            cluster.start("bridge", ["--source", f"replay:{recording}", "--rate-hz", "0", *extra])
            bridge = wait_until(
                lambda: (s := collect_health(router, keys, timeout_s=1.0).get("bridge")) is not None
                and s.counters.get("playback_done") and s, timeout_s=120)
            cluster.stop("bridge")
            cluster.processes.pop("bridge")
            return bridge

        cluster.start("geometry", ["--checkpoint-period-s", "0", "--set", "geometry.frame_queue_size=4",
                                   "--set", "geometry.initial_blocks=4096", "--set", "geometry.load_on_start=false"])
        wait_until(geometry, timeout_s=120)

        play("--max-in-flight", "0")
        settled = wait_until(lambda: (g := geometry()) and g.counters.get("frames_integrated", 0) + g.drops >= n
                             and g, timeout_s=120)
        open_loop_drops = settled.drops
        assert open_loop_drops > 0, "the replay should overflow a 4-frame queue without flow control"
        integrated_before = settled.counters["frames_integrated"]

        bridge = play("--max-in-flight", "3")
        after = wait_until(lambda: (g := geometry()) and g.counters["frames_integrated"] >= integrated_before + n
                           and g, timeout_s=120)
        assert after.counters["frames_integrated"] == integrated_before + n
        assert after.drops == open_loop_drops  # not one more frame lost
        assert bridge.counters["frames_published"] == n
        assert bridge.counters.get("flow_timeouts", 0) == 0
        assert bridge.counters.get("flow_wait_s", 0) > 0  # it did wait for geometry
        cluster.check_alive()
    finally:
        cluster.stop()
        router.close()
