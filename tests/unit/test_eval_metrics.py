"""Confusion-matrix metrics of the evaluation protocol on hand-made cases with known answers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from openfusion.eval.metrics import ConfusionMatrix, compute_metrics, sum_confusions

CLASSES = ("wall", "chair", "table", "lamp")  # lamp never occurs in the ground truth
W, C, T, L, NONE = 0, 1, 2, 3, -1


def _case() -> tuple[np.ndarray, np.ndarray]:
    """wall: 8 right, 1 as chair, 1 unlabelled; chair: 4 right, 1 as table;
    table: 3 right, 1 as chair, 1 as lamp; plus 2 points whose GT is unlabelled (ignored)."""
    pairs = (
        [(W, W)] * 8 + [(W, C), (W, NONE)]
        + [(C, C)] * 4 + [(C, T)]
        + [(T, T)] * 3 + [(T, C), (T, L)]
        + [(NONE, C), (NONE, NONE)]
    )  # fmt: skip
    gt, pred = np.array(pairs, dtype=np.int64).T
    return pred, gt


def test_counts_and_metrics_match_hand_computation() -> None:
    """A wrong row/column convention, a dropped unlabelled column or GT-unlabelled points counted
    would all change these numbers."""
    pred, gt = _case()
    cm = ConfusionMatrix.from_labels(pred, gt, CLASSES)
    assert cm.total == 20  # the two GT-unlabelled points are ignored
    assert cm.counts[W].tolist() == [8, 1, 0, 0, 1]
    assert cm.counts[L].sum() == 0

    m = compute_metrics(cm)
    recall = {"wall": 8 / 10, "chair": 4 / 5, "table": 3 / 5}
    # IoU = TP / (GT count + predicted count - TP); predicted counts: wall 8, chair 6, table 4.
    iou = {"wall": 8 / (10 + 8 - 8), "chair": 4 / (5 + 6 - 4), "table": 3 / (5 + 4 - 3)}
    gt_count = {"wall": 10, "chair": 5, "table": 5}
    assert m.mAcc == pytest.approx(sum(recall.values()) / 3)
    assert m.f_mIoU == pytest.approx(sum(iou[c] * gt_count[c] for c in iou) / 20)
    assert m.mIoU == pytest.approx(sum(iou.values()) / 3)
    assert m.overall_accuracy == pytest.approx(15 / 20)
    assert m.unlabelled_fraction == pytest.approx(1 / 20)
    assert m.num_points == 20
    # The class absent from the GT is listed but does not enter the means.
    assert m.classes_evaluated == ("wall", "chair", "table")
    lamp = next(c for c in m.per_class if c.name == "lamp")
    assert lamp.gt_count == 0 and lamp.pred_count == 1 and math.isnan(lamp.recall) and math.isnan(lamp.iou)
    chair = next(c for c in m.per_class if c.name == "chair")
    assert (chair.gt_count, chair.pred_count, chair.true_positive) == (5, 6, 4)
    assert chair.precision == pytest.approx(4 / 6)


def test_background_exclusion_drops_rows_and_their_predictions() -> None:
    """Excluding wall must remove its 10 GT points *and* the chair prediction made on a wall
    point from chair's false positives (ConceptGraphs drops points whose GT is excluded)."""
    pred, gt = _case()
    m = compute_metrics(ConfusionMatrix.from_labels(pred, gt, CLASSES), exclude_classes=["wall", "ceiling"])
    iou_chair = 4 / (5 + 5 - 4)  # predicted chair among kept rows: 4 + 1
    iou_table = 3 / (5 + 4 - 3)
    assert m.num_points == 10
    assert m.mAcc == pytest.approx((4 / 5 + 3 / 5) / 2)
    assert m.f_mIoU == pytest.approx((iou_chair * 5 + iou_table * 5) / 10)
    assert m.classes_excluded == ("wall",)
    assert [c.name for c in m.per_class] == ["chair", "table", "lamp"]


def test_unlabelled_points_miss_or_ignore() -> None:
    """The documented default counts an unlabelled prediction as a miss; 'ignore' drops it."""
    pred, gt = _case()
    cm = ConfusionMatrix.from_labels(pred, gt, CLASSES)
    miss = compute_metrics(cm)
    ignore = compute_metrics(cm, unlabelled="ignore")
    wall_miss = next(c for c in miss.per_class if c.name == "wall")
    wall_ign = next(c for c in ignore.per_class if c.name == "wall")
    assert wall_miss.recall == pytest.approx(0.8)
    assert wall_ign.recall == pytest.approx(8 / 9)
    assert ignore.num_points == 19
    with pytest.raises(ValueError, match="unlabelled"):
        compute_metrics(cm, unlabelled="skip")


def test_perfect_and_all_unlabelled_maps() -> None:
    """Sanity ends: a perfect labelling scores 1, a map that labels nothing scores 0."""
    gt = np.array([0, 0, 1, 2, 2, 2])
    perfect = compute_metrics(ConfusionMatrix.from_labels(gt.copy(), gt, CLASSES[:3]))
    assert perfect.mAcc == 1.0 and perfect.f_mIoU == 1.0
    empty = compute_metrics(ConfusionMatrix.from_labels(np.full(6, -1), gt, CLASSES[:3]))
    assert empty.mAcc == 0.0 and empty.f_mIoU == 0.0 and empty.unlabelled_fraction == 1.0


def test_sum_over_scenes_aligns_classes_by_name() -> None:
    """Scenes with different class lists are summed by class name, not by index."""
    a = ConfusionMatrix.from_labels(np.array([0, 1]), np.array([0, 1]), ("chair", "table"))
    b = ConfusionMatrix.from_labels(np.array([0, 1, -1]), np.array([1, 1, 0]), ("sofa", "chair"))
    s = sum_confusions([a, b])
    assert s.class_names == ("chair", "table", "sofa")
    # chair row: 1 right (scene a) + 1 right (scene b: gt 1 = chair, pred 1 = chair); the sofa
    # prediction of scene b's chair point goes to column sofa.
    assert s.counts[0].tolist() == [2, 0, 1, 0]
    assert s.counts[2].tolist() == [0, 0, 0, 1]  # scene b's sofa point left unlabelled
    assert (a + b).counts.tolist() == s.counts.tolist()
    # Round trip through JSON (results.json stores it).
    back = ConfusionMatrix.from_dict(json.loads(json.dumps(s.to_dict())))
    assert back.class_names == s.class_names and np.array_equal(back.counts, s.counts)


def test_bad_labels_are_refused_with_a_clear_error() -> None:
    """Out-of-range labels, float labels and mismatched lengths are caller bugs, not data."""
    with pytest.raises(ValueError, match="pred labels must be in"):
        ConfusionMatrix.from_labels(np.array([4]), np.array([0]), CLASSES)
    with pytest.raises(ValueError, match="integers"):
        ConfusionMatrix.from_labels(np.array([0.0]), np.array([0]), CLASSES)
    with pytest.raises(ValueError, match="equal length"):
        ConfusionMatrix.from_labels(np.array([0, 1]), np.array([0]), CLASSES)
    with pytest.raises(ValueError, match="unique"):
        ConfusionMatrix.zeros(["chair", "chair"])


def test_metrics_json_has_no_nan() -> None:
    """results.json must be strict JSON: undefined values (absent classes) become null."""
    pred, gt = _case()
    d = compute_metrics(ConfusionMatrix.from_labels(pred, gt, CLASSES)).to_dict()
    text = json.dumps(d, allow_nan=False)
    assert json.loads(text)["per_class"][3]["iou"] is None
