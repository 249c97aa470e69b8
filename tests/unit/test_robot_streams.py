"""Each robot's stream (openfusion.mapping.robot_streams): chains per robot, who is joined at once and
who is held, the hold's bound and the replay after it, re-check bounds, and what a checkpoint keeps.

Bad inputs tried: robot_frames entries with an unknown mode, a robot named twice, a transform of
three numbers, a non-number, a transform on 'search' (each refused naming the entry); a
re-check that proposes a jump over the bound (refused, transform kept)."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.mapping.params import JoinParams
from openfusion.mapping.robot_join import Registration
from openfusion.mapping.robot_streams import (
    Admission,
    RobotFramesError,
    RobotStreams,
    parse_robot_frames,
    yaw_transform,
)
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld

FRAMES = list(SyntheticSource(SyntheticWorld(0), num_frames=6, width_px=40, height_px=30))


def test_robot_frames_parse_and_name_a_bad_entry() -> None:
    specs = parse_robot_frames("robot0=fixed; robot1 = guess:0.3,0,0,5 ;robot2=search;")
    assert [specs[n].mode for n in ("robot0", "robot1", "robot2")] == ["fixed", "guess", "search"]
    np.testing.assert_allclose(specs["robot1"].T_map_odom, yaw_transform(0.3, 0, 0, 5))
    np.testing.assert_array_equal(specs["robot0"].T_map_odom, np.eye(4))
    for bad, says in [("r1=teleport", "not ROBOT=fixed|guess|search"), ("r1=fixed;r1=search", "twice"),
                      ("r1=guess:1,2,3", "4 finite numbers"), ("r1=guess:1,x,0,0", "must be numbers"),
                      ("r1=search:1,0,0,0", "takes no transform"), ("r/1=fixed", "not ROBOT=")]:
        with pytest.raises(RobotFramesError, match=says):
            parse_robot_frames(bad)


def test_two_robots_chains_do_not_disturb_each_other() -> None:
    """Interleaved playbacks of two robots with the same frame ids: every frame taken once; a
    repeat is a duplicate and a skipped frame out of order only for its own robot."""
    streams = RobotStreams()
    a = streams.get("a", map_empty=True)
    b = streams.get("b", map_empty=True)
    for i in range(3):
        for robot, playback in ((a, "pa"), (b, "pb")):
            assert robot.admit(playback=playback, frame_id=i, prev_frame_id=i - 1) is Admission.TAKE
            robot.took(playback=playback, frame_id=i, stamp_ns=0)
    assert a.admit(playback="pa", frame_id=1, prev_frame_id=0) is Admission.DUPLICATE
    assert b.admit(playback="pb", frame_id=5, prev_frame_id=4) is Admission.OUT_OF_ORDER
    assert b.announce_due and b.holds() == ("pb", 2)
    assert not a.announce_due and a.holds() == ("pa", 2)
    assert a.admit(playback="pa", frame_id=3, prev_frame_id=2) is Admission.TAKE  # a goes on regardless
    assert dict(a.skipped) == {"duplicate": 1} and dict(b.skipped) == {"out_of_order": 1}


def test_live_gaps_are_counted_per_robot() -> None:
    streams = RobotStreams()
    a, b = streams.get("a", map_empty=True), streams.get("b", map_empty=True)
    for robot, ids in ((a, [0, 1, 5]), (b, [0, 9])):
        for i in ids:
            assert robot.admit(playback="", frame_id=i, prev_frame_id=None) is Admission.TAKE
            robot.took(playback="", frame_id=i, stamp_ns=0)
    assert (a.frames_gap, b.frames_gap) == (3, 8)


def test_fixed_robots_define_the_maps_frame_and_nobody_else_anchors_it() -> None:
    streams = RobotStreams(specs=parse_robot_frames("f=fixed"))
    first = streams.get("a", map_empty=True)  # first, but the fixed robot holds the map's frame
    assert first.state == "held" and not first.anchor
    assert streams.get("f", map_empty=True).state == "joined"


def test_the_first_robot_anchors_an_empty_map_others_are_held_fixed_ones_joined() -> None:
    streams = RobotStreams(specs=parse_robot_frames("c=guess:1,2,0,90"))
    first = streams.get("a", map_empty=True)
    assert first.state == "joined" and first.anchor and first.join_method == "anchor"
    second = streams.get("b", map_empty=True)  # the map is empty, but a already anchors it
    assert second.state == "held" and not second.anchor
    guessed = streams.get("c", map_empty=False)
    assert guessed.state == "held"
    fixed = RobotStreams(specs=parse_robot_frames("c=fixed:1,2,0,90")).get("c", map_empty=True)
    assert fixed.state == "joined" and fixed.join_method == "fixed" and not fixed.anchor
    moved = fixed.to_map(FRAMES[0])
    np.testing.assert_allclose(moved.T_world_cam, yaw_transform(1, 2, 0, 90) @ FRAMES[0].T_world_cam)
    assert streams.get("d", map_empty=False).state == "held"  # a map loaded from disk: nothing anchors


def test_a_held_robot_keeps_its_frames_for_the_join_and_a_full_hold_replays_the_rest() -> None:
    streams = RobotStreams(JoinParams(join_max_held_frames=3, join_min_submap_frames=2, join_min_submap_points=10))
    streams.get("a", map_empty=True)
    b = streams.get("b", map_empty=True)
    for frame in FRAMES[:5]:
        assert b.admit(playback="pb", frame_id=frame.frame_id, prev_frame_id=frame.frame_id - 1) is Admission.TAKE
        b.hold(frame, playback="pb", frame_id=frame.frame_id, prev_frame_id=frame.frame_id - 1)
        b.took(playback="pb", frame_id=frame.frame_id, stamp_ns=0)
    assert len(b.held) == 3 and b.hold_overflowed and b.attempt_due(map_blocks=100)
    assert b.skipped["held_dropped"] == 0  # a playback's frames past the hold are replayed, not lost
    T = yaw_transform(0.3, 0, 0, 5)
    frames = b.join(T, method="global")
    assert [h.frame_id for h in frames] == [0, 1, 2]
    assert b.state == "joined" and len(b.held) == 0 and len(b.submap) == 0
    # The chain is back at the last frame kept: frame 3 must come again. The bridge is asked for the
    # frames from the first held one on: the semantic service skipped them while b was held.
    assert b.holds() == ("pb", 2) and b.announce_due and b.waiting
    assert b.announcement() == ("pb", -1) and b.announcement() == ("pb", 2)  # then, while waiting, frame 3 on
    assert b.admit(playback="pb", frame_id=5, prev_frame_id=4) is Admission.OUT_OF_ORDER
    assert b.admit(playback="pb", frame_id=3, prev_frame_id=2) is Admission.TAKE


def test_a_live_robot_past_its_hold_loses_those_frames_counted() -> None:
    streams = RobotStreams(JoinParams(join_max_held_frames=2))
    streams.get("a", map_empty=True)
    b = streams.get("b", map_empty=True)
    for frame in FRAMES[:5]:
        b.hold(frame, playback="", frame_id=frame.frame_id)
    assert len(b.held) == 2 and b.skipped["held_dropped"] == 3


def _registration(T: np.ndarray, *, accepted: bool = True) -> Registration:
    return Registration(T, 0.8, 0.01, 0.0, 0.2, "icp", accepted, "" if accepted else "fitness too low", 100, 100)


def test_a_recheck_corrects_within_its_bounds_only() -> None:
    streams = RobotStreams(specs=parse_robot_frames("b=guess:0,0,0,0"))
    streams.get("a", map_empty=True)
    b = streams.get("b", map_empty=False)
    b.join(np.eye(4), method="icp")
    assert b.apply_recheck(_registration(yaw_transform(0.003, 0, 0, 0.05))) == "kept"
    # One re-check alone does not move the transform; the next one agreeing does.
    assert b.apply_recheck(_registration(yaw_transform(0.05, 0, 0, 0.5))).startswith("pending: 5.0 cm")
    np.testing.assert_array_equal(b.T_map_odom, np.eye(4))
    assert b.apply_recheck(_registration(yaw_transform(0.02, 0, 0, 0))).startswith("pending")  # disagrees
    assert b.apply_recheck(_registration(yaw_transform(0.024, 0, 0, 0.05))).startswith("corrected by 2.4 cm")
    np.testing.assert_allclose(b.T_map_odom, yaw_transform(0.024, 0, 0, 0.05))
    assert b.apply_recheck(_registration(yaw_transform(1.0, 0, 0, 0))).startswith("refused: a correction of")
    assert b.apply_recheck(_registration(np.eye(4), accepted=False)) == "refused: fitness too low"
    np.testing.assert_allclose(b.T_map_odom, yaw_transform(0.024, 0, 0, 0.05))
    assert b.corrections == 1


def test_rechecks_come_every_n_frames_and_never_for_the_anchor_or_a_fixed_robot() -> None:
    streams = RobotStreams(JoinParams(join_recheck_every=3), specs=parse_robot_frames("c=fixed"))
    a = streams.get("a", map_empty=True)
    b = streams.get("b", map_empty=True)
    b.join(np.eye(4), method="global")
    c = streams.get("c", map_empty=False)
    assert [b.recheck_due() for _ in range(6)] == [False, False, True, False, False, True]
    assert not any(a.recheck_due() or c.recheck_due() for _ in range(6))


def test_a_checkpoint_keeps_what_the_map_holds_of_each_robot() -> None:
    streams = RobotStreams()
    a = streams.get("a", map_empty=True)
    b = streams.get("b", map_empty=True)
    for i in range(3):
        a.took(playback="pa", frame_id=i, stamp_ns=0)
        a.in_map(playback="pa", frame_id=i, stamp_ns=0)
        b.hold(FRAMES[i], playback="pb", frame_id=i)  # held: not in the map
        b.took(playback="pb", frame_id=i, stamp_ns=0)
    meta = streams.to_meta()
    restored = RobotStreams()
    restored.restore(meta, default_robot="robot0")
    ra, rb = restored.robots["a"], restored.robots["b"]
    assert ra.holds() == ("pa", 2) and ra.state == "joined" and ra.anchor
    assert rb.holds() == ("", -1) and rb.state == "held"  # its held frames are replayed from the start
    assert ra.waiting and rb.waiting  # both announce where their playbacks continue


def test_a_map_from_before_robots_is_the_default_robots() -> None:
    restored = RobotStreams()
    restored.restore({"last_frame_id": 41, "playback": "p1", "frames_integrated": 42}, default_robot="robot0")
    robot = restored.robots["robot0"]
    assert robot.holds() == ("p1", 41) and robot.state == "joined" and robot.frames_integrated == 42
    empty = RobotStreams()
    empty.restore({"frames_integrated": 0}, default_robot="robot0")
    assert len(empty) == 0


def test_health_carries_each_robot_and_the_health_command_prints_them() -> None:
    """What geometry reports per robot validates as the wire's RobotStatus, and `openfusion health`
    prints a row per robot: joined with its transform, held with why."""
    from openfusion.app.bus_cmds import robots_table
    from openfusion.mapping.robot_join import Registration
    from openfusion.wire.schemas import HealthStats

    streams = RobotStreams()
    streams.get("robot0", map_empty=True)
    held = streams.get("robot1", map_empty=True)
    held.join_attempts = 2
    held.last_registration = Registration(np.eye(4), 0.19, 0.01, 0.0, 0.2, "global", False,
                                          "fitness 0.19 < 0.35 (too little of the submap is on the map)", 10, 10)
    fixed = RobotStreams(specs=parse_robot_frames("robot2=fixed:1.5,-2,0,90")).get("robot2", map_empty=False)
    robots = {r.name: r.status() for r in (*streams, fixed)}
    stats = HealthStats(service="geometry", map_id="m", pid=1, uptime_s=1.0, fps=0.0, latency_ms_p50=0.0,
                        latency_ms_p99=0.0, drops=0, errors=0, robots=robots)
    assert stats.robots["robot1"].state == "held" and stats.robots["robot2"].join_method == "fixed"
    table = robots_table({"geometry": stats}).splitlines()
    assert table[0].split()[:4] == ["robot", "state", "integrated", "held"]
    row = {line.split()[0]: line for line in table[1:]}
    assert "anchor" in row["robot0"] and "2 attempt(s): fitness 0.19 < 0.35" in row["robot1"]
    assert row["robot2"].split()[7:11] == ["1.500", "-2.000", "0.000", "90.00"]
    assert robots_table({}) == ""


def test_an_idle_held_robot_is_tried_again_when_the_map_grows_and_over_its_whole_hold() -> None:
    """A held robot that sends nothing more (its playback ran ahead and ended) is tried again once
    idle: on each stretch of its hold, and again whenever the map has grown by a tenth; never in a
    loop when nothing changed."""
    params = JoinParams(join_min_submap_frames=2, join_min_submap_points=10, join_submap_frames=2,
                        join_attempt_every=100, join_idle_attempt_s=1.0)
    streams = RobotStreams(params)
    streams.get("a", map_empty=True)
    b = streams.get("b", map_empty=True)
    for frame in FRAMES[:6]:  # window: the last 2; hold: all 6, so two stretches outside the window
        b.hold(frame, playback="pb", frame_id=frame.frame_id, prev_frame_id=frame.frame_id - 1)
    now = b.last_held_at_s
    assert b.hold_stretches == 2
    assert b.attempt_due(map_blocks=100, now_s=now)  # the first attempt comes at once
    tried = []
    for _ in range(5):
        later = max(b.last_held_at_s, b.last_attempt_at_s) + 1.5
        if not b.attempt_due(map_blocks=100, now_s=later):
            break
        b.attempted(map_blocks=100)
        b.attempt_pending = False
        tried.append(b.stretches_tried)
    assert tried == [1, 2]  # the recent window with stretch 1, then stretch 2; then nothing changed
    later = b.last_attempt_at_s + 1.5
    assert not b.attempt_due(map_blocks=105, now_s=later)  # grew by less than a tenth
    assert b.attempt_due(map_blocks=120, now_s=later)  # grew: again
