"""Where a region is: spatial relations between region boxes, and "X on/next to/under/above Y" queries.

Pure functions on axis-aligned boxes (world, metres) and the map's up axis; deterministic (ties
break on key). The relation of region A to region B (:func:`relation_of`), tried in this order:

- ``on``: at least :data:`FOOTPRINT_SHARE` of A's footprint (its box seen from above) lies over
  B's footprint, and A's bottom lies within :data:`SUPPORT_GAP_M` of B's top (a monitor on the
  desk, a chair on the floor), or A lies inside B's box raised more than :data:`SUPPORT_GAP_M`
  off B's bottom (a pillow on a bed whose headboard is higher than the pillow);
- ``under``: B is on or above A, or A sits in B's footprint (at least :data:`FOOTPRINT_SHARE`)
  on the same level as B's bottom (within :data:`SUPPORT_GAP_M`) with its top at least
  :data:`SUPPORT_GAP_M` below B's top (a chair pushed under a table, whose box reaches the floor);
  the "inside" rules need B's footprint at most :data:`MAX_COVER_RATIO` times A's (a window is
  not "under" a region whose box spans the room's walls);
- ``above``: A's bottom is more than :data:`SUPPORT_GAP_M` over B's top and their footprints
  overlap (a lamp above the table);
- ``next to``: none of those, the boxes share some height, and the horizontal gap between the
  footprints is at most :data:`NEXT_TO_M` (0 when they overlap).

The up axis is a parameter (:class:`~openfusion.mapping.params.QueryParams` ``up_axis``, one of
``+x -x +y -y +z -z``): the synthetic world and ScanNet have ``+z`` up (floor at z = 0); a source
with another convention sets it.

Relation queries (:func:`parse_relation_query`): ``[the|a|an] X REL [the|a|an] Y`` where REL is
one of ``on``, ``on top of``, ``under``, ``underneath``, ``beneath``, ``below``, ``above``,
``over``, ``next to``, ``beside``, ``near``, ``by`` (the first relation word with text on both
sides splits the query; "something to sit on" has nothing after "on" and stays a plain query, and
so does a text whose X is a generic word, "the thing above my head"; the answer path
(:func:`openfusion.mapping.answers.answer_text`) also answers one whose Y matches no region as
a plain query).
:func:`rank_by_relation` orders the X candidates: first those that match X and stand in the
relation to one of the best Y matches, then the other X matches, then the rest; within each,
by X relevancy, then distance to the anchor, then key.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from openfusion.mapping.query_head import drop_request
from openfusion.wire.schemas.query import RELATIONS  # the relations, in the order relation_of tries them

#: A's bottom within this of B's top: A rests on B (metres; boxes are 1st-99th percentile boxes of
#: voxel centres, so a few centimetres of slack on each side).
SUPPORT_GAP_M = 0.10
#: Share of A's footprint that must lie over B's for ``on`` / ``under``.
FOOTPRINT_SHARE = 0.5
#: ``under`` by footprint (a chair pushed under a table) only below a region whose footprint is at
#: most this many times A's: a box that spans a room (a wall region made of several walls, the
#: ceiling) covers everything without anything being under it.
MAX_COVER_RATIO = 32.0
#: Largest horizontal gap between footprints for ``next to`` (metres).
NEXT_TO_M = 0.5
#: ``nearby``: regions within this box-to-box distance (metres).
NEARBY_M = 1.0
#: Most nearby regions reported per hit.
MAX_NEARBY = 3

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
#: Subjects that name no kind of thing: "X REL Y" with one of these as X is a plain query.
GENERIC_SUBJECTS = frozenset(
    "thing things something anything one stuff object objects item items place spot somewhere".split())

_SYNONYMS = {
    "on": "on", "on top of": "on", "under": "under", "underneath": "under", "beneath": "under",
    "below": "under", "above": "above", "over": "above", "next to": "next to", "beside": "next to",
    "near": "next to", "by": "next to",
}
_REL_WORDS = sorted(_SYNONYMS, key=len, reverse=True)  # "on top of" before "on"
_PATTERN = re.compile(
    r"^\s*(?:(?:the|a|an)\s+)?(?P<target>.+?)\s+(?:(?:that|which)\s+is\s+|is\s+)?(?P<rel>"
    + "|".join(re.escape(w) for w in _REL_WORDS)
    + r")\s+(?:(?:the|a|an)\s+)?(?P<anchor>\S.*?)\s*[.?!]?\s*$",
    re.IGNORECASE,
)


@dataclass(frozen=True)
class RelationQuery:
    """A parsed "X REL Y": the target text, the relation (one of :data:`RELATIONS`) and the anchor text."""

    target: str
    relation: str
    anchor: str


def parse_relation_query(text: str) -> RelationQuery | None:
    """"the chair next to the table" -> RelationQuery("chair", "next to", "table"); None when
    ``text`` is not of that form, or when X is a generic word (:data:`GENERIC_SUBJECTS`: "the
    thing above my head" describes a place, not a thing near "my head"; module docstring)."""
    m = _PATTERN.match(drop_request(text))  # "go to the chair next to the table"; "turn on the lamp": no "on"
    if m is None:
        return None
    target, anchor = m.group("target").strip(), m.group("anchor").strip()
    if not target or not anchor or target.lower() in GENERIC_SUBJECTS:
        return None
    return RelationQuery(target, _SYNONYMS[m.group("rel").lower()], anchor)


def up_axis_index(up_axis: str) -> tuple[int, float]:
    """(axis index, sign) of ``"+z"`` and the like."""
    if up_axis not in UP_AXES:
        raise ValueError(f"up_axis must be one of {', '.join(UP_AXES)}, got {up_axis!r}")
    return "xyz".index(up_axis[1]), (1.0 if up_axis[0] == "+" else -1.0)


@dataclass(frozen=True)
class _Box:
    """A box as height interval [bottom, top] and footprint [lo, hi] on the two other axes."""

    bottom: float
    top: float
    foot_lo: np.ndarray  # (2,)
    foot_hi: np.ndarray  # (2,)

    @property
    def foot_area(self) -> float:
        # plain floats: the same IEEE products as np.prod of the two sides, without numpy's per-call cost
        (x0, y0), (x1, y1) = self.foot_lo.tolist(), self.foot_hi.tolist()
        return max(x1 - x0, 1e-6) * max(y1 - y0, 1e-6)


def _box(lo: np.ndarray, hi: np.ndarray, up_axis: str) -> _Box:
    axis, sign = up_axis_index(up_axis)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    a, b = sign * lo[axis], sign * hi[axis]
    others = [i for i in range(3) if i != axis]
    return _Box(min(a, b), max(a, b), lo[others], hi[others])


def _foot_overlap(a: _Box, b: _Box) -> float:
    """Area of the intersection of the two footprints."""
    (ax0, ay0), (ax1, ay1) = a.foot_lo.tolist(), a.foot_hi.tolist()
    (bx0, by0), (bx1, by1) = b.foot_lo.tolist(), b.foot_hi.tolist()
    return max(min(ax1, bx1) - max(ax0, bx0), 0.0) * max(min(ay1, by1) - max(ay0, by0), 0.0)


def _foot_gap(a: _Box, b: _Box) -> float:
    """Horizontal distance between the footprints (0 when they touch or overlap)."""
    gap = np.maximum(0.0, np.maximum(a.foot_lo - b.foot_hi, b.foot_lo - a.foot_hi))
    return float(np.linalg.norm(gap))


def box_distance(a_lo: np.ndarray, a_hi: np.ndarray, b_lo: np.ndarray, b_hi: np.ndarray) -> float:
    """Euclidean distance between two axis-aligned boxes (0 when they touch or overlap)."""
    gap = np.maximum(0.0, np.maximum(np.asarray(a_lo) - np.asarray(b_hi), np.asarray(b_lo) - np.asarray(a_hi)))
    return float(np.linalg.norm(gap))


def _on(a: _Box, b: _Box) -> bool:
    if _foot_overlap(a, b) < FOOTPRINT_SHARE * a.foot_area:
        return False
    if abs(a.bottom - b.top) <= SUPPORT_GAP_M:  # on B's top
        return True
    # inside B's box, raised off B's bottom: on a surface of B below its highest point (a pillow
    # on a bed with a headboard, a book on a shelf)
    return _covers(b, a) and b.bottom + SUPPORT_GAP_M < a.bottom and a.top <= b.top + SUPPORT_GAP_M


def _covers(b: _Box, a: _Box) -> bool:
    """B is not a box that spans a room (:data:`MAX_COVER_RATIO`)."""
    return b.foot_area <= MAX_COVER_RATIO * a.foot_area


def _above(a: _Box, b: _Box) -> bool:
    return a.bottom > b.top + SUPPORT_GAP_M and _foot_overlap(a, b) > 0.0


def _tucked_under(a: _Box, b: _Box) -> bool:
    return (
        _covers(b, a)
        and _foot_overlap(a, b) >= FOOTPRINT_SHARE * a.foot_area
        and a.top <= b.top - SUPPORT_GAP_M
        and abs(a.bottom - b.bottom) <= SUPPORT_GAP_M
    )


def relation_of(
    a_lo: np.ndarray, a_hi: np.ndarray, b_lo: np.ndarray, b_hi: np.ndarray, *, up_axis: str = "+z"
) -> str | None:
    """The relation of box A to box B (module docstring), or None when they are not related."""
    a, b = _box(a_lo, a_hi, up_axis), _box(b_lo, b_hi, up_axis)
    if _on(a, b):
        return "on"
    if _on(b, a) or _above(b, a) or _tucked_under(a, b):
        return "under"
    if _above(a, b):
        return "above"
    shares_height = min(a.top, b.top) >= max(a.bottom, b.bottom)
    if shares_height and _foot_gap(a, b) <= NEXT_TO_M:
        return "next to"
    return None


#: :meth:`RegionBoxes.rows_within`: boxes wider than this on x (metres) are always candidates.
_WIDE_M = 1.0


@dataclass(frozen=True)
class RegionBoxes:
    """The boxes of a map's regions (keys ascending): what relations are computed from."""

    keys: np.ndarray  # (n,) int
    bbox_min: np.ndarray  # (n, 3)
    bbox_max: np.ndarray  # (n, 3)

    def row(self, key: int) -> int | None:
        i = int(np.searchsorted(self.keys, key))
        return i if i < len(self.keys) and int(self.keys[i]) == int(key) else None

    @cached_property
    def _by_x(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
        """float64 boxes; the rows at most :data:`_WIDE_M` wide on x ordered by their low x, those
        low x and the widest of them; the wider rows (walls, floors: few): built once per set of
        boxes (the query service keeps one per set of summaries)."""
        lo, hi = np.asarray(self.bbox_min, np.float64), np.asarray(self.bbox_max, np.float64)
        extent = hi[:, 0] - lo[:, 0]
        wide = extent > _WIDE_M
        narrow = np.flatnonzero(~wide)
        order = narrow[np.argsort(lo[narrow, 0], kind="stable")]
        widest = float(extent[narrow].max()) if len(narrow) else 0.0
        return lo, hi, order, lo[order, 0], widest, np.flatnonzero(wide)

    def rows_within(self, i: int, reach_m: float) -> np.ndarray:
        """Rows (ascending) that may lie within ``reach_m`` of row ``i``'s box: every row whose box
        is that close, and some that are not (a superset found on the x axis alone, from the
        rows sorted by low x, plus every row wider than :data:`_WIDE_M`; the caller measures the
        exact distance)."""
        lo, hi, order, lo_x, widest, wide = self._by_x
        slack = 1e-6  # metres: rounding never drops a row at exactly ``reach_m``
        first = np.searchsorted(lo_x, lo[i, 0] - reach_m - widest - slack, side="left")
        last = np.searchsorted(lo_x, hi[i, 0] + reach_m + slack, side="right")
        return np.sort(np.concatenate([order[first:last], wide]))


@dataclass(frozen=True)
class Nearby:
    """A region near another one: its key, the relation of the hit to it, the box distance (m)."""

    key: int
    relation: str
    distance_m: float


def nearby_regions(
    key: int, boxes: RegionBoxes, *, up_axis: str = "+z", max_count: int = MAX_NEARBY, within_m: float = NEARBY_M
) -> list[Nearby]:
    """Up to ``max_count`` regions related to ``key`` (:func:`relation_of` of ``key``'s box to
    theirs) within ``within_m``, nearest first (then by key). Empty when ``key`` has no box."""
    i = boxes.row(key)
    if i is None:
        return []
    # box distances to the regions within reach on the x axis (the query service holds
    # thousands; :meth:`RegionBoxes.rows_within`); only the few within ``within_m`` go through
    # the per-pair relation rules
    lo, hi = boxes._by_x[:2]
    rows = boxes.rows_within(i, within_m)
    gaps = np.maximum(0.0, np.maximum(lo[i] - hi[rows], lo[rows] - hi[i]))
    dists = np.full(len(lo), np.inf)
    dists[rows] = np.linalg.norm(gaps, axis=1)
    near = rows[dists[rows] <= within_m]
    near = near[near != i]
    # nearest first (then by key); the relation rules run only until max_count regions relate
    order = near[np.lexsort((np.asarray(boxes.keys)[near], dists[near]))]
    found: list[Nearby] = []
    for j in order.tolist():
        rel = relation_of(boxes.bbox_min[i], boxes.bbox_max[i], boxes.bbox_min[j], boxes.bbox_max[j],
                          up_axis=up_axis)
        if rel is not None:
            found.append(Nearby(int(boxes.keys[j]), rel, round(float(dists[j]), 3)))
            if len(found) == max_count:
                break
    return found


@dataclass(frozen=True)
class RankedByRelation:
    """One X candidate of a relation query: whether it stands in the relation to an anchor."""

    key: int
    holds: bool
    anchor: Nearby | None  # the anchor it stands in the relation to (nearest such), else None


def rank_by_relation(
    candidates: Sequence[tuple[int, float, bool]],
    anchors: Sequence[int],
    boxes: RegionBoxes,
    relation: str,
    *,
    up_axis: str = "+z",
) -> list[RankedByRelation]:
    """Order X ``candidates`` ((key, relevancy, match), any order) by ``relation`` to the
    ``anchors`` (the best Y matches, keys): matching candidates in the relation first, then the
    other matching ones, then the rest in the relation, then the others; within each by
    relevancy (higher first), distance to the anchor (nearer first), key. An anchor is never its
    own candidate's anchor; a candidate without a box cannot hold."""
    if relation not in RELATIONS:
        raise ValueError(f"relation must be one of {RELATIONS}, got {relation!r}")
    rows = []
    for key, rel_value, is_match in candidates:
        i = boxes.row(key)
        best: Nearby | None = None
        if i is not None:
            for a in anchors:
                j = boxes.row(a)
                if j is None or int(a) == int(key):
                    continue
                if relation_of(boxes.bbox_min[i], boxes.bbox_max[i], boxes.bbox_min[j], boxes.bbox_max[j],
                               up_axis=up_axis) != relation:
                    continue
                d = round(box_distance(boxes.bbox_min[i], boxes.bbox_max[i], boxes.bbox_min[j], boxes.bbox_max[j]),
                          3)
                if best is None or (d, int(a)) < (best.distance_m, best.key):
                    best = Nearby(int(a), relation, d)
        holds = best is not None
        order = (not (is_match and holds), not is_match, not holds, -float(rel_value),
                 best.distance_m if best else np.inf, int(key))
        rows.append((order, RankedByRelation(int(key), holds, best)))
    rows.sort(key=lambda r: r[0])
    return [r[1] for r in rows]
