"""A still camera's candidates reuse its last render of the map (``select_still_s``,
:mod:`openfusion.mapping.still_views`), and only while nothing the render shows can have changed.

Shown on the built-in room with its depth noise, a real volume and the scorer: frames from one pose
are rendered once and score as they would on a render of their own; a render is made again when the
labels changed (the caller's version), the camera moved or turned, something stepped in front of it
(the frame's depth disagrees with the depth of the frame the render was kept for), the kept render
is older than ``select_still_s``, for another robot, and always without a version or with the rule
off. Bad input tried: a kept render of another size, a frame with no depth at all (neither is
reused)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from openfusion.frame import resize_nearest
from openfusion.mapping import SemanticVolume
from openfusion.mapping.coverage import CoverageScorer, scoring_size
from openfusion.mapping.params import SelectParams, VolumeParams
from openfusion.mapping.still_views import StillViews, pose_moved, same_surface
from openfusion.sources import open_source

# Pose 0 held for 6 frames (stop=5), then the walk goes on.
FRAMES = list(open_source("synthetic:frames=10,width=160,height=120,lap=40,stop=5"))
STILL = FRAMES[:6]
MOVED = FRAMES[7]


@pytest.fixture(scope="module")
def volume() -> SemanticVolume:
    vol = SemanticVolume(VolumeParams())
    for frame in FRAMES:
        vol.integrate(frame)
    return vol


class CountingRender:
    def __init__(self, volume: SemanticVolume) -> None:
        self.volume = volume
        self.calls = 0

    def __call__(self, T_world_cam, K, depth_m=None):  # noqa: ANN001, ANN204
        """The map's view as the scorer asks it: a probe at the frame's depth (the default
        ``select_view``), a render without one."""
        self.calls += 1
        return self.volume.render(T_world_cam, K) if depth_m is None else self.volume.probe(T_world_cam, K, depth_m)


def _scores(scorer: CoverageScorer, frames, render, **kw) -> list:  # noqa: ANN001
    return [scorer.score(scorer.prepare_frame(f, render, **kw)) for f in frames]


def test_frames_from_one_pose_are_rendered_once_and_score_as_on_their_own_render(volume: SemanticVolume) -> None:
    still = CoverageScorer(SelectParams())
    render = CountingRender(volume)
    reused = _scores(still, STILL, render, labels_version=0)
    assert render.calls == 1 and still.still.reused == len(STILL) - 1
    every = CoverageScorer(SelectParams(select_still_s=None))
    fresh = CountingRender(volume)
    own = _scores(every, STILL, fresh, labels_version=0)
    assert fresh.calls == len(STILL) and every.still.reused == 0
    assert [s.gain for s in reused] == pytest.approx([s.gain for s in own])
    assert reused[0].gain > 0.5  # the map holds no labels: every view is new surface, and stays new


def test_changed_labels_a_moved_camera_or_another_robot_render_again(volume: SemanticVolume) -> None:
    scorer = CoverageScorer(SelectParams())
    render = CountingRender(volume)
    scorer.prepare_frame(STILL[0], render, labels_version=0)
    scorer.prepare_frame(STILL[1], render, labels_version=1)  # an update since
    assert render.calls == 2
    scorer.prepare_frame(STILL[2], render, labels_version=1)
    assert render.calls == 2
    assert pose_moved(STILL[0].T_world_cam, MOVED.T_world_cam)[0] > 0.01
    scorer.prepare_frame(MOVED, render, labels_version=1)
    assert render.calls == 3
    turned = dataclasses.replace(STILL[3], T_world_cam=_turned(STILL[3].T_world_cam, 2.0))
    scorer.prepare_frame(turned, render, labels_version=1)
    assert render.calls == 4
    scorer.prepare_frame(STILL[4], render, robot="r2", labels_version=1)  # r2 has no render kept
    assert render.calls == 5
    assert scorer.still.reused == 1


def test_something_in_front_of_a_still_camera_makes_it_render_again(volume: SemanticVolume) -> None:
    scorer = CoverageScorer(SelectParams())
    render = CountingRender(volume)
    scorer.prepare_frame(STILL[0], render, labels_version=0)
    depth = STILL[1].depth.copy()  # a person 1 m away over a tenth of the view
    h, w = depth.shape
    depth[h // 4: 3 * h // 4, w // 2: w // 2 + w // 5] = int(1.0 * STILL[1].depth_scale)
    scorer.prepare_frame(dataclasses.replace(STILL[1], depth=depth), render, labels_version=0)
    assert render.calls == 2
    scorer.prepare_frame(STILL[2], render, labels_version=0)  # the kept render is the one with the person
    assert render.calls == 3


def test_a_kept_render_is_not_reused_past_select_still_s_nor_without_a_version(volume: SemanticVolume) -> None:
    scorer = CoverageScorer(SelectParams(select_still_s=0.05))  # stamps are 33 ms apart
    render = CountingRender(volume)
    _scores(scorer, STILL[:3], render, labels_version=0)
    assert render.calls == 2  # frame 1 reuses frame 0's, frame 2 is 67 ms after it
    _scores(scorer, STILL[3:], render)  # a caller that does not know the labels' version
    assert render.calls == 5


def test_bad_input_a_render_of_another_size_or_a_frame_without_depth_is_not_reused(volume: SemanticVolume) -> None:
    views = StillViews(still_s=2.0, still_m=0.01, still_deg=1.0)
    frame = STILL[0]
    h, w = scoring_size(frame.intrinsics, 64)
    K = frame.intrinsics.scaled(w, h)
    rendered = volume.render(frame.T_world_cam, K)
    small = resize_nearest(frame.depth_m(), (h, w))
    views.keep("", frame.T_world_cam, K, small, 0.0, 0, rendered)
    assert views.reuse("", frame.T_world_cam, K, small, 0.01, 0) is rendered
    K2 = frame.intrinsics.scaled(32, 24)
    assert views.reuse("", frame.T_world_cam, K2, resize_nearest(frame.depth_m(), (24, 32)), 0.01, 0) is None
    assert views.reuse("", frame.T_world_cam, K, np.zeros((h, w), np.float32), 0.01, 0) is None
    assert not same_surface(small, small[:, :-1])


def _turned(T: np.ndarray, degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    out = np.array(T, np.float64)
    out[:3, :3] = out[:3, :3] @ R
    return out
