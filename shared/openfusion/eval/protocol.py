"""The ConceptFusion / ConceptGraphs labelling protocol, independent of how a map stores semantics.

1. The scene's class names are embedded with the text encoder (one query per class).
2. Every reconstructed surface point gets the class whose text embedding best matches its
   semantics (cosine); points without semantics get ``-1``.
3. Every reconstructed point is matched to its nearest ground-truth point (scipy cKDTree) and
   takes that point's ground-truth label.
4. The (prediction, ground truth) pairs fill a :class:`~openfusion.eval.metrics.ConfusionMatrix`.

With background exclusion the excluded classes are not offered as answers (their scores are
-inf, as ConceptGraphs does) and points whose ground truth is excluded are dropped by
:func:`~openfusion.eval.metrics.compute_metrics`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence

import numpy as np

from openfusion.eval.geometry import nearest_distances
from openfusion.eval.ground_truth import GroundTruth
from openfusion.eval.metrics import ConfusionMatrix

logger = logging.getLogger(__name__)


def class_scores_mask(class_names: Sequence[str], exclude_classes: Iterable[str]) -> np.ndarray:
    """Bool per class: True where the class may be predicted."""
    excluded = set(exclude_classes)
    return np.array([n not in excluded for n in class_names], dtype=bool)


def classify_embeddings(
    embeddings: np.ndarray, class_embeddings: np.ndarray, *, allowed: np.ndarray | None = None
) -> np.ndarray:
    """Best-matching class index (cosine) for each row of ``embeddings`` ((R, d) unit rows)."""
    e = np.asarray(embeddings, dtype=np.float32)
    c = np.asarray(class_embeddings, dtype=np.float32)
    if e.ndim != 2 or c.ndim != 2 or (len(e) and e.shape[1] != c.shape[1]):
        raise ValueError(f"embedding shapes do not match: {e.shape} vs classes {c.shape}")
    if len(c) == 0:
        raise ValueError("no class embeddings to classify against")
    scores = e @ c.T
    if allowed is not None:
        if not np.asarray(allowed).any():
            raise ValueError("every class is excluded; nothing can be predicted")
        scores[:, ~np.asarray(allowed, dtype=bool)] = -np.inf
    return scores.argmax(axis=1).astype(np.int64) if len(e) else np.zeros(0, np.int64)


def labels_from_region_keys(
    point_keys: np.ndarray,
    region_keys: np.ndarray,
    region_classes: np.ndarray,
) -> np.ndarray:
    """Per-point class from per-point region keys and per-region classes (-1 = no key / unknown key)."""
    pk = np.asarray(point_keys).astype(np.int64)
    rk = np.asarray(region_keys).astype(np.int64)
    rc = np.asarray(region_classes).astype(np.int64)
    if rk.shape != rc.shape:
        raise ValueError(f"region_keys {rk.shape} and region_classes {rc.shape} differ")
    out = np.full(pk.shape, -1, dtype=np.int64)
    if rk.size == 0:
        return out
    order = np.argsort(rk)
    rk_sorted = rk[order]
    pos = np.searchsorted(rk_sorted, pk)
    pos_c = np.minimum(pos, len(rk_sorted) - 1)
    hit = (pk >= 0) & (rk_sorted[pos_c] == pk)
    out[hit] = rc[order[pos_c[hit]]]
    unknown = int(((pk >= 0) & ~hit).sum())
    if unknown:
        logger.warning(
            "%d surface point(s) carry a key missing from the dictionary; left unlabelled", unknown
        )
    return out


def ground_truth_labels_for(
    points: np.ndarray, gt: GroundTruth, *, max_distance_m: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(GT label, distance) of the nearest ground-truth point for every reconstructed point.

    ``max_distance_m`` (optional) makes points farther than that from any GT point ``-1``
    (ignored); the protocol default (None) matches every point, as ConceptFusion does.
    """
    dist, idx = nearest_distances(points, gt.points)
    labels = gt.labels[idx].astype(np.int64) if len(idx) else np.zeros(0, np.int64)
    if max_distance_m is not None:
        labels = np.where(dist <= max_distance_m, labels, -1)
    return labels, dist


def confusion_for_points(
    pred_labels: np.ndarray,
    gt_labels_of_points: np.ndarray,
    class_names: Sequence[str],
) -> ConfusionMatrix:
    """Confusion of per-point predictions against the matched ground-truth labels."""
    return ConfusionMatrix.from_labels(
        np.asarray(pred_labels).astype(np.int64),
        np.asarray(gt_labels_of_points).astype(np.int64),
        class_names,
    )
