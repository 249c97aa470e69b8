"""One query text -> ranked regions with relevancy, match, nearby objects and relations.

Shared by every query path (the query service, ``openfusion query --map-dir``, the in-process run):
each supplies how to rank regions for a vector (its dictionary, with its rule for regions too
small to be answers), the regions' embeddings and their boxes; this module does the rest, so
every path answers alike:

- a plain text: regions ranked by cosine ``score``; each gets ``relevancy`` and ``match``
  (:mod:`openfusion.mapping.relevancy`); ``match`` compares a region with the best of the
  :data:`MATCH_POOL` regions closest to the text (v9's share of the best), so it is the same
  whatever ``top_k`` asks for;
- "X REL Y" (:func:`~openfusion.mapping.relations.parse_relation_query`): X candidates ranked by
  the relation to the best Y matches (:func:`~openfusion.mapping.relations.rank_by_relation`);
  each X hit that stands in the relation names its anchor; ``score``, ``relevancy`` and ``match``
  are those of X (``match`` measured against the best X in the relation); when no region matches
  Y the text is answered as a plain query;
- every hit: up to three nearby regions with the hit's relation to each
  (:func:`~openfusion.mapping.relations.nearby_regions`).

:func:`texts_to_embed` lists what to embed for a list of texts (the texts, the X and Y of
relation queries, and the core noun phrase and head word of each for relevancy's head rule), so a
caller embeds everything in one encoder call; :func:`texts_to_rank` the ones whose regions are
ranked (the head rule's parts only score regions the others ranked).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from openfusion.mapping.relations import (
    Nearby,
    RegionBoxes,
    RelationQuery,
    nearby_regions,
    parse_relation_query,
    rank_by_relation,
)
from openfusion.mapping.relevancy import RelevancyScorer, relevancy_texts

#: Best Y matches a relation query measures X candidates against.
MAX_ANCHORS = 3
#: X candidates a relation query looks at beyond ``top_k``.
RELATION_CANDIDATES = 32
#: Regions (closest by cosine) a text is scored against to find its best margin, which ``match``
#: compares every hit with (:func:`openfusion.mapping.relevancy.match_mask`); ``top_k`` more when
#: it asks for more. A region's margin rarely beats the top 32 cosines' best from further down.
MATCH_POOL = 32


def pool_size(n: int) -> int:
    """How many ranked regions to score when ``n`` are wanted (:data:`MATCH_POOL` at least)."""
    return max(int(n), MATCH_POOL)

Rank = Callable[[np.ndarray, int], list[tuple[int, float]]]
Embeddings = Callable[[list[int]], np.ndarray]


@dataclass
class RankedRegion:
    """One answer region before it becomes a library result or a wire hit."""

    key: int
    score: float
    relevancy: float
    match: bool
    nearby: list[Nearby] = field(default_factory=list)
    relation: Nearby | None = None  # relation queries: the anchor this region stands in the relation to


@dataclass
class TextAnswer:
    text: str
    regions: list[RankedRegion]
    relation: RelationQuery | None = None
    anchors: list[int] = field(default_factory=list)  # relation queries: the Y regions used

    @property
    def matched(self) -> bool:
        return any(r.match for r in self.regions)


def texts_to_rank(texts: Sequence[str]) -> list[str]:
    """The texts whose regions are ranked: every text, then the X and Y of each relation query;
    each once, in first-seen order."""
    wanted = list(texts)
    for text in texts:
        rq = parse_relation_query(text)
        if rq is not None:
            wanted += [rq.target, rq.anchor]
    return list(dict.fromkeys(wanted))


def texts_to_embed(texts: Sequence[str]) -> list[str]:
    """:func:`texts_to_rank`, then what the head rule of relevancy embeds for each of them
    (:func:`~openfusion.mapping.relevancy.relevancy_texts`; only scored, never ranked); each once,
    in first-seen order."""
    ranked = texts_to_rank(texts)
    return list(dict.fromkeys(ranked + [part for text in ranked for part in relevancy_texts(text)]))


def _margins(
    rank: Rank, n: int, text: str, vectors: Mapping[str, np.ndarray], embeddings: Embeddings,
    scorer: RelevancyScorer,
) -> tuple[list[tuple[int, float]], np.ndarray]:
    """The :func:`pool_size` (``n``) regions closest to ``text`` ((key, cosine), best first) and
    their margins."""
    ranked = rank(vectors[text], pool_size(n))
    if not ranked:
        return [], np.zeros(0)
    return ranked, scorer.text_margins(text, vectors, embeddings([k for k, _ in ranked]))


def _regions(ranked: list[tuple[int, float]], margin: np.ndarray, match: np.ndarray, n: int,
             scorer: RelevancyScorer) -> list[RankedRegion]:
    rel = scorer.relevancy_of(margin)
    return [RankedRegion(int(k), float(s), round(float(r), 4), bool(ok))
            for (k, s), r, ok in zip(ranked[:n], rel, match, strict=False)]


def _scored(
    rank: Rank, n: int, text: str, vectors: Mapping[str, np.ndarray], embeddings: Embeddings,
    scorer: RelevancyScorer,
) -> list[RankedRegion]:
    """The ``n`` regions closest to ``text`` with relevancy and match, the match judged among
    :func:`pool_size` of them."""
    ranked, margin = _margins(rank, n, text, vectors, embeddings, scorer)
    return _regions(ranked, margin, scorer.matches(margin), n, scorer)


def _relation_candidates(
    rq: RelationQuery, anchors: list[int], n: int, vectors: Mapping[str, np.ndarray], *, rank: Rank,
    embeddings: Embeddings, scorer: RelevancyScorer, boxes: RegionBoxes, up_axis: str,
) -> list[RankedRegion]:
    """X's ``n`` candidates of "X REL Y", ordered by the relation to ``anchors``, each naming its
    anchor. ``match``'s best (v9's share) is the best X that stands in the relation ("the chair
    next to the table" is the chair asked for; another chair is a chair as much as it is), or the
    best X when none does."""
    ranked, margin = _margins(rank, n, rq.target, vectors, embeddings, scorer)
    is_x = scorer.is_match(scorer.relevancy_of(margin))
    first = rank_by_relation([(k, 0.0, bool(x)) for (k, _), x in zip(ranked, is_x, strict=True)], anchors, boxes,
                             rq.relation, up_axis=up_axis)
    holding = {r.key for r in first if r.holds}
    asked = [m for (k, _), m, x in zip(ranked, margin, is_x, strict=True) if x and k in holding]
    candidates = _regions(ranked, margin, scorer.matches(margin, best=max(asked) if asked else None), n, scorer)
    by_key = {c.key: c for c in candidates}
    order = rank_by_relation([(c.key, c.relevancy, c.match) for c in candidates], anchors, boxes, rq.relation,
                             up_axis=up_axis)
    for r in order:
        by_key[r.key].relation = r.anchor
    return [by_key[r.key] for r in order]


def answer_text(
    text: str,
    vectors: Mapping[str, np.ndarray],
    *,
    rank: Rank,
    embeddings: Embeddings,
    scorer: RelevancyScorer,
    boxes: RegionBoxes | None,
    top_k: int,
    up_axis: str = "+z",
    nearby: Callable[[int], list[Nearby]] | None = None,
) -> TextAnswer:
    """The answer to ``text`` (module docstring). ``vectors``: the embedding of every text of
    :func:`texts_to_embed`; ``rank(vector, n)``: up to ``n`` (key, cosine) best first, regions
    that are no answers already left out (it is asked for :func:`pool_size` of them); ``boxes``: every answerable region's box (None: no
    relations, no nearby). A relation query whose Y matches no region is answered as a plain
    query (the whole text): "the thing above my head" names no region "my head" to be above.
    ``nearby(key)``: :func:`~openfusion.mapping.relations.nearby_regions` of ``key`` in ``boxes``
    with ``up_axis`` (a caller that keeps them between queries passes its memo; None: computed)."""
    rq = parse_relation_query(text) if boxes is not None else None
    anchors: list[int] = []
    if rq is not None:
        ys = _scored(rank, MAX_ANCHORS, rq.anchor, vectors, embeddings, scorer)
        anchors = [y.key for y in ys if y.match]
        if not anchors:
            rq = None
    if rq is None:
        regions = _scored(rank, top_k, text, vectors, embeddings, scorer)
    else:
        assert boxes is not None  # a relation is parsed only with boxes
        regions = _relation_candidates(rq, anchors, top_k + RELATION_CANDIDATES, vectors, rank=rank,
                                       embeddings=embeddings, scorer=scorer, boxes=boxes, up_axis=up_axis)[:top_k]
    if boxes is not None:
        for region in regions:
            region.nearby = nearby(region.key) if nearby is not None else nearby_regions(
                region.key, boxes, up_axis=up_axis)
    return TextAnswer(text, regions, rq, anchors)
