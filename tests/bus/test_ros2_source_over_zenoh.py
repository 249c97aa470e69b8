"""The ROS 2 source on a real Zenoh session: frames published in the zenoh-bridge-ros2dds key
layout over loopback are assembled into canonical frames."""

from __future__ import annotations

import threading
import time

import numpy as np
from ros2_support import MS, _stream, body_pose

from openfusion.bus import free_loopback_port
from openfusion.poses import matrix_to_quat, pose_from_tum
from openfusion.sources.ros2 import T_BODY_OPTICAL, Ros2Config, Ros2Source, Ros2Topics
from openfusion.testing.bus import wait_for_subscriber


def _pose_parts(t_ns: int):  # noqa: ANN202 - test helper
    T = body_pose(t_ns)
    return T[:3, 3], matrix_to_quat(T[:3, :3])


def test_loopback_zenoh_source() -> None:
    """End to end on loopback: a publisher session puts CDR payloads on the keys a
    zenoh-bridge-ros2dds with namespace 'bot1' would use; Ros2Source yields the frames."""
    import zenoh

    port = free_loopback_port()

    def conf(*, listen: bool) -> zenoh.Config:
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        if listen:
            c.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
        else:
            c.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
        return c

    topics = Ros2Topics(namespace="bot1")
    with zenoh.open(conf(listen=True)) as pub_session:
        source = Ros2Source(Ros2Config(topics=topics), zenoh_config=conf(listen=False), idle_timeout_s=1.0)
        assert source.keys["color"] == "bot1/camera/color/image_raw"
        keys = source.keys
        for key in keys.values():  # the source's subscriptions have reached the publishing session
            wait_for_subscriber(pub_session, key)

        def publish() -> None:
            for kind, payload in _stream():
                pub_session.put(keys[kind], payload)
                time.sleep(0.002)  # a camera's pace, not a wait: the source's queue holds 256 samples

        thread = threading.Thread(target=publish)
        thread.start()
        try:
            frames = list(source)
        finally:
            thread.join()
            source.close()
    assert [f.stamp_ns for f in frames] == [k * 100 * MS + 3 * MS for k in range(1, 6)]
    assert source.dropped_samples == 0
    np.testing.assert_allclose(
        frames[-1].T_world_cam, pose_from_tum(*_pose_parts(frames[-1].stamp_ns)) @ T_BODY_OPTICAL, atol=2e-4
    )
