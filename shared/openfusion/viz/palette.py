"""Deterministic colours for region keys, labels and query highlights.

A region key always gets the same colour (in every map, every run, every export). Indices 0..17
take a fixed list of well-separated colours (Trubetskoy's "20 distinct colours" without its grey
and beige, which would read as "no region" or background); larger indices walk the golden-ratio
hue sequence ``frac(i * 0.618...)`` with saturation/value cycling over three levels, so
neighbouring indices stay far apart. Labels (class names) get colours by their position in the
label list, from the same sequence.

Reserved colours:

- ``UNLABELLED_RGB`` light grey: surface without a region;
- ``HIGHLIGHT_RGB``: the best query match (strong red), ``HIGHLIGHT_RANK_RGB`` for the next ranks.
"""

from __future__ import annotations

import colorsys
from collections.abc import Sequence

import numpy as np

GOLDEN_RATIO_CONJUGATE = 0.6180339887498949
UNLABELLED_RGB = (190, 190, 190)
#: Best match of a query: a strong red, far from every grey of the backdrop.
HIGHLIGHT_RGB = (235, 30, 30)
#: Matches ranked 2, 3, ... (repeats the last colour after the list).
HIGHLIGHT_RANK_RGB = ((255, 150, 0), (250, 220, 20), (40, 200, 240), (200, 60, 230))

DISTINCT_RGB = (
    (230, 25, 75), (60, 180, 75), (255, 225, 25), (67, 99, 216), (245, 130, 49), (145, 30, 180),
    (66, 212, 244), (240, 50, 230), (191, 239, 69), (250, 190, 212), (70, 153, 144), (220, 190, 255),
    (154, 99, 36), (128, 0, 0), (170, 255, 195), (128, 128, 0), (255, 216, 177), (0, 0, 117),
)  # fmt: skip
_SATURATION = (0.80, 0.60, 0.95)
_VALUE = (0.92, 0.75, 0.60)


def index_colors(indices: np.ndarray | Sequence[int]) -> np.ndarray:
    """(N, 3) uint8 RGB for non-negative integer ``indices`` (keys or label positions)."""
    idx = np.asarray(indices, dtype=np.int64).reshape(-1)
    if idx.size and idx.min() < 0:
        raise ValueError(f"palette indices must be >= 0, got {int(idx.min())}")
    out = np.empty((len(idx), 3), np.uint8)
    fixed = idx < len(DISTINCT_RGB)
    out[fixed] = np.asarray(DISTINCT_RGB, np.uint8)[idx[fixed]]
    for i in np.flatnonzero(~fixed):
        k = int(idx[i])
        hue = (k * GOLDEN_RATIO_CONJUGATE + 0.05) % 1.0
        r, g, b = colorsys.hsv_to_rgb(hue, _SATURATION[k % 3], _VALUE[(k // 3) % 3])
        out[i] = (round(r * 255), round(g * 255), round(b * 255))
    return out


def key_colors(keys: np.ndarray | Sequence[int]) -> np.ndarray:
    """(N, 3) uint8 colour per region key; key ``-1`` (no region) is :data:`UNLABELLED_RGB`."""
    keys = np.asarray(keys, dtype=np.int64).reshape(-1)
    out = np.empty((len(keys), 3), np.uint8)
    out[:] = UNLABELLED_RGB
    labelled = keys >= 0
    if labelled.any():
        uniq, inverse = np.unique(keys[labelled], return_inverse=True)
        out[labelled] = index_colors(uniq)[inverse]
    return out


def highlight_color(rank: int) -> tuple[int, int, int]:
    """Colour of the query match ranked ``rank`` (0 = best)."""
    if rank < 0:
        raise ValueError(f"rank must be >= 0, got {rank}")
    if rank == 0:
        return HIGHLIGHT_RGB
    return HIGHLIGHT_RANK_RGB[min(rank - 1, len(HIGHLIGHT_RANK_RGB) - 1)]


def greyed(colors: np.ndarray, *, lightness: float = 0.72, contrast: float = 0.3) -> np.ndarray:
    """Desaturated, low-contrast version of RGB ``colors`` (N, 3) uint8: the backdrop of a highlight.

    Keeps a hint of the original brightness (``contrast`` of it) around a mid grey ``lightness``.
    """
    rgb = np.asarray(colors, dtype=np.float32).reshape(-1, 3) / 255.0
    luma = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    grey = lightness + contrast * (luma - 0.5)
    grey = np.clip(np.round(grey * 255.0), 0, 255).astype(np.uint8)
    return np.repeat(grey[:, None], 3, axis=1)


def hex_color(rgb: Sequence[int] | np.ndarray) -> str:
    """``#rrggbb`` of an RGB triple."""
    r, g, b = (int(c) for c in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"
