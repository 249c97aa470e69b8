"""Region summaries of a map: per region its surface point count, centroid and robust box
(:class:`RegionTable`), computed from surface points (:func:`region_summaries`).

Apart from :mod:`openfusion.mapping.queries` (which ranks regions with them and re-exports these
names) so that the volume's per-tile summaries (:mod:`openfusion.mapping.tilereadouts`) can use
them without importing the query code. Plain numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from openfusion.mapping.relations import RegionBoxes

# Region boxes use the 1st/99th percentile per axis: labels of silhouette pixels can leave a few
# stray points on the surface just behind an object, which would inflate a min/max box.
BBOX_PERCENTILE = 1.0


@dataclass
class RegionTable:
    """Per-region surface summaries of a map: what a text query reports without the volume.

    Rows are sorted by key; ``bbox_min`` / ``bbox_max`` are :func:`region_summaries`' robust box
    (1st-99th percentile per axis), ``centroid`` the mean of the region's surface points. Map files
    store one (:func:`openfusion.mapping.mapfile.save_map`), so ``openfusion query --map-dir``
    answers from it without reading the volume back.
    """

    keys: np.ndarray  # (n,) int32 ascending
    num_points: np.ndarray  # (n,) int64
    centroid: np.ndarray  # (n, 3) float32
    bbox_min: np.ndarray  # (n, 3) float32
    bbox_max: np.ndarray  # (n, 3) float32

    @classmethod
    def of_points(cls, keys: np.ndarray, points: np.ndarray) -> RegionTable:
        """The table of surface ``points`` labelled ``keys`` (-1 = none, ignored)."""
        k, lo, hi, n = region_summaries(keys, points)
        return cls(k, n, region_centroids(k, keys, points), lo, hi)

    def __len__(self) -> int:
        return len(self.keys)

    def row(self, key: int) -> int | None:
        """Row of ``key``, None when the region has no surface points."""
        i = int(np.searchsorted(self.keys, key))
        return i if i < len(self.keys) and int(self.keys[i]) == int(key) else None

    def boxes(self, *, min_points: int = 1) -> RegionBoxes:
        """The boxes of the regions with at least ``min_points`` surface points (relations)."""
        keep = np.asarray(self.num_points) >= min_points
        return RegionBoxes(self.keys[keep], self.bbox_min[keep], self.bbox_max[keep])


def region_centroids(table_keys: np.ndarray, keys: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(len(table_keys), 3) float32 mean of the ``points`` labelled with each of ``table_keys``
    (sorted ascending, every one present in ``keys``)."""
    keys = np.asarray(keys)
    labelled = keys >= 0
    if not len(table_keys):
        return np.zeros((0, 3), np.float32)
    rows = np.searchsorted(table_keys, keys[labelled])
    p = np.asarray(points, np.float64)[labelled]
    counts = np.bincount(rows, minlength=len(table_keys)).astype(np.float64)
    sums = np.stack([np.bincount(rows, weights=p[:, a], minlength=len(table_keys)) for a in range(3)], axis=1)
    return (sums / np.maximum(counts, 1.0)[:, None]).astype(np.float32)


def region_summaries(
    keys: np.ndarray, points: np.ndarray, *, percentile: float = BBOX_PERCENTILE
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per region: (keys int32 ascending, bbox_min (n,3) float32, bbox_max (n,3) float32,
    num_points int64) of surface ``points`` labelled ``keys`` (-1 = none, ignored).

    The box is the ``percentile``-th / ``100 - percentile``-th percentile per axis (linear
    interpolation, as ``np.percentile``), the one box every query path reports: in-process
    :func:`query_regions`, the geometry service's region summaries and the query service's
    replies with points. ``percentile=0`` gives the min/max box.
    """
    keys = np.asarray(keys)
    points = np.asarray(points)
    labelled = keys >= 0
    k, p = keys[labelled].astype(np.int64), points[labelled].astype(np.float64)
    if not len(k):
        return (np.zeros(0, np.int32), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                np.zeros(0, np.int64))
    uniq, counts = np.unique(k, return_counts=True)
    start = np.cumsum(counts) - counts  # where each region begins once sorted by key
    q = float(percentile) / 100.0
    # Rank within each region (linear interpolation between the two nearest) for both bounds.
    ranks = []
    for frac in (q, 1.0 - q):
        pos = frac * (counts - 1)
        lo = np.floor(pos).astype(np.int64)
        ranks.append((start + lo, start + np.minimum(lo + 1, counts - 1), pos - lo))
    bounds = np.empty((2, len(uniq), 3), np.float64)
    rank = np.searchsorted(uniq, k)  # each point's region row
    given = points[labelled]
    for axis in range(3):
        v = p[_order_by_region_then(rank, given[:, axis]), axis]
        for b, (lo_i, hi_i, w) in enumerate(ranks):
            bounds[b, :, axis] = v[lo_i] * (1.0 - w) + v[hi_i] * w
    return (uniq.astype(np.int32), bounds[0].astype(np.float32), bounds[1].astype(np.float32),
            counts.astype(np.int64))


def _order_by_region_then(rank: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Indices sorting points by region row, then by ``values``, exactly (a region's sorted values
    must not depend on how the points were grouped: a map's summaries are combined from per-tile
    parts, :mod:`openfusion.mapping.tilereadouts`). float32 coordinates (surface points) sort as one
    int64 key (region row above an order-preserving 32-bit image of the float), as fast as the
    float sort it replaced; other dtypes through ``np.lexsort``."""
    if values.dtype == np.float32:
        bits = np.ascontiguousarray(values).view(np.uint32).astype(np.int64)
        ordered = np.where(bits >= 0x80000000, 0xFFFFFFFF - bits, bits + 0x80000000)  # negatives reversed
        return np.argsort((rank.astype(np.int64) << 32) | ordered)
    return np.lexsort((values, rank))
