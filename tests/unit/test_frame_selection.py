"""Coverage-driven frame selection (openfusion.mapping.selection): one test per rule of the scorer,
the candidate window, and the in-process pipeline with a real map.

Views here are hand-made: a camera 2 m in front of a wall (every pixel at 2 m depth), the map's
render given as key and confidence maps, so each rule is tested on its own. Bad inputs tried: a
render or depth of another size than the scored view (refused with the sizes named), a merge that
names a region the scorer never saw, a window asked for a candidate when none is worth encoding
(returns none, drops the ones that fell under the gain), parameters out of range (refused by the
declaration)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from openfusion.frame import CameraIntrinsics
from openfusion.mapping import VolumeParams
from openfusion.mapping.map_clock import MapClock
from openfusion.mapping.params import SelectParams
from openfusion.mapping.pipeline import map_scene
from openfusion.mapping.selection import (
    CandidateWindow,
    CoverageScorer,
    FrameSelector,
    fibonacci_directions,
    scoring_size,
)
from openfusion.poses import look_at
from openfusion.sources import open_source
from openfusion.testing.analytic_scene import AnalyticScene, Room
from openfusion.testing.encoders import FlakyEncoder

W, H = 16, 12
K = CameraIntrinsics(W, H, 14.0, 14.0, (W - 1) / 2, (H - 1) / 2)
# Camera at the origin looking along +x at a wall 2 m away (up +z).
T_FRONT = look_at(np.array([0.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), up=np.array([0.0, 0.0, 1.0]))
# The same spot from 60 degrees to the side (about half the view in other direction bins) and
# from the opposite side (all of it).
T_SIDE = look_at(np.array([1.0, -1.732, 1.0]), np.array([2.0, 0.0, 1.0]), up=np.array([0.0, 0.0, 1.0]))
T_BACK = look_at(np.array([4.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), up=np.array([0.0, 0.0, 1.0]))
DEPTH = np.full((H, W), 2.0, np.float32)
NO_KEYS = np.full((H, W), -1, np.int32)
ZERO_CONF = np.zeros((H, W), np.float32)
ALL_KEY_7 = np.full((H, W), 7, np.int32)
FULL_CONF = np.ones((H, W), np.float32)


def params(**changes: object) -> SelectParams:
    return SelectParams(**{"select_width_px": W, "select_patience_s": None, **changes})


def view(scorer: CoverageScorer, *, T=T_FRONT, keys=NO_KEYS, conf=ZERO_CONF, depth=DEPTH, stamp_s=0.0, frame_id=0,  # noqa: ANN001, ANN201
         robot=""):
    return scorer.prepare(frame_id=frame_id, stamp_ns=int(stamp_s * 1e9), T_world_cam=T, intrinsics=K,
                          depth_m=depth, key_map=keys, conf_map=conf, robot=robot)


def encoded(scorer: CoverageScorer, ev, *, T=T_FRONT, keys=ALL_KEY_7, stamp_s=0.0) -> None:  # noqa: ANN001
    """A view chosen, encoded, and its planned update recorded."""
    scorer.mark_selected(ev)
    scorer.observe_plan(keys, T, K, int(stamp_s * 1e9), robot=ev.robot)


def test_new_surface_an_unlabelled_view_is_worth_encoding() -> None:
    scorer = CoverageScorer(params())
    score = scorer.score(view(scorer))
    assert score.new_surface == pytest.approx(1.0) and score.gain == pytest.approx(1.0)
    assert scorer.worth_encoding(score)
    # half the view labelled confidently: half of it is new surface
    keys = NO_KEYS.copy()
    keys[:, : W // 2] = 7
    conf = np.where(keys >= 0, 1.0, 0.0).astype(np.float32)
    assert scorer.score(view(scorer, keys=keys, conf=conf)).new_surface == pytest.approx(0.5)
    # a confidence under select_low_conf is no label: still new
    low = np.full((H, W), 0.1, np.float32)
    assert scorer.score(view(scorer, keys=ALL_KEY_7, conf=low)).new_surface == pytest.approx(1.0)
    # pixels without depth are no surface: they add nothing
    depth = DEPTH.copy()
    depth[:, W // 2:] = 0
    score = scorer.score(view(scorer, depth=depth))
    assert score.new_surface == pytest.approx(0.5) and score.surface == pytest.approx(0.5)


def test_nothing_new_no_call() -> None:
    """A view the encoder just labelled, seen again: no gain, not encoded."""
    scorer = CoverageScorer(params())
    first = view(scorer)
    encoded(scorer, first)
    again = view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, frame_id=1, stamp_s=0.1)
    score = scorer.score(again)
    assert score.gain == 0.0 and not scorer.worth_encoding(score)
    # min gain 0 still refuses a view with no gain at all
    assert not CoverageScorer(params(select_min_gain=0.0)).worth_encoding(score)


def test_a_little_new_surface_is_encoded_once_it_has_waited_select_patience() -> None:
    """Two of 16 columns new (12 %): under select_min_gain 0.2 right after a chosen view, over the
    bar once the frame time since it makes the bar fall (0.2 / (1 + t / 0.1 s))."""
    scorer = CoverageScorer(params(select_min_gain=0.2, select_patience_s=0.1, select_min_views=0))
    encoded(scorer, view(scorer, stamp_s=10.0), stamp_s=10.0)
    keys = ALL_KEY_7.copy()
    keys[:, :2] = -1
    conf = np.where(keys >= 0, 1.0, 0.0).astype(np.float32)
    depth = DEPTH.copy()
    depth[:, :2] = 3.0  # surface the chosen view did not show (another cube)
    soon = scorer.score(view(scorer, keys=keys, conf=conf, depth=depth, stamp_s=10.03))
    later = scorer.score(view(scorer, keys=keys, conf=conf, depth=depth, stamp_s=10.1))
    assert soon.gain == later.gain == pytest.approx(2 / 16)
    assert scorer.min_gain_at(10.0) == pytest.approx(0.2) and scorer.min_gain_at(10.1) == pytest.approx(0.1)
    assert not scorer.worth_encoding(soon) and scorer.worth_encoding(later)
    # nothing new never passes, however long it waited
    assert not scorer.worth_encoding(scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=50.0)))


def test_the_patience_rule_runs_on_each_robots_own_frames() -> None:
    """Two robots whose stamps interleave (both started at 0): robot a's view chosen at 10.0 s does
    not hold robot b's bar up at 10.0 s; b's bar falls with the time since b's own last chosen view.
    (With one record of stamps, the robots' chosen frames held each other's bar at the top, and a
    two-robot map fell 0.013 f-mIoU under one robot walking both routes.)"""
    scorer = CoverageScorer(params(select_min_gain=0.2, select_patience_s=0.1, select_min_views=0))
    encoded(scorer, view(scorer, stamp_s=9.9, robot="b"), stamp_s=9.9)
    encoded(scorer, view(scorer, stamp_s=10.0, robot="a"), stamp_s=10.0)
    assert scorer.min_gain_at(10.0, "a") == pytest.approx(0.2)
    assert scorer.min_gain_at(10.0, "b") == pytest.approx(0.1)
    keys = ALL_KEY_7.copy()
    keys[:, :2] = -1
    conf = np.where(keys >= 0, 1.0, 0.0).astype(np.float32)
    depth = DEPTH.copy()
    depth[:, :2] = 3.0  # 2 of 16 columns of surface no chosen view showed
    for robot, chosen in (("a", False), ("b", True)):
        score = scorer.score(view(scorer, keys=keys, conf=conf, depth=depth, stamp_s=10.0, robot=robot))
        assert score.robot == robot and score.gain == pytest.approx(2 / 16)
        assert scorer.worth_encoding(score) is chosen, robot


def test_unlabelled_surface_is_tried_select_tries_times_per_direction() -> None:
    """Surface the encoder leaves unlabelled is new until ``select_tries`` encoded frames showed it
    from the same direction bin; from another bin it is new again."""
    scorer = CoverageScorer(params(select_tries=2, select_min_views=0))
    for tries in range(2):
        ev = view(scorer, frame_id=tries)
        assert scorer.score(ev).new_surface == pytest.approx(1.0), f"try {tries + 1} should still count"
        encoded(scorer, ev, keys=NO_KEYS)  # the encoder labelled nothing
    assert scorer.score(view(scorer, frame_id=2)).gain == 0.0
    assert scorer.score(view(scorer, T=T_BACK, frame_id=3)).new_surface == pytest.approx(1.0)


def test_new_direction_of_a_region_counts_and_the_same_direction_does_not() -> None:
    scorer = CoverageScorer(params(select_min_views=0, select_direction_weight=0.5))
    encoded(scorer, view(scorer))
    same = scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, frame_id=1))
    side = scorer.score(view(scorer, T=T_SIDE, keys=ALL_KEY_7, conf=FULL_CONF, frame_id=2))
    back = scorer.score(view(scorer, T=T_BACK, keys=ALL_KEY_7, conf=FULL_CONF, frame_id=3))
    assert same.new_direction == 0.0
    assert 0.2 < side.new_direction < 0.9 and side.new_surface == 0.0
    assert back.new_direction == pytest.approx(1.0)
    assert side.gain == pytest.approx(0.5 * side.new_direction)
    assert scorer.worth_encoding(side) and scorer.worth_encoding(back)
    # a region too small in the view does not count
    tiny = NO_KEYS.copy()
    tiny[0, 0] = 7
    scorer2 = CoverageScorer(params(select_min_views=0, select_min_region_share=0.05))
    assert scorer2.score(view(scorer2, T=T_SIDE, keys=tiny, conf=FULL_CONF)).new_direction == 0.0


def test_a_region_with_few_views_counts_until_it_has_select_min_views() -> None:
    scorer = CoverageScorer(params(select_min_views=2))
    encoded(scorer, view(scorer))
    once = scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, frame_id=1))
    assert once.new_direction == pytest.approx(1.0)  # written by one encoded frame: still counts
    encoded(scorer, view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, frame_id=1))
    assert scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, frame_id=2)).gain == 0.0


def test_stale_region_in_view_is_encoded_again_after_select_stale_s() -> None:
    scorer = CoverageScorer(params(select_min_views=0, select_stale_s=30.0))
    encoded(scorer, view(scorer), stamp_s=0.0)
    soon = scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=29.0))
    late = scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=31.0))
    assert soon.gain == 0.0 and soon.stale == 0.0
    assert late.stale == pytest.approx(1.0) and scorer.worth_encoding(late)
    never = CoverageScorer(params(select_min_views=0, select_stale_s=None))
    encoded(never, view(never))
    assert never.score(view(never, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=1e6)).gain == 0.0


def test_staleness_reads_robots_stamps_on_one_clock_when_their_clocks_disagree() -> None:
    """A simulated robot stamped from 0 encodes region 7; a live robot stamped in Unix time then
    sees it. Compared as they come, the live robot's every view of it was 1.7e9 s later: stale for
    ever, encoded again each time. On the map's clock (its first frame is the map's "now") the
    region is seen 10 s after it was encoded (not stale), and 40 s after it is stale as the rule
    says. A third robot whose first stamp is within an hour of the map's time shares its clock."""
    unix_s = 1.7e9
    scorer = CoverageScorer(params(select_min_views=0, select_stale_s=30.0))
    encoded(scorer, view(scorer, stamp_s=5.0, robot="sim"), stamp_s=5.0)
    live_first = scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=unix_s, robot="live"))
    assert live_first.stale == 0.0 and not scorer.worth_encoding(live_first)
    soon = scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=unix_s + 10.0, robot="live"))
    late = scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=unix_s + 40.0, robot="live"))
    assert soon.stale == 0.0 and late.stale == pytest.approx(1.0)
    assert scorer.clock.offset_s("sim") == 0.0 and scorer.clock.offset_s("live") == pytest.approx(5.0 - unix_s)
    # the sim robot's stamps after the live robot joined: 50 s is map time 50, 10 s after the live
    # robot's last view (map 45): nothing re-encoded for staleness there either
    encoded(scorer, view(scorer, stamp_s=44.0, robot="sim"), stamp_s=44.0)
    assert scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=unix_s + 45.0, robot="live")).stale == 0.0
    # a robot on the map's clock (within CLOCK_AGREE_S of its time) keeps its stamps
    assert scorer.score(view(scorer, keys=ALL_KEY_7, conf=FULL_CONF, stamp_s=100.0, robot="synced")).stale == pytest.approx(1.0)
    assert scorer.clock.offset_s("synced") == 0.0
    with pytest.raises(ValueError, match="agree_s"):  # a tolerance that is no time at all
        MapClock(agree_s=float("nan"))


def test_merges_carry_a_regions_coverage_to_the_surviving_region() -> None:
    scorer = CoverageScorer(params(select_min_views=0))
    encoded(scorer, view(scorer), keys=ALL_KEY_7)
    keys_9 = np.full((H, W), 9, np.int32)
    assert scorer.score(view(scorer, keys=keys_9, conf=FULL_CONF)).new_direction == pytest.approx(1.0)
    scorer.merge({7: 9, 12345: 9})  # 12345: a region the scorer never saw
    assert scorer.score(view(scorer, keys=keys_9, conf=FULL_CONF)).gain == 0.0
    scorer.merge({}, removed=[9])
    assert scorer.regions_recorded == 0


def test_a_held_floor_scored_at_32_px_is_not_new_to_the_next_frames() -> None:
    """A chosen view waiting for a busy encoder (held) marks its unsure surface at 192 px or more,
    whatever width it is scored at: a floor 1.5 m below a 640x480 camera, scored at 32 px and held;
    the next frames, 3 and 7 cm further on (the map still unlabelled, as in the services before
    the labels come), show at most 0.2 of their view as new (measured 0.125 / 0.133, as at 64 px:
    0.127 / 0.088). Marks at 3x the score (96 px) left holes between far floor rows: 0.335 / 0.384,
    and the services chose 71 of 90 frames instead of 52."""
    full = CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
    scorer = CoverageScorer(SelectParams(select_width_px=32, select_patience_s=None))
    h, w = scoring_size(full, 32)

    hall = AnalyticScene(room=Room(size_m=(30.0, 20.0, 10.0)))  # only its floor lies within 6 m

    def floor_view(x_m: float, frame_id: int):  # noqa: ANN202
        T = look_at(np.array([2.0 + x_m, 10.0, 1.5]), np.array([6.0 + x_m, 10.0, 0.0]), up=np.array([0.0, 0.0, 1.0]))

        def depth(k: CameraIntrinsics) -> np.ndarray:
            d = hall.render(T, k)[0]
            return np.where(d < 6.0, d, 0.0).astype(np.float32)

        small = full.scaled(w, h)
        return scorer.prepare(frame_id=frame_id, stamp_ns=frame_id * 10**8, T_world_cam=T, intrinsics=small,
                              depth_m=depth(small), key_map=np.full((h, w), -1, np.int32),
                              conf_map=np.zeros((h, w), np.float32), full_depth_m=depth(full), full_intrinsics=full)

    chosen = floor_view(0.0, 0)
    assert chosen.mark_depth_m is not None and chosen.mark_depth_m.shape[1] >= 192
    first = scorer.score(chosen)  # all of its floor (0.6 of the view: the rest is past 6 m) is new
    assert first.new_surface == pytest.approx(first.surface) and first.surface > 0.5
    scorer.hold(chosen)
    for frame_id, x_m in ((1, 0.03), (2, 0.07)):
        assert scorer.score(floor_view(x_m, frame_id)).new_surface <= 0.2


def test_prepare_refuses_maps_of_another_size() -> None:
    scorer = CoverageScorer(params())
    with pytest.raises(ValueError, match=r"key_map is \(6, 8\), the scored view is \(12, 16\)"):
        scorer.prepare(frame_id=0, stamp_ns=0, T_world_cam=T_FRONT, intrinsics=K, depth_m=DEPTH,
                       key_map=np.zeros((6, 8), np.int32), conf_map=ZERO_CONF)


def test_parameters_are_checked_where_they_are_declared() -> None:
    for bad in ({"select": "sometimes"}, {"select_direction_bins": 65}, {"select_window": 0},
                {"select_min_gain": -0.1}, {"select_cell_m": 0}):
        with pytest.raises(ValidationError):
            SelectParams(**bad)


def test_direction_bins_cover_the_sphere_evenly() -> None:
    d = fibonacci_directions(24)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    # every direction on a fine sample of the sphere is within 35 degrees of a bin centre
    rng = np.random.default_rng(0)
    v = rng.normal(size=(2000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    assert np.degrees(np.arccos((v @ d.T).max(axis=1).min())) < 35.0
    assert scoring_size(CameraIntrinsics(640, 480, 500, 500, 319.5, 239.5), 64) == (48, 64)


def test_window_decides_as_frames_come_and_gives_the_best_waiting_frame() -> None:
    """Three frames while the encoder is busy: an unlabelled view (chosen), the same view again
    (nothing new once the first is chosen: dropped at once, even though nothing was encoded yet),
    and one whose left half the map holds as region 7, a region this record never saw encoded (new
    from every direction, at half weight: chosen). The encoder gets the higher gain first."""
    scorer = CoverageScorer(params(select_min_views=0, select_tries=1))
    window: CandidateWindow[str] = CandidateWindow(scorer, capacity=8)
    half = NO_KEYS.copy()
    half[:, : W // 2] = 7
    assert not window.offer(view(scorer, frame_id=0), "blank").no_gain
    assert [c.payload for c in window.offer(view(scorer, frame_id=1), "blank again").no_gain] == ["blank again"]
    change = window.offer(view(scorer, keys=half, conf=np.where(half >= 0, 1.0, 0.0).astype(np.float32),
                               frame_id=2), "half")
    assert not change.no_gain and len(window) == 2
    first, second = window.take(), window.take()
    assert first.taken is not None and first.taken.payload == "blank" and first.taken.score.gain == pytest.approx(1.0)
    assert second.taken is not None and second.taken.payload == "half"
    assert second.taken.score.new_surface == 0.0 and second.taken.score.new_direction == pytest.approx(0.5)
    assert window.take(timeout_s=0.01).taken is None


def test_a_full_window_lets_its_lowest_gain_frame_go() -> None:
    scorer = CoverageScorer(params(select_min_views=0, select_min_gain=0.1))
    window: CandidateWindow[int] = CandidateWindow(scorer, capacity=2)

    def wall_at(depth_m: float, share: float):  # noqa: ANN202
        depth = np.zeros((H, W), np.float32)
        depth[:, : round(W * share)] = depth_m  # surface the others did not show (another cube)
        return depth

    assert not window.offer(view(scorer, depth=wall_at(2.0, 1.0), frame_id=0), 0).evicted
    assert not window.offer(view(scorer, depth=wall_at(3.0, 0.5), frame_id=1), 1).evicted
    change = window.offer(view(scorer, depth=wall_at(4.0, 0.75), frame_id=2), 2)
    assert [c.payload for c in change.evicted] == [1]
    # a view that adds less than select_min_gain is dropped at once (one pixel of new surface)
    one_pixel = np.zeros((H, W), np.float32)
    one_pixel[0, 0] = 5.0
    small = window.offer(view(scorer, depth=one_pixel, frame_id=3), 3)
    assert [c.payload for c in small.no_gain] == [3] and len(window) == 2
    assert [window.take().taken.payload for _ in range(2)] == [0, 2]


def test_a_run_of_select_lookahead_frames_encodes_at_most_its_best() -> None:
    """select_lookahead 3: frames are decided three at a time. Three views of new surface of 25 %,
    100 % and 50 % (each another cube): only the 100 % one is encoded, when the third frame comes
    (the selector returns nothing before); the next run, of views that add nothing, encodes none;
    a run cut short by the end of the source is decided by flush. Greedy (lookahead 1) would have
    encoded all three of the first run."""
    from types import SimpleNamespace

    from openfusion.frame import Frame

    def wall(frame_id: int, depth_m: float, share: float) -> Frame:
        depth = np.zeros((H, W), np.float32)
        depth[:, : round(W * share)] = depth_m
        return Frame(frame_id=frame_id, stamp_ns=frame_id * 100_000_000, color=np.zeros((H, W, 3), np.uint8),
                     depth=depth, depth_scale=1.0, intrinsics=K, T_world_cam=T_FRONT)

    def render(T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> SimpleNamespace:
        return SimpleNamespace(key_map=NO_KEYS, conf_map=ZERO_CONF)

    run = [wall(0, 2.0, 0.25), wall(1, 3.0, 1.0), wall(2, 4.0, 0.5)]
    greedy = FrameSelector(params(select_tries=1, select_min_gain=0.1), render)
    assert [len(greedy.offer(f)) for f in run] == [1, 1, 1]
    selector = FrameSelector(params(select_tries=1, select_min_gain=0.1, select_lookahead=3), render)
    assert selector.offer(run[0]) == [] and selector.offer(run[1]) == []
    assert [f.frame_id for f in selector.offer(run[2])] == [1]
    assert selector.stats.frames_scored == 3 and selector.stats.skipped_no_gain == 2
    # the chosen view's surface is covered: the same wall again adds nothing, the run encodes none
    assert [selector.offer(wall(i, 3.0, 1.0)) for i in (3, 4, 5)] == [[], [], []]
    assert selector.stats.skipped_no_gain == 5
    # a run cut short by the end of the source: flush decides it
    assert selector.offer(wall(6, 5.0, 1.0)) == []
    assert [f.frame_id for f in selector.flush()] == [6] and selector.flush() == []


def test_the_window_decides_select_lookahead_frames_at_a_time_as_one_process_does() -> None:
    """The services' window with select_lookahead 3: the first two frames wait undecided, the third
    completes the run and only its best frame (the 100 % new view) waits for the encoder, the other
    two are dropped (no_gain); a run cut short (frames stopped coming) is decided by flush."""
    scorer = CoverageScorer(params(select_tries=1, select_min_gain=0.1, select_lookahead=3))
    window: CandidateWindow[int] = CandidateWindow(scorer, capacity=8)

    def wall_at(depth_m: float, share: float):  # noqa: ANN202
        depth = np.zeros((H, W), np.float32)
        depth[:, : round(W * share)] = depth_m
        return depth

    for i, (d, share) in enumerate(((2.0, 0.25), (3.0, 1.0))):
        change = window.offer(view(scorer, depth=wall_at(d, share), frame_id=i), i)
        assert not change.no_gain and not change.evicted and len(window) == 0
    assert window.undecided == 2
    change = window.offer(view(scorer, depth=wall_at(4.0, 0.5), frame_id=2), 2)
    assert sorted(c.payload for c in change.no_gain) == [0, 2] and window.undecided == 0
    assert window.take().taken.payload == 1
    window.offer(view(scorer, depth=wall_at(5.0, 1.0), frame_id=3, stamp_s=1.0), 3)
    assert window.take(timeout_s=0.01).taken is None  # undecided: not the encoder's yet
    assert not window.flush().no_gain and window.take().taken.payload == 3


SPEC = "synthetic:frames=8,width=160,height=120"


def test_the_pipeline_encodes_only_frames_that_add_something() -> None:
    """The same frame played six times: every frame is encoded with select=every, the first only
    (then nothing new) with coverage; a real map, the real render."""
    frame = next(iter(open_source(SPEC)))
    frames = [frame.__class__(**{**frame.__dict__, "frame_id": i, "stamp_ns": i * 33_000_000}) for i in range(6)]
    volume = VolumeParams(initial_block_count=2048)
    every = map_scene(frames, region_encoder=FlakyEncoder(empty_on=(), fail_on=()), volume_params=volume,
                      select_params=SelectParams(select="every"))
    assert every.stats.encoder_calls == 6 and every.stats.skipped_no_gain == 0
    once = map_scene(frames, region_encoder=FlakyEncoder(empty_on=(), fail_on=()), volume_params=volume,
                     select_params=SelectParams(select_tries=1))
    assert once.stats.frames_scored == 6
    assert once.stats.encoder_calls == 1 and once.stats.skipped_no_gain == 5
    assert once.stats.encoder_regions >= len(once.dictionary) > 3  # merges may fold some together
    # the default tries the surface the first call left unlabelled once more (a frame's TSDF holes,
    # an encoder's miss), then nothing: at most select_tries calls
    default = map_scene(frames, region_encoder=FlakyEncoder(empty_on=(), fail_on=()), volume_params=volume)
    assert 1 <= default.stats.encoder_calls <= SelectParams().select_tries
    assert default.stats.skipped_no_gain == 6 - default.stats.encoder_calls
    # select_lookahead 4: the first run of four frames is encoded once, the last two (a run cut
    # short by the end of the source) are decided at the end; every frame is decided exactly once
    ahead = map_scene(frames, region_encoder=FlakyEncoder(empty_on=(), fail_on=()), volume_params=volume,
                      select_params=SelectParams(select_tries=1, select_lookahead=4))
    assert ahead.stats.frames_scored == 6 and ahead.stats.encoder_calls == 1
    assert ahead.stats.skipped_no_gain == 5 and ahead.stats.semantic_frames == 1


def test_frame_selector_with_every_or_latest_scores_nothing() -> None:
    frame = next(iter(open_source(SPEC)))
    for mode in ("every", "latest"):
        selector = FrameSelector(SelectParams(select=mode), render=lambda *_: pytest.fail("no render"))
        assert selector.wants(frame) and selector.stats.frames_scored == 0


def test_another_robots_view_is_filed_under_its_map_pose() -> None:
    """Two robots, one map: robot b's pose is in its own odometry frame (here 3 m and 180 degrees
    off); geometry's render reply carries the pose in the map's frame, and the scorer files the view
    there. So b seeing the wall robot a's encoded frame already covered (from the same side) adds
    nothing, and the same view filed under b's odometry pose (no map pose known) would have
    counted as new surface from the opposite direction."""
    from types import SimpleNamespace

    from openfusion.frame import Frame
    from openfusion.mapping.robot_streams import yaw_transform

    T_map_odom_b = yaw_transform(3.0, 0.0, 0.0, 180.0)
    T_odom_cam_b = np.linalg.inv(T_map_odom_b) @ T_FRONT  # b stands where a stood, in its own frame
    frame_b = Frame(frame_id=5, stamp_ns=int(0.2e9), color=np.zeros((H, W, 3), np.uint8), depth=DEPTH,
                    depth_scale=1.0, intrinsics=K, T_world_cam=T_odom_cam_b)

    def render(with_map_pose: bool):  # noqa: ANN202
        def call(T_world_cam: np.ndarray, intrinsics: CameraIntrinsics, depth_m: np.ndarray) -> SimpleNamespace:
            assert np.allclose(T_world_cam, T_odom_cam_b)  # asked at the robot's own pose
            return SimpleNamespace(key_map=NO_KEYS, conf_map=ZERO_CONF,
                                   T_map_cam=T_map_odom_b @ T_world_cam if with_map_pose else None)
        return call

    for with_map_pose, expected in ((True, 0.0), (False, 1.0)):
        scorer = CoverageScorer(params(select_tries=1))
        encoded(scorer, view(scorer), keys=NO_KEYS)  # robot a's frame, encoded, labelled nothing
        score = scorer.score(scorer.prepare_frame(frame_b, render(with_map_pose)))
        assert score.new_surface == pytest.approx(expected), with_map_pose
