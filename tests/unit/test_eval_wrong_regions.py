"""The evaluation names the regions that hold mislabelled surface (key drift), largest first."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.eval.wrong_regions import wrong_regions
from openfusion.mapping.dictionary import RegionDictionary

CLASSES = ["wall", "floor", "picture"]
WALL, FLOOR, PICTURE = range(3)


def _dictionary() -> tuple[RegionDictionary, int, int, int]:
    d = RegionDictionary("test", 3)
    wall = d.add(np.array([1.0, 0.0, 0.0]), label="wall")
    picture = d.add(np.array([0.0, 1.0, 0.0]), label="picture")
    for v in ([0.0, 1.0, 0.0], [1.0, 0.0, 0.0]):  # a picture view, then a view of the wall it drifted onto
        d.observe(picture, np.array(v))
    floor = d.add(np.array([0.0, 0.0, 1.0]), label="floor")
    return d, wall, picture, floor


def test_a_picture_region_spread_over_the_wall_is_named_first_with_what_lies_under_it() -> None:
    d, wall, picture, floor = _dictionary()
    # The wall region: 100 wall points, 5 floor points at its foot. The picture region: 10 picture
    # points and 40 wall points it spread over. The floor region: 80 floor points, all right.
    keys = np.array([wall] * 105 + [picture] * 50 + [floor] * 80 + [-1] * 7)
    gt = np.array([WALL] * 100 + [FLOOR] * 5 + [PICTURE] * 10 + [WALL] * 40 + [FLOOR] * 80 + [WALL] * 7)
    pred = np.array([WALL] * 105 + [PICTURE] * 50 + [FLOOR] * 80 + [-1] * 7)
    gt[-1], keys[-2] = -1, -1  # a point without ground truth, points without a key: not counted
    out = wrong_regions(keys, pred, gt, CLASSES, d)
    assert [r["key"] for r in out] == [picture, wall]  # the floor region has nothing wrong: left out
    first = out[0]
    assert first["mapped_class"] == "picture" and first["label"] == "picture"
    assert (first["points"], first["wrong"]) == (50, 40)
    assert first["gt_classes"] == {"wall": 40, "picture": 10}  # largest first
    assert first["views"] == 3 and first["agreement"] == pytest.approx(np.linalg.norm([1, 2, 0]) / 3, abs=1e-4)
    assert (out[1]["wrong"], out[1]["gt_classes"]) == (5, {"wall": 100, "floor": 5})
    assert wrong_regions(keys, pred, gt, CLASSES, d, top=1) == out[:1]
    # With the wall not scored (--exclude-background) its points count nowhere: the picture region
    # holds only its 10 picture points, right; the wall region only its 5 floor points, wrong.
    unscored_wall = wrong_regions(keys, pred, gt, CLASSES, d, scored=np.array([False, True, True]))
    assert [(r["key"], r["wrong"], r["points"]) for r in unscored_wall] == [(wall, 5, 5)]


def test_a_region_whose_points_are_unlabelled_counts_them_all_wrong_and_bad_inputs_are_refused() -> None:
    d, wall, _, _ = _dictionary()
    keys = np.array([wall, wall, 99])  # key 99 is not in the dictionary: 0 views, no label
    out = wrong_regions(keys, np.array([-1, -1, WALL]), np.array([WALL, WALL, FLOOR]), CLASSES, d)
    assert [(r["key"], r["mapped_class"], r["wrong"]) for r in out] == [(wall, None, 2), (99, "wall", 1)]
    assert (out[1]["views"], out[1]["label"]) == (0, None)
    assert wrong_regions(np.array([-1]), np.array([0]), np.array([0]), CLASSES, d) == []
    with pytest.raises(ValueError, match="differ in length"):
        wrong_regions(keys, np.array([0]), np.array([0, 0, 0]), CLASSES, d)
    with pytest.raises(ValueError, match="top must be"):
        wrong_regions(keys, keys, keys, CLASSES, d, top=-1)
    with pytest.raises(ValueError, match="one entry per class"):
        wrong_regions(keys, keys, keys, CLASSES, d, scored=np.array([True]))
