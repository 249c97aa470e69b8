"""The read-out's vote (``readout.vote_labels``, ``VolumeParams.label_vote_radius_m``): a labelled
surface point takes the key most same-facing labelled points around it hold.

Bad inputs tried: no labelled points, one labelled point, radius 0, a tie between two keys,
unlabelled points (-1) among the voters.
"""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.mapping import SemanticVolume, VolumeParams
from openfusion.mapping.readout import vote_labels
from tests.unit.test_mapping_volume import K_SMALL, POSES, integrated_volume, two_box_scene

UP = np.array([0.0, 0.0, 1.0], np.float32)


def plane(n: int = 10, step_m: float = 0.02) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(n) * step_m, np.arange(n) * step_m, indexing="ij")
    return np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1).astype(np.float32)


def test_a_stray_point_takes_its_surroundings_key_and_a_strip_keeps_its_own() -> None:
    """A 10x10 plane at 2 cm of key 1 with one point of key 2 inside it and a 3-column strip of key
    3 along one side: the stray point takes key 1 with the confidence of the points that outvoted
    it; the strip, wider than half the radius, keeps every point (its border points have more of
    their own around them)."""
    points = plane()
    keys = np.ones(100, np.int32)
    keys[55] = 2
    strip = points[:, 0] > 0.139
    keys[strip] = 3
    conf = np.where(strip, 0.6, 0.8).astype(np.float32)
    conf[55] = 0.3
    before = keys.copy()
    normals = np.tile(UP, (100, 1))
    assert vote_labels(points, keys, conf, 0.045, normals) == 1
    assert keys[55] == 1 and conf[55] == pytest.approx(0.8)
    assert np.array_equal(np.flatnonzero(keys != before), [55])


def test_only_same_facing_points_vote() -> None:
    """A floor point of key 4 with three wall points of key 3 around it (facing sideways) and one
    floor point of key 4: the walls do not outvote it. Facing up, the same walls would."""
    points = np.array([[0, 0, 0], [0.02, 0, 0], [0, 0.01, 0.02], [0.01, 0.01, 0.02], [-0.01, 0.01, 0.02]], np.float32)
    normals = np.array([UP, UP, [0, -1, 0], [0, -1, 0], [0, -1, 0]], np.float32)
    keys = np.array([4, 4, 3, 3, 3], np.int32)
    conf = np.full(5, 0.9, np.float32)
    assert vote_labels(points, keys.copy(), conf.copy(), 0.045, normals) == 0
    flipped = keys.copy()
    assert vote_labels(points, flipped, conf.copy(), 0.045, np.tile(UP, (5, 1))) == 2  # both floor points
    assert list(flipped) == [3, 3, 3, 3, 3]


def test_ties_keep_the_own_key_and_unlabelled_points_neither_vote_nor_change() -> None:
    """Edge cases: radius 0, no or one labelled point change nothing; a point with one neighbour
    of another key (1 against 1) keeps its own; between two other keys with equal votes the
    smaller wins; points of key -1 stay -1 and do not count."""
    line = np.stack([np.arange(5) * 0.02, np.zeros(5), np.zeros(5)], axis=1).astype(np.float32)
    conf = np.full(5, 0.5, np.float32)
    keys = np.array([7, 8, -1, -1, -1], np.int32)
    assert vote_labels(line, keys.copy(), conf.copy(), 0.0) == 0
    assert vote_labels(line, np.full(5, -1, np.int32), conf.copy(), 0.045) == 0
    assert vote_labels(line, np.array([7, -1, -1, -1, -1], np.int32), conf.copy(), 0.045) == 0
    tie = keys.copy()
    assert vote_labels(line, tie, conf.copy(), 0.03) == 0 and list(tie) == [7, 8, -1, -1, -1]
    # A point of key 5 with one neighbour of key 9 and one of key 6 (2 cm each side) and two
    # unlabelled ones: 1 own vote against 1 and 1, so every point keeps its key.
    cross = np.array([[0, 0, 0], [0.02, 0, 0], [-0.02, 0, 0], [0, 0.02, 0], [0, -0.02, 0]], np.float32)
    middle = np.array([5, 9, 6, -1, -1], np.int32)
    assert vote_labels(cross, middle, conf.copy(), 0.025) == 0
    assert list(middle) == [5, 9, 6, -1, -1]
    # Two points of key 2 and two of key 1 around a point of key 5: 2 against 2, the smaller key wins.
    square = np.array([[0, 0, 0], [0.02, 0, 0], [-0.02, 0, 0], [0, 0.02, 0], [0, -0.02, 0]], np.float32)
    around = np.array([5, 2, 2, 1, 1], np.int32)
    assert vote_labels(square, around, np.full(5, 0.5, np.float32), 0.025) == 1
    assert around[0] == 1


def test_a_tile_with_a_halo_wider_than_the_radius_gets_the_whole_read_out_s_keys() -> None:
    """The property tile read-outs rely on: the vote of a point depends only on points within the
    radius, so voting a region plus a 5 cm halo gives the region's points the same keys (and
    confidences) as voting the whole cloud."""
    rng = np.random.default_rng(3)
    points = plane(40)
    keys = (np.floor(points[:, 0] / 0.2) + 3 * np.floor(points[:, 1] / 0.2)).astype(np.int32)
    noisy = rng.random(len(keys)) < 0.15
    keys[noisy] = rng.integers(0, 9, int(noisy.sum()))
    keys[rng.random(len(keys)) < 0.05] = -1
    conf = rng.random(len(keys)).astype(np.float32)
    normals = np.tile(UP, (len(keys), 1))
    whole_k, whole_c = keys.copy(), conf.copy()
    changed = vote_labels(points, whole_k, whole_c, 0.045, normals)
    assert changed > 50
    region = (points[:, 0] < 0.3) & (points[:, 1] < 0.3)
    with_halo = (points[:, 0] < 0.35) & (points[:, 1] < 0.35)
    part_k, part_c = keys[with_halo].copy(), conf[with_halo].copy()
    vote_labels(points[with_halo], part_k, part_c, 0.045, normals[with_halo])
    inside = region[with_halo]
    assert np.array_equal(part_k[inside], whole_k[region])
    np.testing.assert_array_equal(part_c[inside], whole_c[region])


def test_the_vote_cleans_speckled_labels_and_keeps_clean_ones() -> None:
    """What a user sees: a map labelled from three views whose masks carry salt noise (4 % of the
    pixels given another object's key, a noisy encoder's stray pixels) reads out with at most half
    as many points on the wrong object with the default vote as without; a map labelled from clean
    masks loses at most half a percent of its right points to the vote."""
    scene = two_box_scene()
    ids = np.array([0, 1, 2, 3, 4, 5, 10, 11])

    def right_share(radius_m: float, salt: float) -> float:
        vol: SemanticVolume = integrated_volume(VolumeParams(label_vote_radius_m=radius_m), scene)
        draws = np.random.default_rng(1)
        for pose in POSES:
            _, inst, _ = scene.render(pose, K_SMALL)
            keys = np.where(inst >= 0, inst, -1).astype(np.int32)
            stray = (draws.random(keys.shape) < salt) & (keys >= 0)
            keys[stray] = draws.choice(ids, int(stray.sum()))
            vol.apply_update(pose, K_SMALL, keys, np.full(keys.shape, 0.9, np.float32))
        out = vol.extract_points()
        truth = scene.instance_at(out.points.astype(np.float64))
        sel = out.keys >= 0
        return float((out.keys[sel] == truth[sel]).mean())

    default = VolumeParams().label_vote_radius_m
    assert default > 0
    noisy_off, noisy_on = right_share(0.0, 0.04), right_share(default, 0.04)
    assert (1 - noisy_on) <= 0.5 * (1 - noisy_off), (noisy_off, noisy_on)
    clean_off, clean_on = right_share(0.0, 0.0), right_share(default, 0.0)
    assert clean_on >= clean_off - 0.005, (clean_off, clean_on)


def test_slots_of_one_region_vote_together_when_classes_are_given() -> None:
    """A tile's read-out speaks storage slots; two slots of one merged region must vote as one, as
    their key does in the whole map: a point of slot 9 with one neighbour each of slots 5 and 6
    (one region) and 7 (another) keeps its slot by slots (1 against 1, 1, 1) and takes slot 5,
    the smaller of the winning region's, by classes (2 against 1)."""
    points = np.array([[0, 0, 0], [0.02, 0, 0], [-0.02, 0, 0], [0, 0.02, 0]], np.float32)
    slots = np.array([9, 5, 6, 7], np.int32)
    classes = np.array([3, 1, 1, 2], np.int64)
    conf = np.array([0.5, 0.6, 0.8, 0.9], np.float32)
    by_slot = slots.copy()
    assert vote_labels(points, by_slot, conf.copy(), 0.025) == 0
    assert vote_labels(points, slots, conf, 0.025, classes=classes) == 1
    assert slots[0] == 5 and conf[0] == pytest.approx(0.7)
