"""The per-tile parts of region summaries and region contacts, and adding them up.

The records :class:`~openfusion.mapping.tilereadouts.TileReadouts` keeps per tile (what a part
holds, why it is exact and when it is stale: :mod:`openfusion.mapping.tilereadouts`):
:class:`SummaryPart` (per key slot: point count, coordinate sums, lowest and highest values per
axis), :class:`ContactPart` (per key: labelled voxels and contact counts), :class:`StoredPart` (a
paged-out tile's part: the index memory keeps while the part itself is in the part store). Here
too their flat-array encoding for the part store (:func:`part_arrays` / :func:`part_of`), the exact
rewrite of a contact part after a merge (:func:`relabel_contacts`), and adding every tile's part up
into the whole map's contacts (:func:`combine_contacts`) and region table
(:func:`combine_summaries`, streamed, with the percentile check that says which parts kept too few
values). Pure numpy: nothing here reads the grid or takes a lock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from openfusion.mapping.merging import RegionContacts, contacts_of_counts
from openfusion.mapping.summaries import BBOX_PERCENTILE, RegionTable

Tile = tuple[int, int, int]


@dataclass
class SummaryPart:
    """One tile's surface points, per key slot (module docstring). ``low[i][a]``: the lowest values
    of slot ``i`` along axis ``a``, ascending; ``high[i][a]``: the highest, negated, ascending."""

    clock: int
    slots: np.ndarray  # (S,) int64
    count: np.ndarray  # (S,) int64
    sums: np.ndarray  # (S, 3) float64
    low: list[list[np.ndarray]] = field(default_factory=list)
    high: list[list[np.ndarray]] = field(default_factory=list)
    #: The slots whose keys decided the read-out's vote in the tile (``chunkreadouts._seen_slots``),
    #: sorted: a merge or a cleared key of one of them makes the part stale. Empty without a vote.
    seen: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def holds(self, slots: np.ndarray) -> bool:
        """Whether the part counts points of one of ``slots`` or its vote read one of them."""
        return bool(np.isin(self.slots, slots).any() or np.isin(self.seen, slots).any())

    def votes_on(self, slots: np.ndarray) -> bool:
        """Whether its vote read one of ``slots`` (a merge of them may move its points)."""
        return bool(np.isin(self.seen, slots).any())


@dataclass
class ContactPart:
    """One tile's contact counts, in keys (module docstring)."""

    clock: int
    keys: np.ndarray  # (R,) int64
    surface: np.ndarray  # (R,) int64
    owner: np.ndarray  # (P,) int64
    other: np.ndarray  # (P,) int64
    count: np.ndarray  # (P,) int64

    def holds(self, keys: np.ndarray) -> bool:
        return bool(np.isin(self.keys, keys).any() or np.isin(self.other, keys).any())


@dataclass
class StoredPart:
    """A paged-out tile's part, kept in the part store (:mod:`openfusion.mapping.partstore`): in
    memory only its clock and what a merge or a cleared key must know (the slots of a summary part;
    the keys, owners and others of a contact part)."""

    clock: int
    present: np.ndarray  # (n,) int64, sorted
    #: A summary part's slots, point counts and coordinate sums (what adding parts up reads first).
    slots: np.ndarray | None = None
    count: np.ndarray | None = None
    sums: np.ndarray | None = None
    seen: np.ndarray | None = None  # a summary part's ``seen``

    def holds(self, keys: np.ndarray) -> bool:
        return bool(np.isin(self.present, keys).any())

    def votes_on(self, slots: np.ndarray) -> bool:
        return bool(np.isin(self.seen, slots).any()) if self.seen is not None else self.holds(slots)


def stored_index(kind: str, part: SummaryPart | ContactPart) -> StoredPart:
    """What memory keeps of ``part`` once the part itself is in the part store."""
    if isinstance(part, SummaryPart):
        return StoredPart(part.clock, _present(kind, part), part.slots, part.count, part.sums, part.seen)
    return StoredPart(part.clock, _present(kind, part))


def part_arrays(part: SummaryPart | ContactPart) -> dict[str, np.ndarray]:
    """A part as flat arrays (the part store's encoding)."""
    if isinstance(part, ContactPart):
        return {"clock": np.array([part.clock], np.int64), "keys": part.keys, "surface": part.surface,
                "owner": part.owner, "other": part.other, "count": part.count}
    lows = [v for per in part.low for v in per]
    highs = [v for per in part.high for v in per]
    return {"clock": np.array([part.clock], np.int64), "slots": part.slots, "count": part.count, "sums": part.sums,
            "seen": part.seen, "low_n": np.array([len(v) for v in lows], np.int64), "high_n": np.array([len(v) for v in highs], np.int64),
            "low": np.concatenate(lows) if lows else np.zeros(0, np.float32),
            "high": np.concatenate(highs) if highs else np.zeros(0, np.float32)}


def part_of(kind: str, a: dict[str, np.ndarray]) -> SummaryPart | ContactPart:
    """The inverse of :func:`part_arrays`."""
    clock = int(a["clock"][0])
    if kind == "contacts":
        return ContactPart(clock, a["keys"], a["surface"], a["owner"], a["other"], a["count"])
    part = SummaryPart(clock, a["slots"], a["count"], a["sums"], seen=a.get("seen", np.zeros(0, np.int64)))
    for name, out in (("low", part.low), ("high", part.high)):
        values = np.split(a[name], np.cumsum(a[f"{name}_n"])[:-1]) if len(a[f"{name}_n"]) else []
        for i in range(len(part.slots)):
            out.append(list(values[3 * i : 3 * i + 3]))
    return part


def _present(kind: str, part: SummaryPart | ContactPart) -> np.ndarray:
    if isinstance(part, ContactPart):
        return np.unique(np.concatenate([part.keys, part.owner, part.other]).astype(np.int64))
    return np.unique(np.concatenate([part.slots, part.seen]).astype(np.int64))


def relabel_contacts(part: ContactPart, mapping: dict[int, int]) -> ContactPart | None:
    """A contact part after keys were merged (``{b: a}``) or cleared (``{b: -1}``), exactly, or None
    when it must be counted again. Contacts count, per (owner, other) key pair, the owner's voxels
    touching at least one voxel of the other: renaming ``b`` to ``a`` is exact when the part holds
    ``b`` and not ``a`` (no two counts merge into one), clearing ``b`` drops its rows and pairs
    (the labelled voxels of other keys are unchanged). A part holding one of a merge's keys and
    another key the mapping names (both ``a`` and ``b``, or two of its entries) is counted again."""
    present = set(_present("contacts", part).tolist())
    named = {k for pair in mapping.items() for k in pair if k >= 0}
    hit = present & named
    sources = hit & set(mapping)
    if not sources:
        return part  # only merge targets (or nothing) here: no voxel of this part changed its key
    if len(hit) > 1:
        return None
    (b,) = sources
    a = mapping[b]
    if a < 0:
        keep_k = part.keys != b
        keep_p = (part.owner != b) & (part.other != b)
        return ContactPart(part.clock, part.keys[keep_k], part.surface[keep_k], part.owner[keep_p],
                           part.other[keep_p], part.count[keep_p])
    return ContactPart(part.clock, np.where(part.keys == b, a, part.keys), part.surface.copy(),
                       np.where(part.owner == b, a, part.owner), np.where(part.other == b, a, part.other),
                       part.count.copy())


def combine_contacts(parts: list[ContactPart]) -> RegionContacts:
    """The whole map's contacts from every tile's part (sums)."""
    if not parts:
        return RegionContacts.empty()
    keys = np.concatenate([p.keys for p in parts])
    if not len(keys):
        return RegionContacts.empty()
    surface = np.concatenate([p.surface for p in parts])
    uk, inv = np.unique(keys, return_inverse=True)
    total = np.bincount(inv.reshape(-1), weights=surface, minlength=len(uk)).astype(np.int64)
    owner = np.concatenate([p.owner for p in parts])
    other = np.concatenate([p.other for p in parts])
    count = np.concatenate([p.count for p in parts])
    if len(owner):
        pairs, inv = np.unique(np.stack([owner, other], axis=1), axis=0, return_inverse=True)
        summed = np.bincount(inv.reshape(-1), weights=count, minlength=len(pairs)).astype(np.int64)
        owner, other, count = pairs[:, 0], pairs[:, 1], summed
    return contacts_of_counts(uk, total, owner, other, count)


@dataclass
class _Bound:
    """One percentile bound to find: ascending ranks ``r1 <= r2`` interpolated with weight ``w``."""

    r1: int
    r2: int
    w: float


def _bounds(n: int, percentile: float) -> tuple[_Bound, _Bound]:
    """The low and high bound of :func:`openfusion.mapping.queries.region_summaries` for ``n`` points
    (the high one in ranks of the negated values)."""
    q = float(percentile) / 100.0
    out = []
    for frac in (q, 1.0 - q):
        pos = frac * (n - 1)
        lo = int(math.floor(pos))
        hi = min(lo + 1, n - 1)
        out.append((lo, hi, pos - lo))
    (l1, l2, lw), (h1, h2, hw) = out
    # High side on negated values: ascending rank i of v is rank n - 1 - i of -v.
    return _Bound(l1, l2, lw), _Bound(n - 1 - h2, n - 1 - h1, hw)


def combine_summaries(parts: Any, key1: np.ndarray, percentile: float = BBOX_PERCENTILE, *,
                      index: Any = None) -> tuple[RegionTable, dict[tuple[Tile, int], int]]:
    """The whole map's region table from every tile's part, and the (tile, slot) parts that kept
    too few values for it to be exact, with how many they must keep (module docstring).

    Streamed, so adding up a floor's parts never holds them all: ``index`` (default: ``parts``)
    gives every tile's slots, counts and sums (the points and centroid per key, and so the ranks
    each box bound needs); ``parts`` (a list of ``(tile, part)``, or a callable returning an
    iterator over them, e.g. parts read from the part store one at a time) is then read once,
    keeping per key, side and axis only the lowest values the bound's rank needs."""
    first = index if index is not None else (parts() if callable(parts) else parts)
    counts: dict[int, int] = {}
    sums: dict[int, np.ndarray] = {}
    for _t, part in first:
        for i, s in enumerate(part.slots):
            key = int(key1[int(s)]) - 1
            if key >= 0:
                counts[key] = counts.get(key, 0) + int(part.count[i])
                sums[key] = sums.get(key, np.zeros(3)) + np.asarray(part.sums[i], np.float64)
    keys = sorted(counts)
    row_of = {k: r for r, k in enumerate(keys)}
    bounds = {k: _bounds(counts[k], percentile) for k in keys}
    lowest: dict[tuple[int, int, int], np.ndarray] = {}
    truncated: dict[tuple[int, int, int], list[tuple[Tile, int, float]]] = {}
    for t, part in (parts() if callable(parts) else parts):
        for i, s in enumerate(part.slots):
            key = int(key1[int(s)]) - 1
            if key < 0:
                continue
            n_i = int(part.count[i])
            for side, values in ((0, part.low[i]), (1, part.high[i])):
                k = bounds[key][side].r2 + 1
                for axis in range(3):
                    lst = values[axis]
                    at = (key, side, axis)
                    if len(lst) < n_i:
                        truncated.setdefault(at, []).append((t, int(s), float(lst[-1]) if len(lst) else -math.inf))
                    run = np.concatenate([lowest[at], lst]) if at in lowest else np.asarray(lst, np.float64)
                    if len(run) > k:
                        run = np.partition(run, k - 1)[:k]
                    lowest[at] = run.astype(np.float64, copy=False)
    n_keys = len(keys)
    count_arr = np.zeros(n_keys, np.int64)
    centroid = np.zeros((n_keys, 3), np.float32)
    bbox = np.zeros((2, n_keys, 3), np.float64)
    failing: dict[tuple[Tile, int], int] = {}
    for key in keys:
        row = row_of[key]
        n = counts[key]
        count_arr[row] = n
        centroid[row] = (sums[key] / max(n, 1)).astype(np.float32)
        for side in (0, 1):
            bound = bounds[key][side]
            k = bound.r2 + 1
            for axis in range(3):
                at = (key, side, axis)
                run = lowest.get(at, np.zeros(0))
                cut = float(run.max()) if len(run) >= k else None
                ok = True
                for t, slot, last in truncated.get(at, []):
                    if cut is None or last < cut:
                        failing[(t, slot)] = max(failing.get((t, slot), 0), int(1.25 * k) + 16)
                        ok = False
                if not ok or cut is None:
                    continue
                ordered = np.sort(run)
                v1, v2 = float(ordered[bound.r1]), float(ordered[bound.r2])
                if side == 1:  # ranks of negated values: v[h1] = -v2, v[h2] = -v1 (negation is exact)
                    v1, v2 = -v2, -v1
                bbox[side, row, axis] = v1 * (1.0 - bound.w) + v2 * bound.w
    table = RegionTable(np.array(keys, np.int32), count_arr, centroid, bbox[0].astype(np.float32),
                        bbox[1].astype(np.float32))
    return table, failing
