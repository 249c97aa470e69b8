"""Quality of a map that was already made (a saved map, or a volume + dictionary in memory)
against the ground truth of the scene it was made from: the ConceptFusion protocol of
:mod:`openfusion.eval.protocol` (every class queried, each surface point labelled by its region's
best class, matched to the nearest ground-truth point). What a test or bench uses to compare two
runs of the same scene (encoder pool sizes, a crash and a clean run, a bag and the scene, the
services and the in-process pipeline): :func:`synthetic_map_quality` for the built-in world,
:func:`map_quality` for any ground truth (a ScanNet-layout scene's labelled mesh)."""

from __future__ import annotations

import numpy as np

from openfusion.eval.ground_truth import GroundTruth, synthetic_ground_truth
from openfusion.eval.metrics import compute_metrics
from openfusion.eval.point_labels import segment_with_library
from openfusion.eval.protocol import (
    classify_embeddings,
    confusion_for_points,
    ground_truth_labels_for,
    labels_from_region_keys,
)


def synthetic_map_quality(volume: object, dictionary: object, *, seed: int, text_encoder: object,
                          spacing_m: float = 0.05) -> dict[str, float]:
    """``{"f_mIoU", "mAcc", "points"}`` of a map of ``synthetic:seed=N`` (its volume and dictionary)."""
    from openfusion.sources.synthetic import SyntheticWorld

    gt = synthetic_ground_truth(SyntheticWorld(seed), spacing_m=spacing_m)
    surface = volume.extract_points()  # type: ignore[attr-defined]
    points = np.asarray(surface.points, np.float64)
    class_emb = np.asarray(text_encoder.encode(list(gt.class_names)), np.float32)  # type: ignore[attr-defined]
    region_keys = np.asarray(dictionary.keys, np.int64)  # type: ignore[attr-defined]
    region_cls = classify_embeddings(np.asarray(dictionary.unit_embeddings(), np.float32), class_emb)  # type: ignore[attr-defined]
    pred = labels_from_region_keys(np.asarray(surface.keys, np.int64), region_keys, region_cls)
    gt_of_points, _ = ground_truth_labels_for(points, gt)
    m = compute_metrics(confusion_for_points(pred, gt_of_points, gt.class_names))
    return {"f_mIoU": float(m.f_mIoU), "mAcc": float(m.mAcc), "points": int(len(points))}


def map_quality(volume: object, dictionary: object, ground_truth: GroundTruth, *, text_encoder: object) -> dict:
    """``{"f_mIoU", "mAcc", "unlabelled_fraction", "points"}`` of a map against ``ground_truth``,
    labelled as ``openfusion eval`` labels its own maps (:func:`segment_with_library`; unlabelled
    points count as misses), so a saved map of the services and the evaluation's map compare."""
    gt = ground_truth
    points = np.asarray(volume.extract_points().points, np.float64)  # type: ignore[attr-defined]
    class_emb = np.asarray(text_encoder.encode(list(gt.class_names)), np.float32)  # type: ignore[attr-defined]
    allowed = np.ones(len(gt.class_names), bool)
    pred = segment_with_library(volume, dictionary, class_emb, allowed, points)
    if pred is None:
        surface = volume.extract_points()  # type: ignore[attr-defined]
        region_cls = classify_embeddings(np.asarray(dictionary.unit_embeddings(), np.float32), class_emb)  # type: ignore[attr-defined]
        pred = labels_from_region_keys(np.asarray(surface.keys, np.int64), np.asarray(dictionary.keys, np.int64),  # type: ignore[attr-defined]
                                       region_cls)
    gt_of_points, _ = ground_truth_labels_for(points, gt)
    m = compute_metrics(confusion_for_points(pred, gt_of_points, gt.class_names))
    return {"f_mIoU": float(m.f_mIoU), "mAcc": float(m.mAcc), "unlabelled_fraction": float(m.unlabelled_fraction),
            "points": int(len(points))}
