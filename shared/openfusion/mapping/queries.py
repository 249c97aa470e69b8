"""Open-vocabulary queries over a map: ranked regions for a vector, labelled points per class."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.volume import SemanticVolume

logger = logging.getLogger(__name__)

# Region boxes use the 1st/99th percentile per axis: labels of silhouette pixels can leave a few
# stray points on the surface just behind an object, which would inflate a min/max box.
BBOX_PERCENTILE = 1.0

# Extra ranked regions looked at (at most this many, and at most top_k) so that top_k regions with
# surface points remain after empty ones are left out.
EMPTY_REGION_SLACK = 16


@dataclass
class RegionResult:
    """One ranked region: cosine ``score`` of its embedding against the query."""

    key: int
    score: float
    label: str | None
    bbox_min: np.ndarray  # (3,) float32 metres, 1st percentile per axis; NaN without points
    bbox_max: np.ndarray  # (3,) float32 metres, 99th percentile per axis
    num_points: int
    points: np.ndarray | None = None  # (p, 3) float32 when requested


def query_regions(
    dictionary: RegionDictionary,
    volume: SemanticVolume | None,
    vector: np.ndarray,
    top_k: int = 5,
    *,
    with_points: bool = False,
    max_points: int = 2000,
    embedding_space: str | None = None,
) -> list[RegionResult]:
    """Regions ranked by cosine similarity to ``vector`` (best first).

    ``embedding_space`` names the space the query vector came from; a different space than the
    map's raises :class:`~openfusion.mapping.errors.EmbeddingSpaceError`. With a ``volume``, each
    result carries its surface-point count and robust bounding box (1st-99th percentile) (and up to
    ``max_points`` points when ``with_points``), and regions without surface points (every voxel
    they labelled was taken over by other regions) are left out, so up to ``top_k`` regions that
    exist in the map come back; with ``volume=None`` only the ranking is returned (NaN boxes,
    0 points).
    """
    dictionary.check_space(embedding_space)
    candidates = top_k if volume is None else candidates_for(top_k)
    keys, scores = dictionary.top_k(vector, candidates)
    results = [
        RegionResult(
            int(k),
            float(s),
            dictionary.label(int(k)),
            np.full(3, np.nan, np.float32),
            np.full(3, np.nan, np.float32),
            0,
        )
        for k, s in zip(keys, scores, strict=True)
    ]
    if volume is None or not results:
        return results
    surface = volume.extract_points(keys=keys)
    for res in results:
        sel = surface.keys == res.key
        pts = surface.points[sel]
        res.num_points = int(len(pts))
        if len(pts):
            res.bbox_min = np.percentile(pts, BBOX_PERCENTILE, axis=0).astype(np.float32)
            res.bbox_max = np.percentile(pts, 100.0 - BBOX_PERCENTILE, axis=0).astype(np.float32)
        if with_points:
            if len(pts) > max_points:
                rng = np.random.default_rng(res.key)
                pts = pts[np.sort(rng.choice(len(pts), size=max_points, replace=False))]
            res.points = pts.astype(np.float32)
    return [res for res in results if res.num_points > 0][:top_k]


def candidates_for(top_k: int) -> int:
    """How many ranked regions to look at so that ``top_k`` with surface points usually remain
    after empty ones (all voxels taken over by other regions) are dropped."""
    return int(top_k) + min(int(top_k), EMPTY_REGION_SLACK)



def classify_regions(
    dictionary: RegionDictionary, class_embeddings: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(keys (k,), best class index per key (k,)) by cosine similarity."""
    keys, sims = dictionary.similarities(class_embeddings)
    if len(keys) == 0:
        return keys, np.zeros(0, np.int64)
    return keys, sims.argmax(axis=1)


def segment_points(
    volume: SemanticVolume,
    dictionary: RegionDictionary,
    class_embeddings: np.ndarray,
    *,
    max_points: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Surface points (N, 3) and a class label per point (N,) int32: the class whose embedding best
    matches the point's region; -1 where the point has no region (or its key is unknown)."""
    class_embeddings = np.asarray(class_embeddings, np.float32)
    if class_embeddings.ndim != 2 or len(class_embeddings) == 0:
        raise ValueError(f"class_embeddings must be a non-empty (c, d) array, got {class_embeddings.shape}")
    surface = volume.extract_points(max_points=max_points)
    keys, best = classify_regions(dictionary, class_embeddings)
    labels = np.full(len(surface), -1, np.int32)
    if len(keys):
        order = np.argsort(keys)
        sorted_keys = keys[order]
        pos = np.searchsorted(sorted_keys, surface.keys)
        pos = np.minimum(pos, len(sorted_keys) - 1)
        known = (surface.keys >= 0) & (sorted_keys[pos] == surface.keys)
        labels[known] = best[order][pos[known]]
    return surface.points, labels
