"""Class-agnostic region proposals: Felzenszwalb-style graph segmentation on color + depth edges.

Runs at the encoder's output resolution (160x120 for 640x480 input) in numpy/scipy:

1. color is box-filtered to the output grid and lightly smoothed (Gaussian, ``sigma_px``), depth
   is averaged over valid pixels only;
2. an 8-neighbour pixel graph gets edge weights ``|delta rgb| + depth_weight * min(|delta z| / z, 1)``
   (colour distance in 8-bit units plus a relative depth jump, so an object in front of a wall
   of the same colour is still separated);
3. *pre-merge* (vectorised): all edges lighter than ``premerge_threshold`` are contracted with
   ``scipy.sparse.csgraph.connected_components`` (flat walls and floors collapse at once). When the
   contracted graph would still have more than ``max_graph_edges`` edges (a very textured image),
   the threshold doubles until it fits, which bounds the run time;
4. Felzenszwalb & Huttenlocher (IJCV 2004) on the contracted graph: edges in increasing weight;
   two components merge when the edge is no heavier than ``min(Int(a) + k/|a|, Int(b) + k/|b|)``
   with ``Int`` the largest edge inside a component and ``k = scale``;
5. components smaller than ``min_size_px`` are merged into their lightest neighbour;
6. thin strips, components with fewer than ``min_core_px`` pixels whose 4 neighbours are all in
   the same component (typically the blended ring along an object's outline), are merged into
   their lightest neighbour too.

The result is a label image; :class:`GraphSegmentationProposer` turns it into (n, h, w) binary
confidence maps (largest ``max_regions`` regions first).
"""

from __future__ import annotations

import logging

import numpy as np
from PIL import Image
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from openfusion.encoders.base import EncoderError
from openfusion.frame import Frame

logger = logging.getLogger(__name__)


def downsample_color(color: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """HxWx3 uint8 -> (h, w, 3) float32 box-filtered color."""
    h, w = out_hw
    if color.shape[:2] == (h, w):
        return color.astype(np.float32)
    return np.asarray(Image.fromarray(color).resize((w, h), Image.Resampling.BOX), dtype=np.float32)


def downsample_depth(depth_m: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """HxW metres (0 = none) -> (h, w) mean of the valid pixels in each cell (0 where none)."""
    h, w = out_hw
    d = np.nan_to_num(depth_m.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    valid = (d > 0).astype(np.float32)
    if d.shape == (h, w):
        return d * valid
    box = Image.Resampling.BOX
    s = np.asarray(Image.fromarray(d * valid, mode="F").resize((w, h), box), dtype=np.float32)
    c = np.asarray(Image.fromarray(valid, mode="F").resize((w, h), box), dtype=np.float32)
    return np.where(c > 1e-3, s / np.maximum(c, 1e-3), 0.0).astype(np.float32)


def _grid_edges(color: np.ndarray, depth: np.ndarray, depth_weight: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-neighbour edges (a, b, weight) of an (h, w) grid."""
    h, w = depth.shape
    idx = np.arange(h * w, dtype=np.int64).reshape(h, w)
    src, dst, wts = [], [], []
    # right, down, down-right, down-left
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        ys = slice(0, h - dy)
        yd = slice(dy, h)
        if dx >= 0:
            xs, xd = slice(0, w - dx), slice(dx, w)
        else:
            xs, xd = slice(-dx, w), slice(0, w + dx)
        a = idx[ys, xs].ravel()
        b = idx[yd, xd].ravel()
        dc = np.sqrt(((color[ys, xs] - color[yd, xd]) ** 2).sum(axis=-1)).ravel()
        za = depth[ys, xs].ravel()
        zb = depth[yd, xd].ravel()
        both = (za > 0) & (zb > 0)
        rel = np.where(both, np.abs(za - zb) / np.maximum(np.minimum(za, zb), 1e-3), 0.0)
        src.append(a)
        dst.append(b)
        wts.append(dc + depth_weight * np.minimum(rel, 1.0))
    return np.concatenate(src), np.concatenate(dst), np.concatenate(wts).astype(np.float32)


def _find(parent: list[int], x: int) -> int:
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


def felzenszwalb_segment(
    color: np.ndarray,
    depth_m: np.ndarray | None = None,
    *,
    scale: float = 300.0,
    sigma_px: float = 0.8,
    min_size_px: int = 30,
    depth_weight: float = 150.0,
    premerge_threshold: float = 3.0,
    max_graph_edges: int = 6000,
    min_core_px: int = 12,
) -> np.ndarray:
    """Label image (h, w) int32 (0..n-1) of a (h, w, 3) color image and optional (h, w) depth (metres)."""
    if color.ndim != 3 or color.shape[2] != 3:
        raise EncoderError(f"color must be (h, w, 3), got {color.shape}")
    h, w = color.shape[:2]
    if depth_m is None:
        depth_m = np.zeros((h, w), np.float32)
    if depth_m.shape != (h, w):
        raise EncoderError(f"depth is {depth_m.shape}, color is {(h, w)}")
    col = color.astype(np.float32)
    if sigma_px > 0:
        col = ndimage.gaussian_filter(col, sigma=(sigma_px, sigma_px, 0), mode="nearest")
    a, b, wt = _grid_edges(col, depth_m.astype(np.float32), depth_weight)
    n = h * w

    # 3. pre-merge light edges (vectorised), bounded size of what is left
    threshold = float(premerge_threshold)
    while True:
        light = wt <= threshold
        graph = coo_matrix((np.ones(int(light.sum()), np.int8), (a[light], b[light])), shape=(n, n))
        num_comp, comp = connected_components(graph, directed=False)
        ca, cb = comp[a], comp[b]
        between = ca != cb
        if int(between.sum()) <= max_graph_edges or threshold > 1e4:
            break
        # many edges may be parallel (same component pair): count distinct pairs before giving up
        pairs = np.unique(np.minimum(ca[between], cb[between]) * num_comp + np.maximum(ca[between], cb[between]))
        if pairs.size <= max_graph_edges:
            break
        threshold *= 2.0
    size = np.bincount(comp, minlength=num_comp).astype(np.int64)
    internal = np.zeros(num_comp, np.float32)
    inside = ~between
    np.maximum.at(internal, ca[inside], wt[inside])

    # contracted graph: lightest edge per component pair
    lo = np.minimum(ca[between], cb[between]).astype(np.int64)
    hi = np.maximum(ca[between], cb[between]).astype(np.int64)
    ew = wt[between]
    order = np.lexsort((ew, lo * num_comp + hi))
    key = (lo * num_comp + hi)[order]
    first = np.ones(key.size, bool)
    first[1:] = key[1:] != key[:-1]
    lo, hi, ew = lo[order][first], hi[order][first], ew[order][first]
    by_weight = np.argsort(ew, kind="stable")
    lo_l, hi_l, ew_l = lo[by_weight].tolist(), hi[by_weight].tolist(), ew[by_weight].tolist()

    # 4. Felzenszwalb merging on the contracted graph
    parent = list(range(num_comp))
    sz = size.tolist()
    inner = internal.tolist()
    k = float(scale)
    for u, v, wgt in zip(lo_l, hi_l, ew_l, strict=True):
        ru, rv = _find(parent, u), _find(parent, v)
        if ru == rv:
            continue
        if wgt <= min(inner[ru] + k / sz[ru], inner[rv] + k / sz[rv]):
            parent[rv] = ru
            sz[ru] += sz[rv]
            inner[ru] = max(inner[ru], inner[rv], wgt)

    # 5. small components join their lightest neighbour
    if min_size_px > 1:
        for u, v, _ in zip(lo_l, hi_l, ew_l, strict=True):
            ru, rv = _find(parent, u), _find(parent, v)
            if ru != rv and (sz[ru] < min_size_px or sz[rv] < min_size_px):
                parent[rv] = ru
                sz[ru] += sz[rv]

    # 6. thin strips (e.g. the blended ring along an object's outline) join their lightest neighbour
    roots = np.array([_find(parent, c) for c in range(num_comp)], np.int64)
    if min_core_px > 0:
        lab = roots[comp].reshape(h, w)
        core = np.ones((h, w), bool)
        core[1:, :] &= lab[1:, :] == lab[:-1, :]
        core[:-1, :] &= lab[:-1, :] == lab[1:, :]
        core[:, 1:] &= lab[:, 1:] == lab[:, :-1]
        core[:, :-1] &= lab[:, :-1] == lab[:, 1:]
        core_px = np.bincount(lab[core], minlength=num_comp).tolist()
        for u, v, _ in zip(lo_l, hi_l, ew_l, strict=True):
            ru, rv = _find(parent, u), _find(parent, v)
            if ru != rv and (core_px[ru] < min_core_px or core_px[rv] < min_core_px):
                parent[rv] = ru
                core_px[ru] += core_px[rv]
        roots = np.array([_find(parent, c) for c in range(num_comp)], np.int64)
    _, labels = np.unique(roots[comp], return_inverse=True)
    return labels.reshape(h, w).astype(np.int32)


class GraphSegmentationProposer:
    """Frame -> (n, h, w) binary region maps from :func:`felzenszwalb_segment` (largest first)."""

    name = "graph"

    def __init__(
        self,
        *,
        scale: float = 300.0,
        sigma_px: float = 0.8,
        min_size_px: int = 30,
        depth_weight: float = 150.0,
        max_regions: int = 48,
        min_region_px: int = 16,
        premerge_threshold: float = 3.0,
        max_graph_edges: int = 6000,
        min_core_px: int = 12,
    ) -> None:
        if max_regions < 1:
            raise ValueError(f"max_regions must be >= 1, got {max_regions}")
        self.params = dict(
            scale=scale,
            sigma_px=sigma_px,
            min_size_px=min_size_px,
            depth_weight=depth_weight,
            premerge_threshold=premerge_threshold,
            max_graph_edges=max_graph_edges,
            min_core_px=min_core_px,
        )
        self.max_regions = int(max_regions)
        self.min_region_px = int(min_region_px)

    def propose(self, frame: Frame, out_hw: tuple[int, int]) -> np.ndarray:
        color = downsample_color(frame.color, out_hw)
        depth = downsample_depth(frame.depth_m(), out_hw)
        labels = felzenszwalb_segment(color, depth, **self.params)
        counts = np.bincount(labels.ravel())
        order = np.argsort(-counts, kind="stable")
        order = order[counts[order] >= self.min_region_px][: self.max_regions]
        if order.size == 0:
            return np.zeros((0, *out_hw), np.float32)
        return (labels[None, :, :] == order[:, None, None]).astype(np.float32)
