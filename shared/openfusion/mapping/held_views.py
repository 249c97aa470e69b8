"""The surface of chosen views that wait for the encoder (:class:`HeldViews`), for the coverage
scorer (:meth:`openfusion.mapping.coverage.CoverageScorer.hold`).

A held view's (surface cube, direction bin) pairs count as shown until it is released. Views come
and go one at a time while every candidate frame is scored against all of them, so the table the
score reads (per cube, the bins some held view shows) is kept up to date with a count per pair:
adding or removing a view touches only its own pairs (about 4,000 for a 640x480 frame, 4 ms to
add and 0.6 ms to remove), where rebuilding the table from every held view after each change cost
27 ms with 64 views. Not thread-safe: the scorer calls it under its lock.
"""

from __future__ import annotations

import numpy as np


class HeldViews:
    """Views held by a key (robot, frame id, stamp), and per cube the OR of the bins they show."""

    def __init__(self) -> None:
        self._views: dict[tuple[str, int, float], list[tuple[int, int]]] = {}
        self._counts: dict[tuple[int, int], int] = {}  # (cube, bin) -> held views that show it
        #: per cube, the bit mask of the bins some held view shows (what the score reads)
        self.bits: dict[int, int] = {}

    def __len__(self) -> int:
        return len(self._views)

    def add(self, key: tuple[str, int, float], cells: np.ndarray, bins: np.ndarray) -> None:
        """Hold a view's (cube, bin) pairs (any order, repeats allowed); a key held already is kept as it is."""
        if key in self._views:
            return
        order = np.lexsort((bins, cells))
        cells, bins = cells[order], bins[order]
        first = np.r_[True, (cells[1:] != cells[:-1]) | (bins[1:] != bins[:-1])] if len(cells) else np.zeros(0, bool)
        pairs = list(zip(cells[first].tolist(), bins[first].tolist(), strict=True))
        self._views[key] = pairs
        for pair in pairs:
            n = self._counts.get(pair, 0)
            self._counts[pair] = n + 1
            if not n:
                self.bits[pair[0]] = self.bits.get(pair[0], 0) | (1 << pair[1])

    def remove(self, key: tuple[str, int, float]) -> None:
        """Release a view (no-op for a key not held)."""
        pairs = self._views.pop(key, None)
        for pair in pairs or ():
            n = self._counts.pop(pair) - 1
            if n:
                self._counts[pair] = n
                continue
            rest = self.bits.get(pair[0], 0) & ~(1 << pair[1])
            if rest:
                self.bits[pair[0]] = rest
            else:
                self.bits.pop(pair[0], None)

    def clear(self) -> None:
        self._views.clear()
        self._counts.clear()
        self.bits.clear()
