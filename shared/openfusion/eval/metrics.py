"""Semantic segmentation metrics of the ConceptFusion / ConceptGraphs protocol (pure numpy).

A :class:`ConfusionMatrix` counts reconstructed points by (ground-truth class, predicted class).
Rows are ground-truth classes; columns are the same classes plus one last column, ``UNLABELLED``,
for points the map could not label (prediction ``-1``: a surface voxel with no region key).

Conventions (docs/EVAL.md):

- Points whose ground-truth label is ``-1`` (unlabelled / not one of the evaluated classes) are
  ignored: they appear in no row.
- A point predicted ``-1`` counts as a miss of its ground-truth class (it lowers recall and IoU
  of that class, and is a false positive of no class). ConceptFusion counts every reconstructed
  point, so this is the comparable choice; ``unlabelled="ignore"`` drops those points instead.
- mAcc is the mean per-class recall over the classes present in the ground truth (row sum > 0).
- f-mIoU is ``sum_c IoU_c * gt_count_c / total``, weights from the ground-truth counts.
- Background exclusion (ConceptGraphs ``n_exclude``, default list in
  :data:`openfusion.eval.classes.DEFAULT_BACKGROUND_CLASSES`): rows of excluded classes are dropped; the
  labelling step is expected not to predict excluded classes (see
  :func:`openfusion.eval.protocol.label_points`); if it does, such points count as misses.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)

UNLABELLED = -1


@dataclass(frozen=True)
class ConfusionMatrix:
    """Point counts by ground-truth class (rows) and predicted class (columns + unlabelled).

    ``counts`` is (K, K + 1) int64; column K counts points predicted ``-1``.
    """

    class_names: tuple[str, ...]
    counts: np.ndarray

    def __post_init__(self) -> None:
        k = len(self.class_names)
        if len(set(self.class_names)) != k:
            raise ValueError(f"class names must be unique, got {list(self.class_names)}")
        c = np.asarray(self.counts)
        if c.shape != (k, k + 1):
            raise ValueError(f"counts must have shape ({k}, {k + 1}) for {k} classes, got {c.shape}")
        if c.size and c.min() < 0:
            raise ValueError("counts must be non-negative")
        object.__setattr__(self, "counts", c.astype(np.int64, copy=False))

    @classmethod
    def zeros(cls, class_names: Sequence[str]) -> ConfusionMatrix:
        k = len(class_names)
        return cls(tuple(class_names), np.zeros((k, k + 1), dtype=np.int64))

    @classmethod
    def from_labels(
        cls, pred_labels: np.ndarray, gt_labels: np.ndarray, class_names: Sequence[str]
    ) -> ConfusionMatrix:
        """Count (gt, pred) pairs. Labels are indices into ``class_names``; ``-1`` = none.

        Ground-truth ``-1`` points are ignored; prediction ``-1`` goes to the unlabelled column.
        """
        pred = np.asarray(pred_labels)
        gt = np.asarray(gt_labels)
        if pred.shape != gt.shape or pred.ndim != 1:
            raise ValueError(
                f"pred and gt labels must be 1-D of equal length, got {pred.shape} and {gt.shape}"
            )
        if not (np.issubdtype(pred.dtype, np.integer) and np.issubdtype(gt.dtype, np.integer)):
            raise ValueError(f"labels must be integers, got {pred.dtype} and {gt.dtype}")
        k = len(class_names)
        for name, lab in (("pred", pred), ("gt", gt)):
            if lab.size and (lab.min() < -1 or lab.max() >= k):
                raise ValueError(f"{name} labels must be in [-1, {k - 1}], got [{lab.min()}, {lab.max()}]")
        keep = gt >= 0
        col = np.where(pred[keep] < 0, k, pred[keep]).astype(np.int64)
        flat = gt[keep].astype(np.int64) * (k + 1) + col
        counts = np.bincount(flat, minlength=k * (k + 1)).reshape(k, k + 1)
        return cls(tuple(class_names), counts)

    def __add__(self, other: ConfusionMatrix) -> ConfusionMatrix:
        if not isinstance(other, ConfusionMatrix):
            return NotImplemented
        return sum_confusions([self, other])

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def to_dict(self) -> dict:
        return {"class_names": list(self.class_names), "counts": self.counts.tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> ConfusionMatrix:
        return cls(tuple(data["class_names"]), np.asarray(data["counts"], dtype=np.int64))


def sum_confusions(matrices: Iterable[ConfusionMatrix]) -> ConfusionMatrix:
    """Sum confusion matrices of several scenes, aligning classes by name.

    The result's classes are the union, in order of first appearance. Scenes that lack a class
    contribute zeros to it.
    """
    mats = list(matrices)
    if not mats:
        raise ValueError("need at least one confusion matrix to sum")
    names: list[str] = []
    for m in mats:
        names.extend(n for n in m.class_names if n not in names)
    index = {n: i for i, n in enumerate(names)}
    k = len(names)
    out = np.zeros((k, k + 1), dtype=np.int64)
    for m in mats:
        idx = np.array([index[n] for n in m.class_names] + [k], dtype=np.int64)
        out[np.ix_(idx[:-1], idx)] += m.counts
    return ConfusionMatrix(tuple(names), out)


@dataclass(frozen=True)
class ClassMetrics:
    """One row of the per-class table."""

    name: str
    gt_count: int
    pred_count: int
    true_positive: int
    recall: float
    precision: float
    iou: float


@dataclass(frozen=True)
class SemanticMetrics:
    """Summary of a confusion matrix. Fractions in [0, 1]; NaN when undefined (no GT points)."""

    mAcc: float
    f_mIoU: float
    mIoU: float
    overall_accuracy: float
    num_points: int
    unlabelled_fraction: float
    classes_evaluated: tuple[str, ...]
    classes_excluded: tuple[str, ...]
    per_class: tuple[ClassMetrics, ...]

    def to_dict(self) -> dict:
        return {
            "mAcc": _json_float(self.mAcc),
            "f_mIoU": _json_float(self.f_mIoU),
            "mIoU": _json_float(self.mIoU),
            "overall_accuracy": _json_float(self.overall_accuracy),
            "num_points": self.num_points,
            "unlabelled_fraction": _json_float(self.unlabelled_fraction),
            "classes_evaluated": list(self.classes_evaluated),
            "classes_excluded": list(self.classes_excluded),
            "per_class": [
                {
                    "name": c.name,
                    "gt_count": c.gt_count,
                    "pred_count": c.pred_count,
                    "true_positive": c.true_positive,
                    "recall": _json_float(c.recall),
                    "precision": _json_float(c.precision),
                    "iou": _json_float(c.iou),
                }
                for c in self.per_class
            ],
        }


def compute_metrics(
    confusion: ConfusionMatrix,
    *,
    exclude_classes: Iterable[str] = (),
    unlabelled: str = "miss",
) -> SemanticMetrics:
    """mAcc, f-mIoU, mIoU and the per-class table of ``confusion``.

    ``exclude_classes`` (e.g. :data:`openfusion.eval.classes.DEFAULT_BACKGROUND_CLASSES`) drops those ground-truth rows;
    names not in the matrix are ignored. ``unlabelled`` is ``"miss"`` (default: a point the map
    left unlabelled is a wrong answer for its GT class) or ``"ignore"`` (drop those points).
    The per-class table lists every non-excluded class, including classes absent from the GT
    (gt_count 0, recall/IoU NaN); absent classes do not enter mAcc, mIoU or f-mIoU.
    """
    if unlabelled not in ("miss", "ignore"):
        raise ValueError(f"unlabelled must be 'miss' or 'ignore', got {unlabelled!r}")
    names = confusion.class_names
    k = len(names)
    excluded = set(exclude_classes)
    keep = np.array([n not in excluded for n in names], dtype=bool)
    counts = confusion.counts.astype(np.float64)
    counts = counts[keep]  # drop excluded GT rows
    if unlabelled == "ignore":
        counts = counts[:, :k]
    kept_idx = np.flatnonzero(keep)
    tp = counts[np.arange(len(kept_idx)), kept_idx]
    gt_count = counts.sum(axis=1)
    pred_count = counts[:, kept_idx].sum(axis=0)  # predictions of each kept class among kept rows
    total = gt_count.sum()
    with np.errstate(invalid="ignore", divide="ignore"):
        recall = np.where(gt_count > 0, tp / gt_count, np.nan)
        precision = np.where(pred_count > 0, tp / pred_count, np.nan)
        union = gt_count + pred_count - tp
        iou = np.where(gt_count > 0, tp / np.maximum(union, 1), np.nan)
    present = gt_count > 0
    if total > 0:
        macc = float(np.mean(recall[present]))
        miou = float(np.mean(iou[present]))
        fmiou = float(np.sum(iou[present] * gt_count[present]) / total)
        oacc = float(tp.sum() / total)
        unl = float(counts[:, k].sum() / total) if unlabelled == "miss" else 0.0
    else:
        logger.warning("confusion matrix has no ground-truth points after exclusion; metrics are NaN")
        macc = miou = fmiou = oacc = unl = float("nan")
    per_class = tuple(
        ClassMetrics(
            name=names[j],
            gt_count=int(gt_count[i]),
            pred_count=int(pred_count[i]),
            true_positive=int(tp[i]),
            recall=float(recall[i]),
            precision=float(precision[i]),
            iou=float(iou[i]),
        )
        for i, j in enumerate(kept_idx)
    )
    return SemanticMetrics(
        mAcc=macc,
        f_mIoU=fmiou,
        mIoU=miou,
        overall_accuracy=oacc,
        num_points=int(total),
        unlabelled_fraction=unl,
        classes_evaluated=tuple(names[j] for i, j in enumerate(kept_idx) if present[i]),
        classes_excluded=tuple(n for n in names if n in excluded),
        per_class=per_class,
    )


def _json_float(x: float) -> float | None:
    """NaN/inf become None so results.json stays strict JSON."""
    return float(x) if np.isfinite(x) else None
