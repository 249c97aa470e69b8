"""Bridge service: a real ``openfusion service bridge`` process plays the synthetic scene onto the
bus; a subscriber in the test receives every frame intact (same ids, poses, depth), each frame's
instance image on ``sensor/instance`` (never inside the frame), and the bridge's health
reports what it read and published. Bad input tried: an unknown source scheme
(the process must exit with a one-line error, not a traceback)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from helpers_bus import (
    ROOT,
    ServiceProcess,
    free_port,
    loopback_args,
    loopback_config,
    subprocess_env,
    unique_map_id,
    wait_until,
)
from openfusion.bus import Subscriber, collect_health, open_session
from openfusion.messages import InstanceFrame, RgbdFrame
from openfusion.sources import open_source


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
        inst_sub = Subscriber(session, keys.sensor_instance, InstanceFrame,
                              lambda m: instances.__setitem__(m.frame_id, m), queue_size=64)
        sub = Subscriber(session, keys.sensor_rgbd, RgbdFrame, got.append, queue_size=64)
        args = ["service", "bridge", *loopback_args(map_id, connect=[port]), "--source", spec, "--rate-hz", "0"]
        with ServiceProcess("openfusion.cli", args) as proc:
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
        [sys.executable, "-m", "openfusion.cli", "service", "bridge", *loopback_args(map_id), "--source", "nosuch:/x"],
        capture_output=True, text=True, timeout=60, cwd=ROOT, env=subprocess_env(),
    )
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    assert "nosuch" in result.stderr
