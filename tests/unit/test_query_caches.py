"""The query service's caches (services/query/caches.py) change when work is done, never what is
answered: the same hits, scores, relevancy, match flags and nearby lists with and without them,
and nothing stale after a dictionary delta, a snapshot, or new region summaries. Hash text
encoder (no model), a few hundred regions, no bus."""

from __future__ import annotations

import time

import numpy as np
import pytest

from openfusion.bus.stats import ServiceStats
from openfusion.encoders import make_text_encoder
from openfusion.mapping import RegionDictionary
from openfusion.mapping.relations import nearby_regions
from openfusion.services.query.caches import RankCache, TextEmbeddings
from openfusion.services.query.service import QueryConfig, QuerySection, QueryService, RegionSummaries
from openfusion.wire.schemas import QueryReply, RegionSummaryReply, TextQuery

TEXT = make_text_encoder("hash")
NAMES = ["chair", "table", "sofa", "lamp", "window", "door", "bed", "pillow", "monitor", "desk", "plant", "shelf"]
QUERIES = ["chair", "a lamp", "the chair next to the table", "pillow on the bed", "something to sit on", "desk"]


def _dictionary(n: int, seed: int = 0) -> RegionDictionary:
    rng = np.random.default_rng(seed)
    d = RegionDictionary(TEXT.embedding_space, TEXT.dim)
    with d.batch():
        for i in range(n):
            name = NAMES[i % len(NAMES)]
            vec = TEXT.encode([name])[0] + 0.3 * rng.standard_normal(TEXT.dim).astype(np.float32)
            d.add(vec.astype(np.float32), label=f"{name} {i}")
    return d


def _reply(n: int, seed: int = 0, *, shift_m: float = 0.0) -> RegionSummaryReply:
    """Boxes of ``n`` regions packed in a 4 m room (so each has neighbours), 80 points each."""
    rng = np.random.default_rng(seed)
    lo = (rng.uniform(0, 4, (n, 3)) + shift_m).astype(np.float32)
    hi = (lo + rng.uniform(0.1, 0.6, (n, 3))).astype(np.float32)
    return RegionSummaryReply(map_version=1, key_horizon=n, age_s=0.0, keys=np.arange(n, dtype=np.int32),
                              bbox_min=lo, bbox_max=hi, num_points=np.full(n, 80, np.int64), centroid=(lo + hi) / 2)


def _summaries(n: int, seed: int = 0, *, shift_m: float = 0.0) -> RegionSummaries:
    return RegionSummaries(_reply(n, seed, shift_m=shift_m), time.monotonic())


def _service(dictionary: RegionDictionary, *, cache: int) -> QueryService:
    svc = QueryService(QueryConfig(map_id="unit", query=QuerySection(text_encoder="hash", text_cache_size=cache)),
                       text_encoder=TEXT)
    svc.replica.reset(dictionary)
    return svc


def _hits(reply: QueryReply) -> list[tuple]:
    return [(h.key, h.score, h.relevancy, h.match, h.label, tuple(h.bbox_min), tuple(h.bbox_max),
             [(n.key, n.relation, n.distance_m, n.label) for n in h.nearby],
             None if h.relation is None else (h.relation.key, h.relation.relation)) for h in reply.regions]


def _uncached(dictionary: RegionDictionary, summaries_seed: int, text: str, *, shift_m: float = 0.0) -> list[tuple]:
    """The answer with nothing kept: no text cache, fresh summaries (empty nearby memo)."""
    svc = _service(dictionary, cache=0)
    svc.summaries = _summaries(300, summaries_seed, shift_m=shift_m)
    return _hits(svc.handle_text(TextQuery(text=text, top_k=5)))


def test_cached_answers_are_the_uncached_ones() -> None:
    d = _dictionary(300)
    svc = _service(d, cache=64)
    svc.summaries = _summaries(300)
    for _round in range(2):  # first round fills every cache, the second answers from them
        for text in QUERIES:
            got = _hits(svc.handle_text(TextQuery(text=text, top_k=5)))
            assert got == _uncached(d, 0, text), text
            assert any(h[7] for h in got), "no hit has nearby regions: the test would not see a stale list"
    assert svc.texts.hits > 0 and len(svc.rankings) > 0 and svc.summaries.derived.nearby_hits > 0


def test_a_dictionary_delta_is_seen_by_the_next_query() -> None:
    d = _dictionary(300)
    svc = _service(d, cache=64)
    svc.summaries = _summaries(300)
    before = _hits(svc.handle_text(TextQuery(text="chair", top_k=5)))
    base = d.version
    new_key = d.add(TEXT.encode(["chair"])[0], label="the chair itself")  # a region exactly "chair"
    svc.on_delta(d.delta_since(base))
    after = _hits(svc.handle_text(TextQuery(text="chair", top_k=5)))
    assert after[0][0] == new_key and before[0][0] != new_key
    assert after == _uncached(d, 0, "chair")


def test_a_snapshot_of_another_dictionary_at_the_same_version_is_seen() -> None:
    """A restarted semantic service can reach the same version number with other regions."""
    d1, d2 = _dictionary(300, seed=1), _dictionary(300, seed=2)
    assert d1.version == d2.version
    svc = _service(d1, cache=64)
    svc.summaries = _summaries(300)
    first = _hits(svc.handle_text(TextQuery(text="lamp", top_k=5)))
    svc.replica.apply_snapshot(d2.snapshot())
    second = _hits(svc.handle_text(TextQuery(text="lamp", top_k=5)))
    assert first == _uncached(d1, 0, "lamp") and second == _uncached(d2, 0, "lamp") and first != second


def test_new_summaries_bring_new_boxes_and_nearby_lists() -> None:
    d = _dictionary(300)
    svc = _service(d, cache=64)
    svc.summaries = _summaries(300, seed=0)
    first = _hits(svc.handle_text(TextQuery(text="the chair next to the table", top_k=5)))
    svc.summaries = _summaries(300, seed=5)  # geometry's next summaries: every box moved
    second = _hits(svc.handle_text(TextQuery(text="the chair next to the table", top_k=5)))
    assert second == _uncached(d, 5, "the chair next to the table") and second != first
    boxes = svc.summaries.boxes(min_points=svc.section.min_region_points)
    key = second[0][0]
    assert svc.summaries.derived.nearby(key, boxes, up_axis="+z") == nearby_regions(key, boxes, up_axis="+z")


def test_text_embeddings_are_bounded_and_encoded_once() -> None:
    calls: list[list[str]] = []

    def encode(texts: list[str]) -> np.ndarray:
        calls.append(list(texts))
        return TEXT.encode(texts)

    cache = TextEmbeddings(encode, max_texts=2)
    a = cache.encode(["a", "b"])
    np.testing.assert_array_equal(a, TEXT.encode(["a", "b"]))
    cache.encode(["b", "a"])
    assert calls == [["a", "b"]]  # both from the cache
    cache.encode(["c"])  # "a" was used last: "b" goes
    cache.encode(["a"])
    assert calls == [["a", "b"], ["c"]] and len(cache) == 2
    cache.encode(["b"])
    assert calls[-1] == ["b"]
    with pytest.raises(ValueError, match="max_texts"):
        TextEmbeddings(encode, max_texts=-1)


def test_rank_cache_holds_one_state() -> None:
    cache = RankCache(max_entries=8)
    cache.put((1, 3), "chair", 32, [(1, 0.9)])
    assert cache.get((1, 3), "chair", 32) == [(1, 0.9)]
    assert cache.get((1, 4), "chair", 32) is None and len(cache) == 0 and cache.invalidations == 1
    cache.put(None, "chair", 32, [(1, 0.9)])  # no dictionary: nothing kept
    assert cache.get(None, "chair", 32) is None and len(cache) == 0


class _Geometry:
    """A runner whose geometry answers the summaries it is given (refresh_summaries' one call)."""

    def __init__(self) -> None:
        self.reply: RegionSummaryReply | None = None
        self.stats = ServiceStats()

    def call(self, endpoint: object, request: object, *, timeout_s: float) -> RegionSummaryReply:
        assert self.reply is not None
        return self.reply


def test_equal_summaries_keep_their_nearby_lists_and_changed_ones_do_not() -> None:
    """The background refresh fetches summaries every second: an unchanged map keeps its memo,
    a changed one starts afresh (and answers from the new boxes)."""
    d = _dictionary(300)
    svc = _service(d, cache=64)
    geometry = _Geometry()
    svc._runner = geometry  # type: ignore[assignment]
    geometry.reply = _reply(300, seed=0)
    assert svc.refresh_summaries()
    svc.handle_text(TextQuery(text="chair", top_k=5))
    memo = svc.summaries.derived
    assert memo.nearby_misses > 0
    assert svc.refresh_summaries()  # the same map again
    assert svc.summaries.derived is memo
    geometry.reply = _reply(300, seed=0, shift_m=0.01)  # every box moved by 1 cm
    assert svc.refresh_summaries()
    assert svc.summaries.derived is not memo
    assert _hits(svc.handle_text(TextQuery(text="chair", top_k=5))) == _uncached(d, 0, "chair", shift_m=0.01)
