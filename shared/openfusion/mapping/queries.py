"""Open-vocabulary queries over a map: ranked regions for a vector, labelled points per class."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from openfusion.mapping.params import default_min_region_points
from openfusion.mapping.relations import Nearby
from openfusion.mapping.summaries import (  # re-exported: where callers have always found them
    BBOX_PERCENTILE as BBOX_PERCENTILE,
)
from openfusion.mapping.summaries import RegionTable as RegionTable
from openfusion.mapping.summaries import region_centroids as region_centroids
from openfusion.mapping.summaries import region_summaries as region_summaries
from openfusion.wire.schemas.query import NearbyRegion

if TYPE_CHECKING:  # the volume (Open3D) is imported only by callers that have one
    from openfusion.mapping.answers import TextAnswer
    from openfusion.mapping.dictionary import RegionDictionary
    from openfusion.mapping.relevancy import SpaceCalibration
    from openfusion.mapping.volume import SemanticVolume

logger = logging.getLogger(__name__)

# Extra ranked regions looked at (at most this many, and at most top_k) so that top_k regions with
# enough surface points remain after empty and small ones are left out.
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
    relevancy: float | None = None  # in [0, 1] (openfusion.mapping.relevancy); None when not computed
    match: bool | None = None  # relevancy >= the space's calibrated threshold
    centroid: np.ndarray | None = None  # (3,) float32 metres, mean of the surface points
    nearby: list[NearbyRegion] = field(default_factory=list)  # up to 3 related regions, nearest first
    relation: NearbyRegion | None = None  # relation queries: the anchor this region stands in the relation to


def query_regions(
    dictionary: RegionDictionary,
    volume: SemanticVolume | None,
    vector: np.ndarray,
    top_k: int = 5,
    *,
    with_points: bool = False,
    max_points: int = 2000,
    embedding_space: str | None = None,
    min_points: int | None = None,
) -> list[RegionResult]:
    """Regions ranked by cosine similarity to ``vector`` (best first).

    ``embedding_space`` names the space the query vector came from; a different space than the
    map's raises :class:`~openfusion.mapping.errors.EmbeddingSpaceError`. With a ``volume``, each
    result carries its surface-point count and robust bounding box (1st-99th percentile) (and up to
    ``max_points`` points when ``with_points``), and regions with fewer than ``min_points`` surface
    points (default: :class:`~openfusion.mapping.params.QueryParams` ``min_region_points``; stray
    fragments, or regions whose voxels were all taken over by other regions) are left out, so up
    to ``top_k`` regions that exist in the map come back; with ``volume=None`` only the ranking is
    returned (NaN boxes, 0 points). :func:`query_region_table` gives the same answers from a
    saved :class:`RegionTable` without the volume.
    """
    dictionary.check_space(embedding_space)
    if volume is None:
        keys, scores = dictionary.top_k(vector, top_k)
        return [
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
    keys, scores = dictionary.top_k(vector, candidates_for(top_k))
    if not len(keys):
        return []
    surface = volume.extract_points(keys=keys)
    results = _answers(dictionary, keys, scores, RegionTable.of_points(surface.keys, surface.points), top_k,
                       min_points)
    if with_points:
        for res in results:
            res.points = subsample_points(surface.points[surface.keys == res.key], max_points, seed=res.key)
    return results


def query_region_table(
    dictionary: RegionDictionary,
    table: RegionTable,
    vector: np.ndarray,
    top_k: int = 5,
    *,
    embedding_space: str | None = None,
    min_points: int | None = None,
) -> list[RegionResult]:
    """:func:`query_regions` answered from a map's :class:`RegionTable` (no volume, no points):
    the same ranking, candidates, counts, boxes and ``min_points`` rule."""
    dictionary.check_space(embedding_space)
    keys, scores = dictionary.top_k(vector, candidates_for(top_k))
    return _answers(dictionary, keys, scores, table, top_k, min_points)


def _answers(
    dictionary: RegionDictionary,
    keys: np.ndarray,
    scores: np.ndarray,
    table: RegionTable,
    top_k: int,
    min_points: int | None,
) -> list[RegionResult]:
    """Ranked candidates -> results with counts and boxes from ``table``; regions below
    ``min_points`` surface points left out, at most ``top_k``."""
    least = default_min_region_points() if min_points is None else max(1, int(min_points))
    results = []
    for k, s in zip(keys, scores, strict=True):
        i = table.row(int(k))
        if i is None or int(table.num_points[i]) < least:
            continue
        results.append(RegionResult(int(k), float(s), dictionary.label(int(k)), table.bbox_min[i].copy(),
                                    table.bbox_max[i].copy(), int(table.num_points[i])))
        if len(results) == top_k:
            break
    return results


def subsample_points(points: np.ndarray, max_points: int, *, seed: int) -> np.ndarray:
    """At most ``max_points`` of ``points`` (float32), a random subset in their original order
    when there are more (spread over the whole region, unlike the first ``max_points``);
    ``seed`` (the region key) makes it the same subset every time."""
    points = np.asarray(points, np.float32)
    if len(points) > max_points:
        rng = np.random.default_rng(seed)
        points = points[np.sort(rng.choice(len(points), size=max_points, replace=False))]
    return points


def candidates_for(top_k: int) -> int:
    """How many ranked regions to look at so that ``top_k`` with enough surface points usually
    remain after empty and small ones (``min_region_points``) are dropped."""
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


def answer_texts(
    dictionary: RegionDictionary,
    table: RegionTable,
    texts: list[str],
    encoder: Any,
    *,
    top_k: int = 5,
    min_points: int | None = None,
    up_axis: str = "+z",
    calibration: SpaceCalibration | None = None,
) -> list[tuple[list[RegionResult], TextAnswer]]:
    """Each of ``texts`` answered from a map's dictionary and :class:`RegionTable` (a saved map's
    summaries, or the table of the volume's surface), as the query service answers it
    (:func:`openfusion.mapping.answers.answer_text`: relevancy, match, centroid, nearby regions,
    "X next to Y" queries): every text (and the parts of relation queries, and the negative
    phrases and categories of relevancy) embedded in ONE call of ``encoder``. ``calibration``: the map's (its file records one); default: the library's for
    the dictionary's space. Returns (results, the answer with its relation query) per text."""
    from openfusion.mapping.answers import answer_text, texts_to_embed
    from openfusion.mapping.relevancy import RelevancyScorer, calibration_for

    dictionary.check_space(getattr(encoder, "embedding_space", None))
    least = default_min_region_points() if min_points is None else max(1, int(min_points))
    calibration = calibration or calibration_for(dictionary.embedding_space)
    wanted = texts_to_embed(texts)
    phrases = calibration.phrases  # negatives, then query categories
    embedded = np.asarray(encoder.encode(wanted + phrases), np.float32)  # one call: texts, parts, phrases
    vectors = dict(zip(wanted, embedded[: len(wanted)], strict=True))
    scorer = RelevancyScorer.of_vectors(calibration, embedded[len(wanted):])

    def rank(vector: np.ndarray, n: int) -> list[tuple[int, float]]:
        return [(r.key, r.score) for r in query_region_table(dictionary, table, vector, n, min_points=least)]

    def embeddings(keys: list[int]) -> np.ndarray:
        return np.stack([dictionary.embedding(k) for k in keys])

    boxes = table.boxes(min_points=least)
    out = []
    for text in texts:
        answer = answer_text(text, vectors, rank=rank, embeddings=embeddings, scorer=scorer, boxes=boxes,
                             top_k=top_k, up_axis=up_axis)
        results = []
        for region in answer.regions:
            i = table.row(region.key)
            assert i is not None  # rank() returns table rows only
            results.append(RegionResult(
                region.key, region.score, dictionary.label(region.key), table.bbox_min[i].copy(),
                table.bbox_max[i].copy(), int(table.num_points[i]), relevancy=region.relevancy, match=region.match,
                centroid=table.centroid[i].copy(), nearby=[_labelled(n, dictionary) for n in region.nearby],
                relation=_labelled(region.relation, dictionary) if region.relation is not None else None))
        out.append((results, answer))
    return out


def _labelled(nearby: Nearby, dictionary: RegionDictionary) -> NearbyRegion:
    label = dictionary.label(nearby.key) if nearby.key in dictionary else None
    return NearbyRegion(key=nearby.key, label=label or None, relation=nearby.relation, distance_m=nearby.distance_m)
