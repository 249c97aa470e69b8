"""The query service's replies carry relevancy, match, centroid, nearby regions and relations
(issue 17): handlers called directly (no bus), then one round trip through a real Zenoh session
with the client and the wire codec (hash text encoder; the dictionary and region summaries of a
small room are given to the service, so no semantic or geometry service runs).

The room (z up): a floor, a table, a cup on the table, one chair next to the table and one far
from it (the far one is the better "chair" by cosine).

Bad input tried: a summary reply whose centroid count differs from its keys (refused by the
schema), a query of a word that names nothing in the room (answered, no hit a match)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from pydantic import ValidationError

from openfusion.bus import open_session
from openfusion.client import OpenFusionClient
from openfusion.encoders import make_text_encoder
from openfusion.mapping import RegionDictionary
from openfusion.mapping.relevancy import calibration_for
from openfusion.services.query.region_hits import RegionSummaries
from openfusion.services.query.service import QueryConfig, QueryService
from openfusion.testing.bus import ServiceThread, free_port, loopback_config, unique_map_id, wait_for_services
from openfusion.wire.codec import decode, encode
from openfusion.wire.schemas import QueryReply, RegionSummaryReply, TextQuery, TextQueryBatch

pytestmark = pytest.mark.timeout(120)

TEXT = make_text_encoder("hash")
#: key -> (label, embedded text, box lo, box hi)
ROOM = {
    0: ("floor", "floor", (0.0, 0.0, -0.02), (6.0, 5.0, 0.02)),
    1: ("chair", "chair", (0.3, 4.0, 0.0), (0.8, 4.5, 0.9)),  # far from the table
    2: ("table", "table", (2.0, 2.0, 0.0), (3.2, 2.8, 0.75)),
    3: ("chair", "wooden chair", (3.4, 2.1, 0.0), (3.9, 2.6, 0.9)),  # next to the table
    4: ("cup", "cup", (2.4, 2.3, 0.76), (2.5, 2.4, 0.86)),
}


def _summaries(*, centroids: bool = True) -> RegionSummaries:
    keys = np.array(sorted(ROOM), np.int32)
    lo = np.array([ROOM[k][2] for k in keys], np.float32)
    hi = np.array([ROOM[k][3] for k in keys], np.float32)
    reply = RegionSummaryReply(map_version=1, key_horizon=len(keys), keys=keys, bbox_min=lo, bbox_max=hi,
                               num_points=np.full(len(keys), 400, np.int64),
                               centroid=(lo + hi) / 2 + 0.01 if centroids else None)
    return RegionSummaries(reply, fetched_at=time.monotonic())


def _service(config: QueryConfig | None = None, *, centroids: bool = True) -> QueryService:
    service = QueryService(config or QueryConfig(map_id="unit"), text_encoder=make_text_encoder("hash"))
    d = RegionDictionary(TEXT.embedding_space, TEXT.dim)
    for key in sorted(ROOM):
        assert d.add(TEXT.encode([ROOM[key][1]])[0], label=ROOM[key][0]) == key
    service.replica.apply_snapshot(d.snapshot())
    service.summaries = _summaries(centroids=centroids)
    return service


def test_every_hit_carries_relevancy_match_centroid_and_nearby_regions() -> None:
    service = _service()
    reply = service.handle_text(TextQuery(text="table", top_k=3))
    threshold = calibration_for(TEXT.embedding_space).threshold
    assert reply.match_threshold == threshold and reply.relation is None and reply.matched
    best = reply.regions[0]
    assert (best.key, best.match) == (2, True) and best.relevancy == pytest.approx(1.0, abs=0.05)
    assert all(h.relevancy is not None and (h.relevancy >= threshold) == h.match for h in reply.regions)
    np.testing.assert_allclose(best.centroid, (np.array(ROOM[2][2]) + ROOM[2][3]) / 2 + 0.01, atol=1e-6)
    near = {(n.key, n.label, n.relation) for n in best.nearby}
    assert (0, "floor", "on") in near and (4, "cup", "under") in near and len(best.nearby) <= 3
    # a geometry that sends no centroids: the box centre
    plain = _service(centroids=False).handle_text(TextQuery(text="table", top_k=1)).regions[0]
    np.testing.assert_allclose(plain.centroid, (np.array(ROOM[2][2]) + ROOM[2][3]) / 2, atol=1e-6)
    with pytest.raises(ValidationError, match="centroid"):
        RegionSummaryReply(map_version=1, key_horizon=1, keys=np.array([0], np.int32),
                           bbox_min=np.zeros((1, 3), np.float32), bbox_max=np.ones((1, 3), np.float32),
                           num_points=np.array([5]), centroid=np.zeros((2, 3), np.float32))


def test_a_word_that_names_nothing_has_no_match_and_a_relation_query_ranks_by_the_relation() -> None:
    service = _service()
    zebra = service.handle_text(TextQuery(text="zebra", top_k=5))
    assert zebra.regions and not zebra.matched and all(h.match is False for h in zebra.regions)
    chair = service.handle_text(TextQuery(text="chair", top_k=2))
    assert chair.regions[0].key == 1  # the far chair is the better "chair" by cosine
    reply = service.handle_text(TextQuery(text="the chair next to the table", top_k=2))
    assert [h.key for h in reply.regions] == [3, 1]
    first = reply.regions[0]
    assert (first.relation.key, first.relation.label, first.relation.relation) == (2, "table", "next to")
    assert reply.regions[1].relation is None
    info = reply.relation
    assert (info.target, info.relation, info.anchor, info.anchor_keys) == ("chair", "next to", "table", [2])
    cup = service.handle_text(TextQuery(text="a cup on the table", top_k=1)).regions[0]
    assert cup.key == 4 and cup.relation.relation == "on" and cup.match
    # a batch answers each text as one text would, the relation query included
    batch = service.handle_text_batch(TextQueryBatch(texts=["zebra", "the chair next to the table"], top_k=2))
    assert [h.key for h in batch.replies[1].regions] == [3, 1] and not batch.replies[0].matched
    # the new fields survive the wire codec
    back = decode(encode(reply), expected=QueryReply)
    assert back.regions[0].relation == first.relation and back.regions[0].nearby == first.nearby
    assert back.regions[0].relevancy == first.relevancy and back.relation == reply.relation


def test_the_client_gets_the_new_fields_over_the_bus() -> None:
    map_id = unique_map_id("relevancy")
    port = free_port()
    base = loopback_config(map_id, listen=[port]).model_dump()
    config = QueryConfig.model_validate({**base, "query": {"text_encoder": "hash", "summary_max_age_s": 3600,
                                                            "summary_refresh_s": 3600}})
    with ServiceThread(_service(config), config, "query"):
        client = OpenFusionClient(open_session(loopback_config(map_id, connect=[port])), config.keys, timeout_s=20.0,
                                  owns_session=True)
        with client:
            wait_for_services(client.session, map_id, ["query"])
            reply = client.query_text("the chair next to the table", top_k=2)
            assert [h.key for h in reply.regions] == [3, 1] and reply.regions[0].relation.key == 2
            assert reply.regions[0].match and reply.regions[0].centroid is not None and reply.regions[0].nearby
            zebra, chair = client.query_texts(["zebra", "chair"], top_k=3)
            assert not zebra.matched and chair.matched
