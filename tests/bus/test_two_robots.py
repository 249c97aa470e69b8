"""Two robots into one geometry service, its handlers called directly (the registration thread runs
as in the service): a robot whose odometry is 0.3 m and 5 degrees off the map's frame, with no
guess, is held until its submap registers and then joined to within 3 cm and 0.5 degrees; its
held frames go into the map through the transform found, and its bridge is asked to replay them
for the semantic service. A robot that starts in a room the map has not seen is held (counted in
health) and joined once it walks into mapped space. Renders and updates of a held robot are refused
or dropped, never written misaligned. And the frame queue serves robots in turn: one robot's flood
never starves another (real Zenoh sessions).

Bad input tried: a render request and a semantic update for a robot that is not joined (refused
with ``robot_not_joined`` / dropped and counted, the map unchanged)."""

from __future__ import annotations

import dataclasses
import itertools
import threading

import numpy as np
import pytest
from test_resume_playback import _Runner  # noqa: I001 - the bus-free runner double of that module

from openfusion.bus import Publisher, RequestError, Subscriber
from openfusion.frame import CameraIntrinsics
from openfusion.mapping.robot_join import pose_difference
from openfusion.mapping.robot_streams import yaw_transform
from openfusion.services.geometry.service import GeometryConfig, GeometrySection, GeometryService
from openfusion.sources.synthetic.building import SyntheticBuilding
from openfusion.sources.synthetic.source import BuildingSource
from openfusion.testing.bus import wait_until
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.schemas import ControlRequest, RenderRequest, RgbdFrame, SemanticUpdate

pytestmark = pytest.mark.timeout(300)

T_MAP_ODOM = yaw_transform(0.25, -0.15, 0.05, 5.0)  # 0.3 m and 5 degrees: what the join must find
T_ODOM_MAP = np.linalg.inv(T_MAP_ODOM)


@pytest.fixture(scope="module")
def building() -> tuple[SyntheticBuilding, list, list]:
    """Two rooms off one corridor; robot a walks room 0, robot b room 1 (both from the corridor's start)."""
    b = SyntheticBuilding(0, rooms=2)
    walk = {"width_px": 160, "height_px": 120, "revisit": 0}  # a frame every 0.3 m or 20 degrees
    return b, list(BuildingSource(b, route=[0], **walk)), list(BuildingSource(b, route=[1], **walk))


def _geometry() -> tuple[GeometryService, _Runner]:
    section = GeometrySection(voxel_size_m=0.04, initial_block_count=4096, checkpoint_period_s=0.0)
    geo = GeometryService(GeometryConfig(map_id="robots", geometry=section))
    runner = _Runner()
    geo.setup(runner)  # type: ignore[arg-type]
    return geo, runner


def _msg(frame, robot: str, *, offset: bool = False, live: bool = False) -> RgbdFrame:  # noqa: ANN001
    if offset:  # the robot reports poses in its own odometry frame
        frame = dataclasses.replace(frame, T_world_cam=T_ODOM_MAP @ frame.T_world_cam)
    if live:  # taken as they come (no playback chain)
        return RgbdFrame.from_frame(frame, robot=robot)
    return RgbdFrame.from_frame(frame, playback="p" + robot, prev_frame_id=frame.frame_id - 1, robot=robot)


def test_a_robot_with_an_offset_is_held_then_joined_and_its_held_frames_integrated(building) -> None:
    _b, walk_a, walk_b = building
    geo, runner = _geometry()
    try:
        for fa, fb in itertools.zip_longest(walk_a, walk_b):  # at the same time
            if fa is not None:
                geo.on_frame(_msg(fa, "a"))
            if fb is not None:
                geo.on_frame(_msg(fb, "b", offset=True))
        # Joined, and its held frames integrated (the counter comes after both).
        wait_until(lambda: runner.counter(GeometryCounter.ROBOTS_JOINED) >= 1 or None, timeout_s=240)
        a, b = geo.robots.robots["a"], geo.robots.robots["b"]
        metres, degrees = pose_difference(T_MAP_ODOM, b.T_map_odom)
        assert metres <= 0.03 and degrees <= 0.5, (metres, degrees)
        assert (a.frames_integrated, b.frames_integrated) == (len(walk_a), len(walk_b))
        assert b.join_method == "global" and a.join_method == "anchor"
        assert geo.frames_integrated == len(walk_a) + len(walk_b)
        # The bridge of b is asked to replay from its first frame (the semantic service skipped them).
        replays = [m for m in runner.published.sent if m.resume > 0 and m.robot == "b"]
        assert replays and (replays[-1].holds_playback, replays[-1].holds_frame_id) == ("pb", -1)
        assert runner.counter(GeometryCounter.ROBOTS_JOINED) == 1
        status = geo.robot_status()
        assert status["b"]["state"] == "joined" and status["b"]["join_fitness"] > 0
        # Replayed frames are duplicates for geometry: nothing is integrated twice.
        for fb in walk_b[:3]:
            geo.on_frame(_msg(fb, "b", offset=True))
        assert b.frames_integrated == len(walk_b) and b.skipped["duplicate"] == 3
    finally:
        geo.close()


def test_a_held_robots_renders_are_refused_and_its_updates_dropped(building) -> None:
    _b, walk_a, walk_b = building
    geo, runner = _geometry()
    try:
        geo.on_frame(_msg(walk_a[0], "a"))
        geo.on_frame(_msg(walk_b[0], "b", offset=True))
        assert geo.robots.robots["b"].state == "held"
        K = CameraIntrinsics(fx=40.0, fy=40.0, cx=20.0, cy=15.0, width_px=40, height_px=30)
        request = RenderRequest(frame_id=0, T_world_cam=walk_b[0].T_world_cam, robot="b",
                                **RenderRequest.intrinsics_fields(K))
        with pytest.raises(RequestError, match="robot 'b' is not joined"):
            geo.handle_render(request)
        version = geo.map_version
        geo.on_update(SemanticUpdate(frame_id=0, T_world_cam=walk_b[0].T_world_cam, robot="b",
                                     **SemanticUpdate.intrinsics_fields(K), key_map=np.zeros((30, 40), np.int32),
                                     conf_map=np.ones((30, 40), np.float32), new_keys=np.array([0], np.int32)))
        assert geo.map_version == version and runner.counter(GeometryCounter.UPDATES_DROPPED_NOT_JOINED) == 1
    finally:
        geo.close()


@pytest.mark.slow  # a registration attempt every 10 frames until it joins: ~30 s on 2 cores
def test_a_robot_that_starts_in_an_unseen_room_is_held_until_it_reaches_mapped_space() -> None:
    b = SyntheticBuilding(0, rooms=2)
    walk = {"width_px": 160, "height_px": 120, "revisit": 0}
    walk_a = list(BuildingSource(b, route=[0], **walk))
    # Robot b walks room 1, then into the corridor and room 0; it starts inside room 1, unseen by a.
    route_b = list(BuildingSource(b, route=[1, 0], **walk))
    corridor_y1 = b.plan.corridor_width_m
    inside = next(i for i, f in enumerate(route_b) if abs(f.T_world_cam[1, 3] - corridor_y1 / 2) > corridor_y1)
    walk_b = route_b[inside:]
    geo, runner = _geometry()
    try:
        for fa in walk_a:  # the map: the corridor and room 0
            geo.on_frame(_msg(fa, "a"))
        for fb in walk_b[:15]:  # a live robot (it starts mid-walk: no playback from its first frame)
            geo.on_frame(_msg(fb, "b", offset=True, live=True))
        robot = geo.robots.robots["b"]
        # A first attempt, from inside room 1: nothing of the map in view, so it stays held.
        wait_until(lambda: (robot.join_attempts >= 1 and not robot.attempt_pending) or None, timeout_s=120)
        assert robot.state == "held" and robot.frames_integrated == 0
        assert geo.robot_status()["b"]["state"] == "held"
        assert runner.counter(GeometryCounter.ROBOTS_HELD) == 1
        # Out into the corridor and room 0 (mapped space), as a camera would: an attempt every
        # join_attempt_every frames, each waited for, until one joins it.
        every = geo.robots.params.join_attempt_every
        fed = 15
        while robot.state == "held" and fed < len(walk_b):
            attempts = robot.join_attempts
            for fb in walk_b[fed:fed + every]:
                geo.on_frame(_msg(fb, "b", offset=True, live=True))
            fed += every
            wait_until(lambda: (robot.join_attempts > attempts and not robot.attempt_pending) or None,  # noqa: B023
                       timeout_s=120)
        assert robot.state == "joined", robot.last_registration
        wait_until(lambda: runner.counter(GeometryCounter.ROBOTS_JOINED) >= 1 or None, timeout_s=60)
        assert fed < len(walk_b) - every  # joined well before the end of its walk
        for fb in walk_b[fed:]:
            geo.on_frame(_msg(fb, "b", offset=True, live=True))
        # Every frame in the map, those from room 1 too (through the transform found).
        assert robot.frames_integrated == len(walk_b) and not robot.skipped
        metres, degrees = pose_difference(T_MAP_ODOM, robot.T_map_odom)
        assert metres <= 0.03 and degrees <= 0.5, (metres, degrees)
        assert runner.counter(GeometryCounter.FRAMES_HELD) >= 16
    finally:
        geo.close()


def test_the_frame_queue_serves_publishers_in_turn(sessions) -> None:  # noqa: ANN001
    """A flood of 300 samples from one publisher and 10 from another into a fair queue of 16 that is
    read slowly: every one of the 10 arrives (the flood loses only its own oldest), and the two
    alternate while both have samples waiting."""
    s1, s2, port = sessions
    key = f"test/fair/{port}"
    handled: list[str] = []
    gate = threading.Event()

    def slow(msg: ControlRequest) -> None:
        gate.wait(10)
        handled.append(str(msg.path))

    sub = Subscriber(s2, key, ControlRequest, slow, queue_size=16, fair=True)
    try:
        flood, few = Publisher(s1, key), Publisher(s1, key)
        assert flood.wait_for_subscribers(10) and few.wait_for_subscribers(10)
        for i in range(300):
            flood.put(ControlRequest(action="save", path=f"flood-{i}"))
            if i % 30 == 0:
                few.put(ControlRequest(action="save", path=f"few-{i // 30}"))
        wait_until(lambda: sub.arrived >= 310 or None, timeout_s=30)
        gate.set()
        # Every sample accounted for: handled, or dropped from its publisher's full queue (which
        # sample the reader had in hand when the flood came depends on timing: a flood or a few one).
        wait_until(lambda: (sub.queued == 0 and len(handled) + sub.dropped_queue >= 310) or None, timeout_s=30)
    finally:
        sub.close()
    few_handled = [p for p in handled if p.startswith("few")]
    assert few_handled == [f"few-{i}" for i in range(10)]
    assert len(handled) - len(few_handled) <= 17  # the flood's queue of 16, and the one in hand
    assert sub.dropped_queue >= 300 - 17
    # In turn: after the sample in hand, no two flood samples in a row while few ones wait.
    assert handled.index("few-9") <= 1 + 2 * 10
