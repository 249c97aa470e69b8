"""Geometry's render endpoint on a real bus: a render waiting for a semantic update does not hold
up the renders behind it.

What a user would notice: the semantic service renders every candidate frame to score it while
the frame it encodes waits (up to ``render_update_wait_s``) for the update before it. With one
thread answering renders, an update that was lost stalled the scoring of every candidate behind
that wait, and the window of candidates aged while the encoder sat idle. Renders are counted in
health (``renders``, ``render_busy_s``); a candidate's view asked with its depth is a probe, counted
apart (``probes``, ``probe_busy_s``). Bad input tried: a render
asking for an update that never comes (it renders without it after the wait, counted).
"""

from __future__ import annotations

import threading
from contextlib import ExitStack

import numpy as np

from openfusion.bus import Publisher, call, open_session
from openfusion.frame import resize_nearest
from openfusion.services.geometry.service import GeometryConfig, GeometryService
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld
from openfusion.testing.bus import (
    ServiceThread,
    free_port,
    loopback_config,
    unique_map_id,
    wait_for_services,
    wait_until,
)
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.endpoints import GEOMETRY_RENDER, SENSOR_RGBD
from openfusion.wire.schemas import RenderRequest, RgbdFrame

FRAME = next(iter(SyntheticSource(SyntheticWorld(0), num_frames=1, width_px=80, height_px=60)))


def _render(after_seq: int) -> RenderRequest:
    return RenderRequest(frame_id=FRAME.frame_id, T_world_cam=FRAME.T_world_cam, after_update_source="lost-semantic",
                         after_update_seq=after_seq, **RenderRequest.intrinsics_fields(FRAME.intrinsics))


def test_a_render_waiting_for_a_lost_update_does_not_hold_up_the_next_render() -> None:
    with ExitStack() as stack:
        map_id, port = unique_map_id("renders"), free_port()
        cfg = loopback_config(map_id, model=GeometryConfig, listen=[port],
                              geometry={"initial_block_count": 2048, "load_on_start": False,
                                        "render_update_wait_s": 5.0})
        geo = stack.enter_context(ServiceThread(GeometryService(cfg), cfg, "geometry"))
        session = open_session(loopback_config(map_id, connect=[port]))
        stack.callback(session.close)
        wait_for_services(session, map_id, ["geometry"])
        rgbd = Publisher(session, SENSOR_RGBD.key(cfg.keys), message=RgbdFrame)
        wait_until(lambda: rgbd.has_subscribers, timeout_s=60)
        rgbd.put(RgbdFrame.from_frame(FRAME))
        wait_until(lambda: geo.counter(GeometryCounter.FRAMES_INTEGRATED) >= 1, timeout_s=60)

        waited: list[float] = []
        stuck = threading.Thread(target=lambda: waited.append(float(
            (call(session, cfg.keys, GEOMETRY_RENDER, _render(7), timeout_s=60).depth_m > 0).mean())))
        stuck.start()
        wait_until(lambda: geo.app._updates.waiting == 1, timeout_s=30,  # noqa: SLF001
                   describe=lambda: "the render never waited for its update")
        # asked after the waiting one, answered while it still waits (its update never comes)
        reply = call(session, cfg.keys, GEOMETRY_RENDER, _render(0), timeout_s=4.0)
        assert (reply.depth_m > 0).mean() > 0.2  # the frame's surface
        assert not waited and geo.app._updates.waiting == 1  # noqa: SLF001
        stuck.join(30)
        assert waited and waited[0] > 0.2  # rendered without the update after the wait
        assert geo.counter(GeometryCounter.RENDER_UPDATE_WAIT_TIMEOUTS) == 1
        # both answered, counted with the time their ray casts took (health's render load)
        assert geo.counter(GeometryCounter.RENDERS) == 2
        assert geo.counter(GeometryCounter.RENDER_BUSY_S) > 0

        # a candidate's view with its own depth: answered by a probe (no ray cast), counted apart,
        # the same surface as the render
        depth = resize_nearest(FRAME.depth_m(), (FRAME.intrinsics.height_px, FRAME.intrinsics.width_px))
        probed = call(session, cfg.keys, GEOMETRY_RENDER,
                      _render(0).model_copy(update={"probe_depth_m": depth.astype(np.float32)}), timeout_s=30)
        both = (probed.depth_m > 0) & (reply.depth_m > 0)
        assert both.mean() > 0.2
        assert (np.abs(probed.depth_m - reply.depth_m)[both] <= 0.02).mean() > 0.85
        assert geo.counter(GeometryCounter.PROBES) == 1 and geo.counter(GeometryCounter.RENDERS) == 2
        assert geo.counter(GeometryCounter.PROBE_BUSY_S) > 0
        # a map no larger than the request's probe_above_blocks (select_view auto, a room) is ray-cast
        small = _render(0).model_copy(update={"probe_depth_m": depth.astype(np.float32),
                                              "probe_above_blocks": 10**6})
        cast = call(session, cfg.keys, GEOMETRY_RENDER, small, timeout_s=30)
        np.testing.assert_array_equal(cast.depth_m, reply.depth_m)
        assert geo.counter(GeometryCounter.PROBES) == 1 and geo.counter(GeometryCounter.RENDERS) == 3
