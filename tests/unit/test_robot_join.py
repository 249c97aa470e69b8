"""Joining a robot's odometry frame to the map's (openfusion.mapping.robot_join): a submap of the
built-in room seen by a robot whose odometry is 0.3 m and 5 degrees off the map's frame.

Bad inputs tried: a guess with NaN entries and one that is not a rigid transform (refused, naming
the guess); a submap of a handful of points (refused with the reason, never accepted); a submap of
another room (not accepted); a bare corridor (refused as under-constrained)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from openfusion.mapping import SemanticVolume, VolumeParams
from openfusion.mapping.params import JoinParams
from openfusion.mapping.robot_join import Submap, pose_difference, register_submap
from openfusion.poses import InvalidPoseError
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld

# The offset: 0.3 m and 5 degrees (yaw, the odometry frame is gravity-aligned).
OFFSET_M = (0.25, -0.15, 0.05)
OFFSET_DEG = 5.0
MAX_ERROR_M = 0.03
MAX_ERROR_DEG = 0.5


def yaw_pose(deg: float, t: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    a = np.deg2rad(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = t
    return T


T_MAP_ODOM = yaw_pose(OFFSET_DEG, OFFSET_M)  # what the registration must find


@pytest.fixture(scope="module")
def room() -> tuple[list, np.ndarray]:
    """120 frames (one lap) of the built-in room at 320x240, and the surface of a map made from
    the first half of the lap in the map's frame."""
    frames = list(SyntheticSource(SyntheticWorld(0), num_frames=120, width_px=320, height_px=240))
    volume = SemanticVolume(VolumeParams(initial_block_count=4096))
    for frame in frames[:60]:
        volume.integrate(frame)
    return frames, volume.extract_points().points.astype(np.float64)


def submap_of(frames: list, ids: range, T_map_odom: np.ndarray = T_MAP_ODOM) -> Submap:
    """The frames as a robot whose odometry frame is ``T_map_odom`` from the map's reports them."""
    submap = Submap(JoinParams().join_voxel_m)
    T_odom_map = np.linalg.inv(T_map_odom)
    for i in ids:
        frame = frames[i]
        submap.add(dataclasses.replace(frame, T_world_cam=T_odom_map @ frame.T_world_cam))
    return submap


def test_a_submap_over_mapped_space_is_found_without_a_guess(room) -> None:
    frames, map_points = room
    found = register_submap(submap_of(frames, range(40, 70)).points, map_points, JoinParams())
    assert found.accepted, found.reason
    assert found.method == "global"
    metres, degrees = pose_difference(T_MAP_ODOM, found.T_map_odom)
    assert metres <= MAX_ERROR_M and degrees <= MAX_ERROR_DEG, (metres, degrees)
    assert found.fitness > found.runner_up_fitness


def test_a_guess_is_refined_by_icp(room) -> None:
    frames, map_points = room
    guess = yaw_pose(3.0, (0.15, -0.05, 0.0))  # 2 degrees and ~15 cm off the truth
    found = register_submap(submap_of(frames, range(50, 60)).points, map_points, JoinParams(), guess=guess)
    assert found.accepted and found.method == "icp", found.reason
    metres, degrees = pose_difference(T_MAP_ODOM, found.T_map_odom)
    assert metres <= MAX_ERROR_M and degrees <= MAX_ERROR_DEG, (metres, degrees)


def test_a_submap_of_another_room_is_not_accepted(room) -> None:
    """A robot in a room the map has never seen (another seed): whatever the search finds, it is
    refused, so nothing is fused misaligned."""
    _frames, map_points = room
    elsewhere = list(SyntheticSource(SyntheticWorld(7), num_frames=120, width_px=320, height_px=240))
    found = register_submap(submap_of(elsewhere, range(40, 70)).points, map_points, JoinParams())
    assert not found.accepted
    assert found.reason


def test_a_bare_corridor_is_under_constrained() -> None:
    """Two long parallel walls and a floor: any shift along the corridor fits, so no registration
    is accepted even from the right guess."""
    rng = np.random.default_rng(0)
    along = rng.uniform(0.0, 12.0, 6000)
    up = rng.uniform(0.0, 2.5, 6000)
    walls = np.c_[along, np.where(np.arange(6000) % 2 == 0, 0.0, 2.0), up]
    floor = np.c_[rng.uniform(0.0, 12.0, 4000), rng.uniform(0.0, 2.0, 4000), np.zeros(4000)]
    corridor = np.concatenate([walls, floor])
    seen = corridor[(corridor[:, 0] > 3.0) & (corridor[:, 0] < 7.0)]
    found = register_submap(seen, corridor, JoinParams(join_min_submap_points=100), guess=np.eye(4))
    assert not found.accepted
    assert "under-constrained" in found.reason


def test_too_few_points_are_refused_with_the_reason(room) -> None:
    _frames, map_points = room
    found = register_submap(np.zeros((5, 3)), map_points, JoinParams())
    assert not found.accepted and "too few points" in found.reason


@pytest.mark.parametrize("bad", [np.full((4, 4), np.nan), np.diag([2.0, 1.0, 1.0, 1.0])])
def test_a_bad_guess_is_refused(room, bad: np.ndarray) -> None:
    _frames, map_points = room
    with pytest.raises(InvalidPoseError, match="guess"):
        register_submap(map_points[:2000], map_points, JoinParams(), guess=bad)
