"""Spatial relations between region boxes and "X next to Y" queries (openfusion.mapping.relations),
and a region-summary map of a room with two chairs, one next to the table: "the chair next to the
table" answers that one first, through the same library path ``openfusion query --map-dir`` uses.

Bad input tried: an unknown up axis, an unknown relation, texts that only look like relation
queries ("something to sit on": nothing after "on")."""

from __future__ import annotations

import numpy as np
import pytest

from openfusion.encoders import make_text_encoder
from openfusion.mapping import RegionDictionary
from openfusion.mapping.queries import RegionTable, answer_texts
from openfusion.mapping.relations import (
    MAX_NEARBY,
    NEARBY_M,
    Nearby,
    RegionBoxes,
    RelationQuery,
    nearby_regions,
    parse_relation_query,
    rank_by_relation,
    relation_of,
    up_axis_index,
)

# Boxes (lo, hi) in metres, z up: a table (top at 0.75 m), a mug on it, a lamp hanging above it,
# a chair beside it, a box under it, and a far chair.
FLOOR = ((0.0, 0.0, -0.02), (6.0, 5.0, 0.02))
TABLE = ((2.0, 2.0, 0.0), (3.2, 2.8, 0.75))
MUG = ((2.4, 2.3, 0.76), (2.5, 2.4, 0.86))
LAMP = ((2.5, 2.3, 1.6), (2.7, 2.5, 1.9))
NEAR_CHAIR = ((3.4, 2.1, 0.0), (3.9, 2.6, 0.9))
FAR_CHAIR = ((0.3, 4.0, 0.0), (0.8, 4.5, 0.9))
CRATE = ((2.2, 2.2, 0.0), (2.6, 2.6, 0.4))


def _rel(a, b, up: str = "+z") -> str | None:  # noqa: ANN001
    return relation_of(np.array(a[0]), np.array(a[1]), np.array(b[0]), np.array(b[1]), up_axis=up)


def test_relations_of_boxes() -> None:
    assert _rel(MUG, TABLE) == "on"
    assert _rel(TABLE, MUG) == "under"
    assert _rel(TABLE, FLOOR) == "on" and _rel(NEAR_CHAIR, FLOOR) == "on"
    assert _rel(LAMP, TABLE) == "above" and _rel(TABLE, LAMP) == "under"
    assert _rel(CRATE, TABLE) == "under"  # tucked under: in its footprint, below its top
    bed, pillow = ((4.0, 1.3, 0.0), (6.0, 2.8, 1.0)), ((5.5, 1.4, 0.5), (5.8, 2.0, 0.64))  # headboard at 1 m
    assert _rel(pillow, bed) == "on" and _rel(bed, pillow) == "under"
    walls = ((0.0, 0.0, 0.0), (6.0, 5.0, 2.8))  # a region spanning the room's walls covers all, holds nothing
    assert _rel(((0.0, 1.0, 0.9), (0.1, 2.0, 2.0)), walls) != "under"
    assert _rel(NEAR_CHAIR, TABLE) == "next to" and _rel(TABLE, NEAR_CHAIR) == "next to"
    assert _rel(FAR_CHAIR, TABLE) is None  # 1.2 m away and more
    assert _rel(LAMP, NEAR_CHAIR) is None  # no shared height, no overlap from above


def test_the_up_axis_is_a_parameter() -> None:
    """The same scene with y up (x, z, y), or with -z up (z negated): the same relations."""
    swap = lambda b: (tuple(np.array(b[0])[[0, 2, 1]]), tuple(np.array(b[1])[[0, 2, 1]]))  # noqa: E731
    flip = lambda b: ((b[0][0], b[0][1], -b[1][2]), (b[1][0], b[1][1], -b[0][2]))  # noqa: E731
    assert _rel(swap(MUG), swap(TABLE), "+y") == "on" and _rel(swap(LAMP), swap(TABLE), "+y") == "above"
    assert _rel(flip(MUG), flip(TABLE), "-z") == "on" and _rel(flip(CRATE), flip(TABLE), "-z") == "under"
    assert _rel(swap(MUG), swap(TABLE), "+z") != "on"  # the wrong axis gives other relations
    with pytest.raises(ValueError, match="up_axis"):
        up_axis_index("up")


@pytest.mark.parametrize(
    ("text", "parsed"),
    [
        ("the chair next to the table", RelationQuery("chair", "next to", "table")),
        ("cup on the desk", RelationQuery("cup", "on", "desk")),
        ("a lamp above the table?", RelationQuery("lamp", "above", "table")),
        ("the box that is underneath the bed", RelationQuery("box", "under", "bed")),
        ("pillow on top of the sofa", RelationQuery("pillow", "on", "sofa")),
        ("plant beside a window", RelationQuery("plant", "next to", "window")),
        ("Chair Near The Door", RelationQuery("Chair", "next to", "Door")),
        ("something to sit on", None),
        ("chair", None),
        ("on the table", None),
        # a generic X names no thing to find: a plain query ("the thing above my head": the ceiling)
        ("the thing above my head", None),
        ("something on the table", None),
        ("stuff under the bed", None),
        # a leading request or command is no part of X, and a command's particle is no relation
        ("go to the chair next to the table", RelationQuery("chair", "next to", "table")),
        ("Please find the cup on the desk", RelationQuery("cup", "on", "desk")),
        ("turn on the lamp", None),
        ("switch on the light above the desk", RelationQuery("light", "above", "desk")),
    ],
)
def test_parse_relation_query(text: str, parsed: RelationQuery | None) -> None:
    assert parse_relation_query(text) == parsed


def _boxes(*named) -> RegionBoxes:  # noqa: ANN002
    return RegionBoxes(np.arange(len(named)), np.array([b[0] for b in named], np.float32),
                       np.array([b[1] for b in named], np.float32))


def test_nearby_is_nearest_first_at_most_three_and_deterministic() -> None:
    boxes = _boxes(FLOOR, TABLE, MUG, LAMP, NEAR_CHAIR, FAR_CHAIR, CRATE)
    near = nearby_regions(1, boxes)  # the table
    assert len(near) == 3 and [n.distance_m for n in near] == sorted(n.distance_m for n in near)
    assert {(n.key, n.relation) for n in near} <= {(0, "on"), (2, "under"), (6, "next to"), (4, "next to"),
                                                   (3, "under")}
    assert (0, "on") in {(n.key, n.relation) for n in near}
    assert nearby_regions(1, boxes) == near
    assert [(n.key, n.relation) for n in nearby_regions(2, boxes)][0] == (1, "on")  # the mug is on the table
    assert nearby_regions(99, boxes) == []


def test_rank_by_relation_puts_the_matching_candidate_in_the_relation_first() -> None:
    boxes = _boxes(FLOOR, TABLE, MUG, LAMP, NEAR_CHAIR, FAR_CHAIR, CRATE)
    # the far chair is the better X by relevancy, the near one stands next to the anchor (table)
    ranked = rank_by_relation([(5, 0.99, True), (4, 0.98, True), (6, 0.97, False)], [1], boxes, "next to")
    assert [r.key for r in ranked] == [4, 5, 6] and ranked[0].holds and ranked[0].anchor.key == 1
    assert not ranked[1].holds and ranked[1].anchor is None
    # a non-matching region in the relation does not beat a matching one
    ranked = rank_by_relation([(6, 0.5, False), (5, 0.9, True)], [1], boxes, "under")
    assert [r.key for r in ranked] == [5, 6]
    with pytest.raises(ValueError, match="relation"):
        rank_by_relation([], [1], boxes, "inside")


@pytest.mark.parametrize("encoder_name", ["hash"])
def test_the_chair_next_to_the_table_answers_that_chair_first(encoder_name: str) -> None:
    """A room's region summaries with two chairs (the far one is the better "chair" by score:
    it was seen more and its embedding is the name's), a table, a floor and a mug: "the chair next
    to the table" answers the near chair first, naming the table; "chair" alone answers the far
    one first; "cup on the table" finds the mug; every hit carries relevancy, match, centroid and
    nearby regions."""
    text = make_text_encoder(encoder_name)
    d = RegionDictionary(text.embedding_space, text.dim)
    far = d.add(text.encode(["chair"])[0], label="chair")
    near_vec = text.encode(["chair"])[0] * 0.9 + text.encode(["wooden chair"])[0] * 0.1
    near = d.add(near_vec / np.linalg.norm(near_vec), label="chair")
    table = d.add(text.encode(["table"])[0], label="table")
    floor = d.add(text.encode(["floor"])[0], label="floor")
    mug = d.add(text.encode(["cup"])[0], label="cup")
    named = {far: FAR_CHAIR, near: NEAR_CHAIR, table: TABLE, floor: FLOOR, mug: MUG}
    keys = np.array(sorted(named), np.int32)
    lo = np.array([named[k][0] for k in keys], np.float32)
    hi = np.array([named[k][1] for k in keys], np.float32)
    table_ = RegionTable(keys, np.full(len(keys), 500, np.int64), (lo + hi) / 2, lo, hi)
    (next_to, answer), (plain, _), (cup, _) = answer_texts(
        d, table_, ["the chair next to the table", "chair", "cup on the table"], text, top_k=3)
    assert next_to[0].key == near and next_to[0].relation.key == table and next_to[0].relation.relation == "next to"
    assert next_to[1].key == far and next_to[1].relation is None
    assert answer.relation == RelationQuery("chair", "next to", "table") and answer.anchors == [table]
    assert plain[0].key == far
    assert cup[0].key == mug and cup[0].relation.relation == "on" and cup[0].match
    for hit in next_to[:2]:
        assert hit.match and 0.0 <= hit.relevancy <= 1.0
        np.testing.assert_allclose(hit.centroid, (np.array(named[hit.key][0]) + named[hit.key][1]) / 2, atol=1e-6)
        assert (floor, "on") in {(n.key, n.relation) for n in hit.nearby}


def test_a_relation_query_whose_anchor_matches_nothing_is_a_plain_query() -> None:
    """"the chair next to the zebra": no region matches "zebra", so no anchor stands for it and
    the text is answered as a plain query (no relation, no anchors), the chair first; with an
    anchor that matches, the same shape of text stays a relation query."""
    text = make_text_encoder("hash")
    d = RegionDictionary(text.embedding_space, text.dim)
    chair = d.add(text.encode(["chair"])[0], label="chair")
    table = d.add(text.encode(["table"])[0], label="table")
    named = {chair: NEAR_CHAIR, table: TABLE}
    keys = np.array(sorted(named), np.int32)
    lo = np.array([named[k][0] for k in keys], np.float32)
    hi = np.array([named[k][1] for k in keys], np.float32)
    table_ = RegionTable(keys, np.full(len(keys), 500, np.int64), (lo + hi) / 2, lo, hi)
    (zebra, zebra_answer), (next_to, next_to_answer) = answer_texts(
        d, table_, ["the chair next to the zebra", "the chair next to the table"], text, top_k=2)
    assert zebra_answer.relation is None and zebra_answer.anchors == []
    assert zebra[0].key == chair and zebra[0].relation is None
    assert next_to_answer.relation == RelationQuery("chair", "next to", "table") and next_to_answer.anchors == [table]
    assert next_to[0].key == chair and next_to[0].relation.key == table


def _nearby_by_full_scan(key: int, boxes: RegionBoxes, *, up_axis: str = "+z", max_count: int = MAX_NEARBY
                         ) -> list[Nearby]:
    """The nearby search before the x index: distances to every region (the reference)."""
    i = boxes.row(key)
    if i is None:
        return []
    lo, hi = np.asarray(boxes.bbox_min, np.float64), np.asarray(boxes.bbox_max, np.float64)
    dists = np.linalg.norm(np.maximum(0.0, np.maximum(lo[i] - hi, lo - hi[i])), axis=1)
    near = np.flatnonzero(dists <= NEARBY_M)
    near = near[near != i]
    found = []
    for j in near[np.lexsort((np.asarray(boxes.keys)[near], dists[near]))].tolist():
        rel = relation_of(boxes.bbox_min[i], boxes.bbox_max[i], boxes.bbox_min[j], boxes.bbox_max[j], up_axis=up_axis)
        if rel is not None:
            found.append(Nearby(int(boxes.keys[j]), rel, round(float(dists[j]), 3)))
            if len(found) == max_count:
                break
    return found


@pytest.mark.parametrize("up_axis", ["+z", "-y"])
def test_nearby_through_the_x_index_equals_the_full_scan(up_axis: str) -> None:
    """The query service's nearby search looks only at regions within reach on x (plus the wide
    ones): the same lists as measuring every region, with walls spanning the room, boxes exactly
    at the reach, and regions stacked on one another."""
    rng = np.random.default_rng(3)
    n = 2_000
    lo = rng.uniform(0, 8, (n, 3)).astype(np.float32)
    hi = (lo + rng.uniform(0.02, 0.6, (n, 3))).astype(np.float32)
    lo[:4], hi[:4] = [0, 0, 0], [8, 0.1, 3]  # walls and a floor-like slab, wider than any other box
    lo[10], hi[10] = lo[11] + [hi[11, 0] - lo[11, 0] + NEARBY_M, 0, 0], hi[11] + [hi[11, 0] - lo[11, 0] + NEARBY_M, 0, 0]
    lo[20], hi[20] = [lo[21, 0], lo[21, 1], hi[21, 2]], [hi[21, 0], hi[21, 1], hi[21, 2] + 0.2]  # 20 on 21
    boxes = RegionBoxes(np.arange(n) * 3, lo, hi)  # keys not rows
    assert boxes._by_x[5].size >= 4  # the wide rows are there
    compared = 0
    for key in list(range(0, 90, 3)) + [30, 33, 60, 63, 3 * (n - 1), 7]:
        assert nearby_regions(key, boxes, up_axis=up_axis) == _nearby_by_full_scan(key, boxes, up_axis=up_axis)
        every = nearby_regions(key, boxes, up_axis=up_axis, max_count=n)  # all within reach, not just 3
        assert every == _nearby_by_full_scan(key, boxes, up_axis=up_axis, max_count=n)
        compared += len(every)
    assert compared > 10 * 30  # regions related within reach: far more than the three nearest each
