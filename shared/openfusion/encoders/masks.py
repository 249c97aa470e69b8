"""Mask resampling and morphology at the encoder's output resolution (numpy / scipy only)."""

from __future__ import annotations

import functools

import numpy as np
from scipy import ndimage

from openfusion.encoders.base import EncoderError


@functools.lru_cache(maxsize=16)
def _cell_index(height_px: int, width_px: int, out_h: int, out_w: int) -> np.ndarray:
    """Flat output-cell index of every input pixel (pixel centre -> the cell that contains it).

    Uses the pixel-centre convention of :meth:`CameraIntrinsics.scaled`: input pixel u lands in
    output cell floor((u + 0.5) * out / in). For integer factors (640 -> 160) every cell receives
    exactly factor^2 pixels, i.e. exact area averaging. Cached per size (read-only), with the
    pixel count of every cell.
    """
    rows = np.minimum(((np.arange(height_px) + 0.5) * out_h / height_px).astype(np.int64), out_h - 1)
    cols = np.minimum(((np.arange(width_px) + 0.5) * out_w / width_px).astype(np.int64), out_w - 1)
    cell = (rows[:, None] * out_w + cols[None, :]).ravel()
    cell.flags.writeable = False
    return cell


@functools.lru_cache(maxsize=16)
def _cell_count(height_px: int, width_px: int, out_h: int, out_w: int) -> np.ndarray:
    count = np.bincount(_cell_index(height_px, width_px, out_h, out_w), minlength=out_h * out_w).astype(np.float32)
    count.flags.writeable = False
    return count


#: Region ids spanning at most this many values are mapped to rows through a lookup table (one
#: gather per pixel); wider ranges fall back to a binary search per pixel.
_MAX_LOOKUP_RANGE = 1 << 20


def _region_of_pixels(flat: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Row of ``ids`` of every pixel label in ``flat``, or ``ids.size`` for a label not in ``ids``
    (the first row of a repeated id)."""
    n = ids.size
    lo, hi = int(ids.min()), int(ids.max())
    if np.can_cast(flat.dtype, np.int64) and hi - lo < _MAX_LOOKUP_RANGE:
        # table index 0: below lo, hi - lo + 2: above hi; both map to "no region"
        lut = np.full(hi - lo + 3, n, np.int64)
        lut[ids[::-1] - lo + 1] = np.arange(n)[::-1]  # reversed: a repeated id keeps its first row
        return lut[np.clip(flat, lo - 1, hi + 1, dtype=np.int64) - (lo - 1)]
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    pos = np.clip(np.searchsorted(sorted_ids, flat), 0, n - 1)
    return np.where(sorted_ids[pos] == flat, order[pos], n)


def label_ids(label_image: np.ndarray) -> np.ndarray:
    """The sorted distinct labels of an integer image (``np.unique``'s answer), by one bincount
    when the labels are non-negative and span a small range (instance images), else ``np.unique``."""
    flat = label_image.ravel()
    if flat.size and np.can_cast(flat.dtype, np.intp):  # integer labels of at most 63 bits
        lo, hi = int(flat.min()), int(flat.max())
        if lo >= 0 and hi < _MAX_LOOKUP_RANGE:
            return np.flatnonzero(np.bincount(flat, minlength=hi + 1)).astype(label_image.dtype)
    return np.unique(label_image)


def area_downsample_labels(
    label_image: np.ndarray, region_ids: np.ndarray, out_hw: tuple[int, int]
) -> np.ndarray:
    """Per-region coverage fractions on an ``out_hw`` grid.

    ``label_image`` is an HxW integer image; ``region_ids`` the ids to extract (any order). Returns
    (n, h, w) float32 where entry [i, y, x] is the fraction of the input pixels of output cell
    (y, x) that carry ``region_ids[i]``: 1 inside a region, 0 outside, soft in between at boundaries.
    One pass over the image (a table lookup and one bincount), independent of the number of regions.
    """
    if label_image.ndim != 2:
        raise EncoderError(f"label image must be HxW, got shape {label_image.shape}")
    out_h, out_w = int(out_hw[0]), int(out_hw[1])
    H, W = label_image.shape
    if out_h < 1 or out_w < 1 or out_h > H or out_w > W:
        raise EncoderError(f"output size {out_w}x{out_h} must be within 1x1 .. {W}x{H}")
    ids = np.asarray(region_ids, dtype=np.int64).ravel()
    n = ids.size
    cells = out_h * out_w
    if n == 0:
        return np.zeros((0, out_h, out_w), np.float32)
    region = _region_of_pixels(label_image.ravel(), ids)
    # pixels of no region count in an extra row n, dropped: no boolean compaction of the image
    key = region * cells + _cell_index(H, W, out_h, out_w)
    counts = np.bincount(key, minlength=(n + 1) * cells)[: n * cells].astype(np.float32)
    conf = counts.reshape(n, cells) / _cell_count(H, W, out_h, out_w)[None, :]
    return np.clip(conf, 0.0, 1.0).reshape(n, out_h, out_w)


def disk_footprint(radius_px: int) -> np.ndarray:
    """Boolean disk of the given radius (a (2r+1)^2 square mask)."""
    r = int(radius_px)
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    return (x * x + y * y) <= r * r + 1e-9


def erode_soft(conf: np.ndarray, radius_px: int) -> np.ndarray:
    """Grey erosion of one (h, w) confidence map with a disk: moves boundaries inward by radius_px."""
    if radius_px <= 0:
        return conf.copy()
    return ndimage.grey_erosion(conf, footprint=disk_footprint(radius_px), mode="nearest").astype(np.float32)


def dilate_soft(conf: np.ndarray, radius_px: int) -> np.ndarray:
    """Grey dilation of one (h, w) confidence map with a disk: moves boundaries outward by radius_px."""
    if radius_px <= 0:
        return conf.copy()
    return ndimage.grey_dilation(conf, footprint=disk_footprint(radius_px), mode="constant", cval=0.0).astype(
        np.float32
    )


def resize_maps_bilinear(maps: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """Resize (n, h, w) float maps to (n, H, W) with bilinear interpolation (pixel-centre aligned)."""
    n, h, w = maps.shape
    out_h, out_w = int(out_hw[0]), int(out_hw[1])
    if (h, w) == (out_h, out_w):
        return maps.astype(np.float32, copy=True)
    ys = np.clip((np.arange(out_h) + 0.5) * h / out_h - 0.5, 0, h - 1)
    xs = np.clip((np.arange(out_w) + 0.5) * w / out_w - 0.5, 0, w - 1)
    y0 = np.floor(ys).astype(np.int64)
    x0 = np.floor(xs).astype(np.int64)
    y1 = np.minimum(y0 + 1, h - 1)
    x1 = np.minimum(x0 + 1, w - 1)
    wy = (ys - y0).astype(np.float32)[None, :, None]
    wx = (xs - x0).astype(np.float32)[None, None, :]
    m = maps.astype(np.float32)
    top = m[:, y0][:, :, x0] * (1 - wx) + m[:, y0][:, :, x1] * wx
    bottom = m[:, y1][:, :, x0] * (1 - wx) + m[:, y1][:, :, x1] * wx
    return (top * (1 - wy) + bottom * wy).astype(np.float32)
