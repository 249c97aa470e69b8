"""Which map regions hold the most mislabelled surface: the evaluation's view of key drift.

Under noisy masks the largest errors of a region map are rarely speckle. One region's key spreads
over a neighbouring object (a picture key over part of its wall, a floor key up a wall) and every
point it holds there is labelled with the region's class (docs/EVAL.md, "A settled key refuses a
region it disagrees with" and "Probed after the rule"). A confusion matrix says *that* wall
points were called picture; this says *which* region did it, what it covers, how many views its
embedding averages and how well they agree (the length of their mean of unit vectors), which is
what a segmenter's or a matching rule's failure looks like in the map.

Per region: the class the protocol gave its points (the most common predicted class over them),
how many of its surface points have a ground-truth class, how many of those are another class,
and the ground-truth classes under it, largest first. Points without a key, without a
ground-truth class or of a class the protocol does not score do not count. Plain numpy over the
arrays the evaluation already holds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def wrong_regions(
    keys: np.ndarray,
    pred: np.ndarray,
    gt_of_points: np.ndarray,
    class_names: Sequence[str],
    dictionary: Any,
    *,
    top: int = 5,
    classes_shown: int = 3,
    scored: np.ndarray | None = None,
) -> list[dict]:
    """The ``top`` regions holding the most surface points of a class other than the one their
    points were labelled with, most first (regions with none are left out).

    ``keys`` (n,) the region key of each surface point (-1: none), ``pred`` (n,) its predicted class
    index (-1: unlabelled), ``gt_of_points`` (n,) its ground-truth class index (-1: none);
    ``dictionary`` a :class:`~openfusion.mapping.dictionary.RegionDictionary` (views and agreement;
    a key it does not hold reports 0 and 0). Each entry: ``key``, ``mapped_class`` (None when its
    points are unlabelled), ``points``, ``wrong``, ``gt_classes`` (``{name: points}``, the
    ``classes_shown`` largest), ``views``, ``agreement``, ``label`` (the dictionary's label, when
    the encoder gave one). ``scored`` (bool (k,)): the classes the protocol scores; points of the
    others (``--exclude-background``: no prediction can be right there) do not count."""
    keys, pred, gt = (np.asarray(a).reshape(-1) for a in (keys, pred, gt_of_points))
    if not (len(keys) == len(pred) == len(gt)):
        raise ValueError(f"keys, pred and gt_of_points differ in length: {len(keys)}, {len(pred)}, {len(gt)}")
    if top < 0 or classes_shown < 1:
        raise ValueError(f"top must be >= 0 and classes_shown >= 1, got {top}, {classes_shown}")
    k = len(class_names)
    use = (keys >= 0) & (gt >= 0) & (gt < k)
    if scored is not None:
        scored = np.asarray(scored, bool).reshape(-1)
        if len(scored) != k:
            raise ValueError(f"scored must have one entry per class ({k}), got {len(scored)}")
        use &= scored[np.clip(gt, 0, k - 1)]
    if not use.any() or top == 0:
        return []
    uniq, inv = np.unique(keys[use], return_inverse=True)
    # Per region: points by ground-truth class, and by predicted class (column k: unlabelled).
    by_gt = np.zeros((len(uniq), k), np.int64)
    np.add.at(by_gt, (inv, gt[use]), 1)
    p = pred[use]
    by_pred = np.zeros((len(uniq), k + 1), np.int64)
    np.add.at(by_pred, (inv, np.where((p >= 0) & (p < k), p, k)), 1)
    mapped = by_pred.argmax(axis=1)
    points = by_gt.sum(axis=1)
    right = np.where(mapped < k, by_gt[np.arange(len(uniq)), np.minimum(mapped, k - 1)], 0)
    wrong = points - right
    order = [i for i in np.argsort(-wrong, kind="stable") if wrong[i] > 0][:top]
    counts, agreement = dictionary.support_of(uniq[order])
    out = []
    for j, i in enumerate(order):
        key = int(uniq[i])
        shown = [c for c in np.argsort(-by_gt[i], kind="stable")[:classes_shown] if by_gt[i, c] > 0]
        out.append({
            "key": key,
            "mapped_class": class_names[mapped[i]] if mapped[i] < k else None,
            "points": int(points[i]),
            "wrong": int(wrong[i]),
            "gt_classes": {class_names[c]: int(by_gt[i, c]) for c in shown},
            "views": int(counts[j]),
            "agreement": round(float(agreement[j]), 4),
            "label": dictionary.label(key) if key in dictionary else None,
        })
    return out
