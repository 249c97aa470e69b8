"""Several texts in one request (``query/text_batch``): the query service embeds them in one
encoder call and answers each as a one-text query would, in order; the client asks in one round
trip per 64 texts. The handler is called directly first (no bus), then through a real Zenoh
session with the query service on a ServiceRunner in this process (hash text encoder, no model;
the dictionary and region summaries are given to it, so no semantic or geometry service runs).

Bad input tried: a batch with one text over the text limit (refused naming which text), a ``top_k``
over the limit (openfusion.wire.limits: the handler is held to them for a message built without
validation, the client refuses them before sending, and a foreign client's message that carries
them is refused by the schema with the same line), another embedding space, no dictionary yet;
empty, oversize and too-long batches are refused by the schema (tests/unit/test_messages.py)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from openfusion.bus import QueryError, RequestError, call, open_session
from openfusion.client import OpenFusionClient
from openfusion.encoders import make_text_encoder
from openfusion.mapping import RegionDictionary
from openfusion.mapping.answers import texts_to_embed
from openfusion.mapping.relevancy import DEFAULT_NEGATIVES, DEFAULT_QUERY_CATEGORIES
from openfusion.services.query.region_hits import RegionSummaries
from openfusion.services.query.service import QueryConfig, QueryService
from openfusion.testing.bus import ServiceThread, free_port, loopback_config, unique_map_id, wait_for_services
from openfusion.testing.encoders import CountingTextEncoder
from openfusion.wire.counters import QueryCounter
from openfusion.wire.endpoints import QUERY_TEXT_BATCH
from openfusion.wire.limits import LimitError
from openfusion.wire.schemas import (
    PointsReply,
    QueryBatchReply,
    RegionSummaryReply,
    TextQuery,
    TextQueryBatch,
)

pytestmark = pytest.mark.timeout(120)

TEXT = make_text_encoder("hash")
NAMES = ("chair", "table", "lamp", "sofa", "plant", "bookshelf", "office chair")
#: Surface points of each region (key = index in NAMES): the lamp is a fragment below min_region_points.
POINTS = (400, 300, 2, 250, 120, 90, 380)




def _summaries() -> RegionSummaries:
    n = len(NAMES)
    lo = np.arange(n * 3, dtype=np.float32).reshape(n, 3)
    reply = RegionSummaryReply(map_version=1, key_horizon=n, keys=np.arange(n, dtype=np.int32), bbox_min=lo,
                               bbox_max=lo + 1.0, num_points=np.array(POINTS, np.int64))
    return RegionSummaries(reply, fetched_at=time.monotonic())


def _service(config: QueryConfig | None = None, *, with_map: bool = True) -> QueryService:
    config = config or QueryConfig(map_id="unit")
    service = QueryService(config, text_encoder=CountingTextEncoder())
    # relevancy's negatives and query categories, once at start
    assert service.text_encoder.calls == [[*DEFAULT_NEGATIVES, *DEFAULT_QUERY_CATEGORIES]]
    service.text_encoder.calls.clear()
    if with_map:
        dictionary = RegionDictionary(TEXT.embedding_space, TEXT.dim)
        for name in NAMES:
            dictionary.add(TEXT.encode([name])[0], label=name)
        service.replica.apply_snapshot(dictionary.snapshot())
        service.summaries = _summaries()
    return service


def _same(a, b) -> None:  # noqa: ANN001 - two QueryReplies
    assert (a.query, a.embedding_space) == (b.query, b.embedding_space)
    assert [(h.key, h.label, h.num_points) for h in a.regions] == [(h.key, h.label, h.num_points) for h in b.regions]
    for x, y in zip(a.regions, b.regions, strict=True):
        assert x.score == pytest.approx(y.score, abs=1e-6)
        np.testing.assert_array_equal(x.bbox_min, y.bbox_min)
        np.testing.assert_array_equal(x.bbox_max, y.bbox_max)


def test_a_batch_embeds_every_text_in_one_call_and_answers_each_as_one_text_would() -> None:
    """Replies in the order of the texts (a repeated text answered twice, embedded once), each
    equal to the one-text answer; the lamp fragment (2 points) is no answer in either."""
    service = _service()
    texts = ["table", "chair", "something to sit on", "lamp", "chair"]
    batch = service.handle_text_batch(TextQueryBatch(texts=texts, top_k=3))
    assert isinstance(batch, QueryBatchReply)
    assert service.text_encoder.calls == [texts[:4]]
    assert [r.query for r in batch.replies] == texts
    for text, reply in zip(texts, batch.replies, strict=True):
        _same(reply, service.handle_text(TextQuery(text=text, top_k=3)))
    assert batch.replies[0].regions[0].label == "table" and batch.replies[1].regions[0].label == "chair"
    assert all(2 not in [h.key for h in r.regions] for r in batch.replies)
    assert batch.replies[0].regions[0].num_points == 300
    np.testing.assert_array_equal(batch.replies[0].regions[0].bbox_min, [3.0, 4.0, 5.0])


def test_a_batch_with_points_asks_geometry_once_for_the_regions_of_every_text(monkeypatch) -> None:
    """One points request for the union of every text's regions; each reply has its regions'
    points (box and count from them), a region shared by two texts in both."""
    service = _service()
    asked: list[list[int] | None] = []
    rng = np.random.default_rng(3)
    keys = np.repeat(np.arange(len(NAMES), dtype=np.int32), 60)
    points = rng.random((len(keys), 3), dtype=np.float32) + keys[:, None].astype(np.float32)

    def points_of(wanted: list[int] | None, _max: int) -> PointsReply:
        asked.append(wanted)
        mine = np.isin(keys, wanted)
        return PointsReply(points=points[mine], colors=np.zeros((int(mine.sum()), 3), np.uint8), keys=keys[mine])

    monkeypatch.setattr(service, "_points_of", points_of)
    batch = service.handle_text_batch(TextQueryBatch(texts=["chair", "office chair", "sofa"], top_k=2,
                                                     with_points=True, max_points=25))
    every = sorted({h.key for r in batch.replies for h in r.regions})
    assert asked == [every]
    for reply in batch.replies:
        assert reply.regions
        for hit in reply.regions:
            assert hit.num_points == 60 and hit.points is not None and len(hit.points) == 25
            assert np.all(np.floor(hit.points) == hit.key)
    assert {0, 6} <= {h.key for h in batch.replies[0].regions} & {h.key for h in batch.replies[1].regions}


@pytest.mark.parametrize(
    ("config", "request_", "code", "reason"),
    [
        ({}, TextQueryBatch.model_construct(texts=["chair", "x" * 600]), "too_large",
         "the query text 2 of 2 has 600 characters; the limit is 512"),
        ({}, TextQueryBatch.model_construct(texts=["chair", "lamp"], top_k=101), "too_large",
         "top_k must be from 1 to 100, got 101"),
        ({}, TextQueryBatch(texts=["chair"], embedding_space="clip-vit-b-32"), "embedding_space_mismatch",
         "'clip-vit-b-32' but the map is in 'hash-trigram-"),
    ],
)
def test_a_bad_batch_is_refused_whole_before_anything_is_embedded(config, request_, code, reason) -> None:  # noqa: ANN001
    service = _service(QueryConfig(map_id="unit", query=config))
    with pytest.raises(RequestError) as info:
        service.handle_text_batch(request_)
    assert info.value.code == code and reason in info.value.reason
    assert service.text_encoder.calls == []


def test_a_batch_without_a_map_is_refused() -> None:
    with pytest.raises(RequestError) as info:
        _service(with_map=False).handle_text_batch(TextQueryBatch(texts=["chair", "table"]))
    assert info.value.code == "no_map"


def test_the_client_asks_several_texts_in_one_round_trip_per_64() -> None:
    """Over a real Zenoh session: query_texts gives what query_text gives for each text, one
    encoder call per 64 texts, ``queries`` counts every text; a refusal comes back as a QueryError."""
    map_id = unique_map_id("batch")
    port = free_port()
    base = loopback_config(map_id, listen=[port]).model_dump()
    # no text cache: every request's texts reach the encoder (what is asserted is how they are batched)
    config = QueryConfig.model_validate({**base, "query": {"text_encoder": "hash", "summary_max_age_s": 3600,
                                                            "summary_refresh_s": 3600, "text_cache_size": 0}})
    with ServiceThread(_service(config), config, "query") as query:
        client = OpenFusionClient(open_session(loopback_config(map_id, connect=[port])), config.keys, timeout_s=20.0,
                                  owns_session=True)
        with client:
            wait_for_services(client.session, map_id, ["query"])
            encoder = query.app.text_encoder
            texts = ["lamp", "chair", "table"]
            replies = client.query_texts(texts, top_k=2)
            assert encoder.calls == [texts]
            for text, reply in zip(texts, replies, strict=True):
                _same(reply, client.query_text(text, top_k=2))
            assert query.counter(QueryCounter.QUERIES) == 6
            many = [NAMES[i % len(NAMES)] for i in range(70)]
            encoder.calls.clear()
            replies = client.query_texts(many, top_k=1)
            # one encoder call per request of 64, each text embedded once (with the head words the
            # relevancy's head rule needs: "office chair" brings "chair")
            assert encoder.calls == [texts_to_embed(many[:64]), texts_to_embed(many[64:])]
            assert encoder.calls[1] == ["table", "lamp", "sofa", "plant", "bookshelf", "office chair", "chair"]
            assert [r.query for r in replies] == many
            assert all(r.regions[0].label == n for n, r in zip(many, replies, strict=True) if n != "lamp")
            assert client.query_texts([]) == []
            encoder.calls.clear()
            with pytest.raises(LimitError, match="the query text 2 of 2 has 600 characters; the limit is 512"):
                client.query_texts(["chair", "x" * 600])
            with pytest.raises(LimitError, match="top_k must be from 1 to 100, got 1000000000"):
                client.query_text("chair", top_k=1_000_000_000)
            assert encoder.calls == []  # refused before anything was sent
            # a foreign client that sends them anyway: refused by the schema, with the same line
            with pytest.raises(QueryError) as info:
                call(client.session, config.keys, QUERY_TEXT_BATCH,
                     TextQueryBatch.model_construct(texts=["chair", "x" * 600]), timeout_s=20.0)
            assert info.value.code.startswith("bad_request")
            assert "the query text 2 of 2 has 600 characters; the limit is 512" in info.value.reason
            assert info.value.key == QUERY_TEXT_BATCH.key(config.keys)
            assert encoder.calls == []
