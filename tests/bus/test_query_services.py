"""Several query services on one map (services/query/instances.py): every request is answered
exactly once (one Zenoh reply on the shared key, one service computed it), the client spreads
its requests over both, and when one is closed mid-run, requests keep being answered by the other. In this process: a router, a
stand-in semantic (dictionary) and geometry (region summaries) queryable, two QueryServices on
real ServiceRunners, hash text encoder (no model), 6 concurrent client threads."""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Iterator

import numpy as np
import pytest

from openfusion.bus import Queryable, QueryError, get_all
from openfusion.bus.query import RETRY_UNANSWERED_S
from openfusion.client import OpenFusionClient
from openfusion.encoders import make_text_encoder
from openfusion.mapping import RegionDictionary
from openfusion.services.query.service import DEFINITION, QueryConfig, QuerySection, QueryService
from openfusion.testing.bus import LoopbackRouter, ServiceThread, wait_until
from openfusion.wire.counters import QueryCounter
from openfusion.wire.endpoints import GEOMETRY_REGIONS, QUERY_TEXT, SEMANTIC_DICTIONARY
from openfusion.wire.schemas import (
    DictionaryRequest,
    QueryReply,
    RegionSummaryReply,
    RegionSummaryRequest,
    TextQuery,
)

pytestmark = pytest.mark.timeout(120)

TEXT = make_text_encoder("hash")
NAMES = ["chair", "table", "sofa", "lamp", "window", "door", "bed", "plant"]
N_REGIONS = 200
CLIENTS = 6


def _dictionary() -> RegionDictionary:
    d = RegionDictionary(TEXT.embedding_space, TEXT.dim)
    for i in range(N_REGIONS):
        d.add(TEXT.encode([NAMES[i % len(NAMES)]])[0], label=f"{NAMES[i % len(NAMES)]} {i}")
    return d


def _summaries() -> RegionSummaryReply:
    rng = np.random.default_rng(0)
    lo = rng.uniform(0, 5, (N_REGIONS, 3)).astype(np.float32)
    hi = (lo + 0.4).astype(np.float32)
    return RegionSummaryReply(map_version=1, key_horizon=N_REGIONS, age_s=0.0,
                              keys=np.arange(N_REGIONS, dtype=np.int32), bbox_min=lo, bbox_max=hi,
                              num_points=np.full(N_REGIONS, 100, np.int64), centroid=(lo + hi) / 2)


@pytest.fixture
def bus() -> Iterator[dict]:
    with LoopbackRouter("queries") as router:
        stand_in = router.open_client()
        keys = router.keys
        dictionary, summaries = _dictionary(), _summaries()
        qbls = [Queryable(stand_in, SEMANTIC_DICTIONARY.key(keys), DictionaryRequest, lambda _r: dictionary.snapshot()),
                Queryable(stand_in, GEOMETRY_REGIONS.key(keys), RegionSummaryRequest, lambda _r: summaries)]
        client = OpenFusionClient.from_config(router.config(), timeout_s=20.0)
        yield {"router": router, "client": client}
        client.close()
        for q in qbls:
            q.close()
        stand_in.close()


def _query_service(router: LoopbackRouter, instance: int | None) -> ServiceThread:
    config = router.config(QueryConfig, query=QuerySection(text_encoder="hash", instance=instance))
    return ServiceThread(QueryService(config, text_encoder=TEXT), config, DEFINITION.instance_name(config))


def test_two_query_services_answer_each_request_once_and_survive_one_closing(bus) -> None:
    client: OpenFusionClient = bus["client"]
    first, second = _query_service(bus["router"], None), _query_service(bus["router"], 2)
    first.__enter__()
    second.__enter__()
    try:
        wait_until(lambda: {"query", "query-2"} <= set(client.live_services(timeout_s=1.0)), timeout_s=20)
        assert {"query", "query-2"} <= set(client.health(timeout_s=2.0))  # health lists each
        key = QUERY_TEXT.key(client.keys)
        replies: Counter[int] = Counter()  # replies per request
        errors: list[str] = []
        sent = [0]
        lock = threading.Lock()
        stop = threading.Event()
        closed_one = threading.Event()

        def one_client(i: int) -> None:
            n = 0
            while not stop.is_set() and n < 400:
                text = NAMES[(i + n) % len(NAMES)]
                if n % 2:  # the client: spread over the live query services by name
                    try:
                        got: list = [client.query_text(text, top_k=3)]
                    except QueryError as exc:
                        got = [exc]
                else:  # the shared key, every Zenoh reply counted: Zenoh sends it to one service
                    got = get_all(client.session, key, TextQuery(text=text, top_k=3), QueryReply, timeout_s=10.0,
                                 retry_unanswered_s=RETRY_UNANSWERED_S)
                ok = [r for r in got if isinstance(r, QueryReply)]
                with lock:
                    sent[0] += 1
                    replies[len(got)] += 1
                    errors.extend(str(r) for r in got if isinstance(r, QueryError))
                    if ok and ok[0].regions[0].label.split()[0] != text:
                        errors.append(f"{text!r} answered with {ok[0].regions[0].label!r}")
                n += 1

        threads = [threading.Thread(target=one_client, args=(i,), daemon=True) for i in range(CLIENTS)]
        for t in threads:
            t.start()
        wait_until(lambda: sent[0] >= 60, timeout_s=60)
        # both answer (the client spreads its requests); close the busier one
        served = {s: s.counter(QueryCounter.QUERIES) for s in (first, second)}
        assert min(served.values()) > 0, f"one query service answered nothing: {served}"
        busy = max(served, key=served.get)
        idle = second if busy is first else first
        before_close = sent[0]
        busy.__exit__(None, None, None)
        closed_one.set()
        after_close = idle.counter(QueryCounter.QUERIES)
        wait_until(lambda: idle.counter(QueryCounter.QUERIES) >= after_close + 60, timeout_s=60)
        stop.set()
        for t in threads:
            t.join(30)
        assert not errors, errors[:5]
        assert set(replies) == {1}, f"replies per request: {dict(replies)} (0 = lost, 2+ = duplicated)"
        assert sent[0] > before_close + 60
        # each request computed once: the services' own counts add up to the requests sent
        total = busy.counter(QueryCounter.QUERIES) + idle.counter(QueryCounter.QUERIES)
        assert total == sent[0], (total, sent[0])
    finally:
        for s in (first, second):
            if s.runner.session is not None and not s.runner._closed:
                s.__exit__(None, None, None)
