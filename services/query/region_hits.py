"""What a query answers with, per region: geometry's region summaries as a lookup table
(:class:`RegionSummaries`) and the ranked regions turned into :class:`RegionHit` replies
(:func:`region_hits`), box, count, centroid, points, nearby regions and relation.

Plain code without a bus: the query service (:mod:`services.query.service`) fetches the
summaries and points, and the tests build hits from a volume's own summaries.
"""

from __future__ import annotations

import time

import numpy as np

from openfusion.mapping.answers import RankedRegion
from openfusion.mapping.queries import region_centroids, region_summaries, subsample_points
from openfusion.mapping.relations import Nearby, RegionBoxes
from openfusion.services.query.caches import SummaryDerived
from openfusion.wire.schemas import NearbyRegion, PointsReply, RegionHit, RegionSummaryReply

_ZERO3 = np.zeros(3, np.float32)


class RegionSummaries:
    """Geometry's per-region summaries (one :class:`RegionSummaryReply`) as a lookup table."""

    def __init__(self, reply: RegionSummaryReply, fetched_at: float) -> None:
        self.map_version = reply.map_version
        self.key_horizon = reply.key_horizon
        self.fetched_at = fetched_at  # monotonic time the request was sent
        self._index = {int(k): i for i, k in enumerate(reply.keys.tolist())}
        self._keys = np.asarray(reply.keys)
        self._bbox_min, self._bbox_max, self._num_points = reply.bbox_min, reply.bbox_max, reply.num_points
        self._centroid = reply.centroid
        # boxes and nearby lists of THIS set of summaries: new summaries, new (empty) caches
        self.derived = SummaryDerived(self._build_boxes)

    @classmethod
    def of_points(cls, keys: np.ndarray, points: np.ndarray) -> RegionSummaries:
        """The same table computed here from labelled points (e.g. a ``geometry/points`` reply)."""
        k, lo, hi, n = region_summaries(keys, points)
        reply = RegionSummaryReply(map_version=0, key_horizon=0, age_s=0.0, keys=k, bbox_min=lo, bbox_max=hi,
                                   num_points=n, centroid=region_centroids(k, keys, points))
        return cls(reply, fetched_at=time.monotonic())

    def centroid(self, key: int) -> np.ndarray | None:
        """Mean of ``key``'s surface points; the box centre when geometry did not send centroids;
        None when the region has no points (or is unknown)."""
        i = self._index.get(int(key))
        if i is None or int(self._num_points[i]) == 0:
            return None
        if self._centroid is not None:
            return np.asarray(self._centroid[i], np.float32)
        return ((self._bbox_min[i] + self._bbox_max[i]) / 2).astype(np.float32)

    def boxes(self, *, min_points: int = 1) -> RegionBoxes:
        """The boxes of the regions with at least ``min_points`` surface points (relations);
        built once per ``min_points`` (:class:`~services.query.caches.SummaryDerived`)."""
        return self.derived.boxes_of(min_points)

    def _build_boxes(self, min_points: int) -> RegionBoxes:
        keep = np.asarray(self._num_points) >= min_points
        order = np.argsort(self._keys[keep], kind="stable")
        return RegionBoxes(self._keys[keep][order], self._bbox_min[keep][order], self._bbox_max[keep][order])

    def __len__(self) -> int:
        return len(self._index)

    def same_boxes(self, other: RegionSummaries) -> bool:
        """Whether ``other`` lists the same regions with the same boxes and counts (what
        :class:`~services.query.caches.SummaryDerived` is computed from)."""
        return (np.array_equal(self._keys, other._keys) and np.array_equal(self._bbox_min, other._bbox_min)
                and np.array_equal(self._bbox_max, other._bbox_max)
                and np.array_equal(self._num_points, other._num_points))

    def covers(self, key: int) -> bool:
        """Whether the summary knows ``key`` (listed, or below the horizon: no surface points)."""
        return key < self.key_horizon or key in self._index

    def get(self, key: int) -> tuple[np.ndarray, np.ndarray, int]:
        """(bbox_min, bbox_max, num_points) of ``key``; zeros when it has no points (or is unknown)."""
        i = self._index.get(int(key))
        if i is None:
            return _ZERO3, _ZERO3, 0
        return self._bbox_min[i], self._bbox_max[i], int(self._num_points[i])


def drop_empty_regions(
    ranked: list[tuple[int, float]], summaries: RegionSummaries | None, *, min_points: int = 1
) -> list[tuple[int, float]]:
    """``ranked`` without the regions the summary knows to have fewer than ``min_points`` surface
    points (stray fragments; 0 when every voxel they labelled was taken over by other regions);
    regions it does not know yet stay."""
    if summaries is None:
        return list(ranked)
    return [(k, s) for k, s in ranked if not (summaries.covers(k) and summaries.get(k)[2] < min_points)]


def region_hits(
    ranked: list[tuple[int, float]] | list[RankedRegion],
    labels: dict[int, str],
    points: PointsReply | None,
    *,
    with_points: bool,
    max_points: int,
    summaries: RegionSummaries | None = None,
) -> list[RegionHit]:
    """Ranked (key, score) pairs, or :class:`~openfusion.mapping.answers.RankedRegion` answers
    (with relevancy, match, nearby regions, relation), → :class:`RegionHit` list. Box, count and
    centroid come from ``points`` (the points of those keys) when given, else from ``summaries``
    (zeros and no centroid when neither knows); the box is the library's
    (:func:`~openfusion.mapping.queries.region_summaries`), as in-process. ``labels``: of the
    ranked keys and of their nearby regions."""
    regions = [r if isinstance(r, RankedRegion) else RankedRegion(int(r[0]), float(r[1]), None, None)  # type: ignore[arg-type]
               for r in ranked]
    hits = []
    if points is not None:  # boxes of the ranked regions only (a point query's reply holds the whole map)
        ranked_pts = np.isin(points.keys, [r.key for r in regions])
        summaries = RegionSummaries.of_points(points.keys[ranked_pts], points.points[ranked_pts])
    for region in regions:
        key = region.key
        bbox_min, bbox_max, n = summaries.get(key) if summaries is not None else (_ZERO3, _ZERO3, 0)
        kept = None  # also when points were asked for but geometry did not answer
        if with_points and points is not None:
            kept = subsample_points(points.points[points.keys == key], max_points, seed=int(key))
        hits.append(
            RegionHit(
                key=int(key),
                score=float(region.score),
                label=labels.get(int(key)) or None,
                bbox_min=np.asarray(bbox_min, np.float32),
                bbox_max=np.asarray(bbox_max, np.float32),
                num_points=n,
                points=kept,
                relevancy=region.relevancy,
                match=region.match,
                centroid=summaries.centroid(key) if summaries is not None else None,
                nearby=[_nearby(nb, labels) for nb in region.nearby],
                relation=_nearby(region.relation, labels) if region.relation is not None else None,
            )
        )
    return hits


def _nearby(nearby: Nearby, labels: dict[int, str]) -> NearbyRegion:
    return NearbyRegion(key=nearby.key, label=labels.get(nearby.key) or None, relation=nearby.relation,
                        distance_m=nearby.distance_m)
