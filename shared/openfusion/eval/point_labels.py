"""Per-point labels and per-region counts of a mapped scene (helpers of :mod:`.runner`): the
dictionary's arrays, the library's own segmentation of the surface, the nearest-labelled fill of
unlabelled points, and how many regions the map holds per ground-truth object."""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from openfusion.eval.ground_truth import GroundTruth
from openfusion.mapping import segment_points

logger = logging.getLogger("openfusion.eval.runner")


def dictionary_arrays(dictionary: object) -> tuple[np.ndarray, np.ndarray]:
    """(keys (R,), unit embeddings (R, d)) of every region in the dictionary."""
    keys = dictionary.keys  # type: ignore[attr-defined]
    emb = dictionary.unit_embeddings()  # type: ignore[attr-defined]
    return np.asarray(keys, dtype=np.int64), np.array(emb, dtype=np.float32)


def segment_with_library(
    volume: object, dictionary: object, class_emb: np.ndarray, allowed: np.ndarray, points: np.ndarray
) -> np.ndarray | None:
    """Per-point classes from :func:`openfusion.mapping.segment_points` (what users get), offered
    only the allowed classes; ``None`` if its point set differs from ``points``."""

    allowed_idx = np.flatnonzero(allowed)
    seg_points, seg_labels = segment_points(volume, dictionary, class_emb[allowed_idx])
    if seg_points.shape != points.shape or not np.array_equal(seg_points, points.astype(seg_points.dtype)):
        logger.warning("segment_points returned another point set than extract_points; labelling locally")
        return None
    seg = np.asarray(seg_labels, dtype=np.int64)
    return np.where(seg >= 0, allowed_idx[np.maximum(seg, 0)], -1)


def nearest_labelled_fill(points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """``labels`` with every -1 replaced by the label of the nearest labelled point."""
    out = np.asarray(labels).copy()
    lab = out >= 0
    if lab.all() or not lab.any():
        return out
    _, idx = cKDTree(points[lab]).query(points[~lab], k=1, workers=-1)
    out[~lab] = out[lab][np.asarray(idx, dtype=np.int64)]
    return out


#: A region counts as an answer-sized object when it has at least this many surface points.
REGION_MIN_POINTS = 100


def region_counts(point_keys: np.ndarray, gt: GroundTruth, observed_mask: np.ndarray | None) -> dict:
    """How many regions the map holds per ground-truth object: ``regions_100`` (regions with at
    least :data:`REGION_MIN_POINTS` surface points), ``regions_any`` (with any), ``gt_objects``
    (ground-truth instances with an evaluated class and at least one observed ground-truth
    point; None when the ground truth has no instances) and the ratio."""
    keys = np.asarray(point_keys)
    counts = np.bincount(keys[keys >= 0]) if (keys >= 0).any() else np.zeros(0, np.int64)
    out: dict = {"regions_100": int((counts >= REGION_MIN_POINTS).sum()), "regions_any": int((counts > 0).sum()),
                 "gt_objects": None, "regions_100_per_object": None}
    if gt.instance_ids is not None:
        seen = gt.labels >= 0
        if observed_mask is not None:
            seen &= np.asarray(observed_mask, bool)
        objects = len(np.unique(gt.instance_ids[seen & (gt.instance_ids > 0)]))
        out["gt_objects"] = objects
        out["regions_100_per_object"] = out["regions_100"] / objects if objects else None
    return out
