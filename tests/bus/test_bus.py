"""Bus helpers on loopback: pub/sub with exact drop counting, bad messages kept from callbacks,
query/reply with reasons for every refusal, health and liveliness, and real service processes
(the demo service) appearing, disappearing on kill -9, and exiting 0 on SIGTERM/SIGINT."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh

from openfusion.bus import (
    Publisher,
    Queryable,
    QueryError,
    RequestError,
    ServiceRunner,
    ServiceStats,
    Subscriber,
    collect_health,
    get,
    live_services,
)
from openfusion.testing.bus import (
    loopback_config,
    wait_for_queryable,
    wait_for_subscriber,
    wait_until,
)
from openfusion.testing.demo_service import PingReply, PingRequest
from openfusion.wire.codec import decode, encode
from openfusion.wire.endpoints import CONTROL, GEOMETRY_RENDER, Endpoint
from openfusion.wire.schemas import (
    ControlReply,
    ControlRequest,
    ErrorReply,
    HealthStats,
    RenderReply,
    TextQuery,
)

pytestmark = pytest.mark.timeout(120)


def _query(i: int) -> TextQuery:
    return TextQuery(text=f"chair {i}", top_k=1 + i % 7)


# --------------------------------------------------------------------------------- pub/sub


def test_pubsub_delivers_every_message_in_order(sessions, keys) -> None:
    """A normal subscriber receives all messages, in order, decoded, with nothing counted as dropped."""
    a, b, _ = sessions
    sub = Subscriber(a, keys.key("test", "fifo"), TextQuery, queue_size=100)
    pub = Publisher(b, keys.key("test", "fifo"), congestion_control=zenoh.CongestionControl.BLOCK)
    assert pub.wait_for_subscribers(5.0)
    for i in range(50):
        pub.put(_query(i))
    got = [sub.recv(timeout_s=5.0) for _ in range(50)]
    assert [m.text for m in got] == [f"chair {i}" for i in range(50)]
    assert (pub.sent, sub.received, sub.drops, sub.errors) == (50, 50, 0, 0)
    assert sub.recv(timeout_s=0.1) is None
    sub.close()
    pub.close()


def test_latest_only_counts_drops_exactly(sessions, keys) -> None:
    """Fast producer, slow consumer, latest_only: the consumer sees the newest messages and
    published == received + drops exactly; the service stats show the same drop count."""
    a, b, _ = sessions
    stats = ServiceStats()
    seen: list[int] = []

    def slow(msg: TextQuery) -> None:
        seen.append(int(msg.text.split()[1]))
        time.sleep(0.02)  # a slow consumer: 20 ms of work per message

    sub = Subscriber(a, keys.key("test", "latest"), TextQuery, slow, latest_only=True, stats=stats)
    pub = Publisher(b, keys.key("test", "latest"), congestion_control=zenoh.CongestionControl.BLOCK)
    assert pub.wait_for_subscribers(5.0)
    n = 300
    for i in range(n):
        pub.put(_query(i))
    wait_until(lambda: sub.arrived == n, timeout_s=20)
    wait_until(lambda: sub.received + sub.drops == n, timeout_s=20)
    wait_until(lambda: stats.processed == sub.received)  # the last callback has returned
    assert sub.drops > 0, "a 20 ms consumer cannot keep up with a tight publishing loop"
    assert sub.received + sub.drops == n
    assert sub.received == len(seen) and seen == sorted(seen) and seen[-1] == n - 1  # newest kept
    assert stats.drops == sub.drops and stats.processed == len(seen)
    sub.close()
    pub.close()


def test_sequence_gaps_from_a_source_count_as_upstream_drops(sessions, keys) -> None:
    """Samples lost before reaching the subscriber (sequence gaps) are counted per source;
    a second source does not disturb the first one's count."""
    a, b, _ = sessions
    key = keys.key("test", "gaps")
    sub = Subscriber(a, key, TextQuery, queue_size=100)
    wait_for_subscriber(b, key)
    payload = encode(_query(0))
    for source, seqs in ((b"sourceAA", [0, 1, 5, 6, 9]), (b"sourceBB", [3, 4])):
        for seq in seqs:
            b.put(key, payload, attachment=source + seq.to_bytes(8, "little"))
    wait_until(lambda: sub.arrived == 7, timeout_s=5)
    assert sub.dropped_upstream == 3 + 2  # A lost 2,3,4 and 7,8; B joined late at 3: nothing
    assert sub.dropped_queue == 0
    sub.close()


def test_bad_messages_never_reach_the_callback(sessions, keys) -> None:
    """Garbage, another schema and a callback that raises are logged and counted; good messages
    before and after are delivered and the subscriber keeps running."""
    a, b, _ = sessions
    key = keys.key("test", "bad")
    stats = ServiceStats()
    got: list[str] = []
    done = threading.Event()

    def callback(msg: TextQuery) -> None:
        if msg.text == "boom":
            raise RuntimeError("callback failure")
        got.append(msg.text)
        if msg.text == "last":
            done.set()

    sub = Subscriber(a, key, TextQuery, callback, stats=stats)
    wait_for_subscriber(b, key)
    b.put(key, encode(TextQuery(text="first")))
    b.put(key, b"\x00not msgpack")
    b.put(key, encode(ControlReply(ok=True)))  # valid message, wrong schema for this key
    b.put(key, encode(TextQuery(text="boom")))
    b.put(key, encode(TextQuery(text="last")))
    assert done.wait(5.0)
    assert got == ["first", "last"]
    assert sub.errors == 3 and stats.errors == 3 and sub.received == 3  # garbage+schema+raise; 3 decoded
    sub.close()


# ------------------------------------------------------------------------------ query/reply


def _control_handler(request: ControlRequest) -> ControlReply:
    if request.action == "reset":
        raise RuntimeError("disk on fire")
    if request.action == "load" and not request.path:
        raise RequestError("missing_path", "load needs a path")
    return ControlReply(ok=True, message=f"{request.action} {request.path}")


def test_query_reply_and_every_refusal_reason(sessions, keys) -> None:
    """Valid requests are answered; undecodable ones, another schema, handler refusals and handler
    crashes come back as QueryError with the code and reason; the queryable keeps answering."""
    a, b, _ = sessions
    stats = ServiceStats()
    key = CONTROL["save"].key(keys)
    qbl = Queryable(a, key, ControlRequest, _control_handler, stats=stats)
    wait_for_queryable(b, key)
    assert get(b, key, ControlRequest(action="save", path="/x"), ControlReply).message == "save /x"

    with pytest.raises(QueryError) as info:
        get(b, key, ControlRequest(action="reset"), ControlReply)
    assert info.value.code == "handler_error" and "disk on fire" in info.value.reason

    with pytest.raises(QueryError) as info:
        get(b, key, ControlRequest(action="load"), ControlReply)
    assert (info.value.code, info.value.reason) == ("missing_path", "load needs a path")

    with pytest.raises(QueryError) as info:
        get(b, key, TextQuery(text="x"), ControlReply)
    assert info.value.code == "bad_request:unexpected_schema"

    for payload, reason in ((b"\xc1garbage", "not_msgpack"), (None, "truncated")):
        replies = list(b.get(key, payload=payload, timeout=5))
        assert len(replies) == 1 and replies[0].err is not None
        error = decode(replies[0].err.payload, expected=ErrorReply)
        assert error.code == f"bad_request:{reason}" and reason in error.reason

    with pytest.raises(QueryError) as info:  # a reply of another schema than asked for
        get(b, key, ControlRequest(action="save"), RenderReply)
    assert info.value.code == "bad_reply:unexpected_schema"

    assert get(b, key, ControlRequest(action="save", path="/y"), ControlReply).ok
    assert (qbl.answered, qbl.refused, qbl.errors) == (3, 1, 4)  # 3 ok (+bad_reply one), 1 refused
    assert stats.errors == 4 and stats.counters["refused"] == 1
    qbl.close()


def test_get_without_a_service_names_key_and_service(sessions, keys) -> None:
    """Nobody serving the key: a clear QueryError naming the key, the wait and the service."""
    _, b, _ = sessions
    with pytest.raises(QueryError) as info:
        get(b, GEOMETRY_RENDER.key(keys), ControlRequest(action="save"), ControlReply, timeout_s=0.5)
    assert info.value.code == "timeout"
    assert str(info.value).endswith(
        f"no service answered on {GEOMETRY_RENDER.key(keys)} within 0.5 s: is the geometry service running?"
    )


def test_overloaded_queryable_drops_queries_instead_of_hanging_callers(sessions, keys) -> None:
    """With a full queue, extra queries are dropped (finalized): callers get an answer or a quick
    'no service answered', never a wait for their full timeout."""
    a, b, _ = sessions
    key = keys.key("test", "slow")
    release = threading.Event()
    busy = threading.Event()

    def slow(request: ControlRequest) -> ControlReply:
        busy.set()
        release.wait(10)
        return ControlReply(ok=True)

    qbl = Queryable(a, key, ControlRequest, slow, queue_size=1)
    wait_for_queryable(b, key)
    outcomes: list[str] = []

    def ask() -> None:
        try:
            get(b, key, ControlRequest(action="save"), ControlReply, timeout_s=60)
            outcomes.append("ok")
        except QueryError as exc:
            outcomes.append(exc.code)

    threads = [threading.Thread(target=ask) for _ in range(5)]
    start = time.monotonic()
    # The first query occupies the handler before the others arrive, so exactly one more fits
    # the queue (size 1) and three are dropped, whatever the thread timing.
    threads[0].start()
    assert busy.wait(10), "the first query never reached the handler"
    for t in threads[1:]:
        t.start()
    wait_until(lambda: qbl.dropped >= 3, timeout_s=10)
    release.set()
    for t in threads:
        t.join(30)
    assert time.monotonic() - start < 30, "a dropped query made its caller wait for the 60 s timeout"
    assert sorted(outcomes) == ["ok", "ok", "timeout", "timeout", "timeout"]
    qbl.close()


def test_a_second_worker_answers_while_the_first_handler_waits(sessions, keys) -> None:
    """With ``workers=2`` a handler that waits (geometry's render waiting for a semantic update)
    holds one worker; another query is answered meanwhile. With one worker it would wait behind it
    (the caller's 5 s timeout). Bad input: no workers at all is refused at declaration."""
    a, b, _ = sessions
    key = keys.key("test", "waits")
    release, waiting = threading.Event(), threading.Event()

    def handler(request: ControlRequest) -> ControlReply:
        if request.action == "load":
            waiting.set()
            release.wait(30)
        return ControlReply(ok=True, message=request.action)

    with pytest.raises(ValueError, match="at least one worker"):
        Queryable(a, keys.key("test", "none"), ControlRequest, handler, workers=0)
    qbl = Queryable(a, key, ControlRequest, handler, workers=2)
    wait_for_queryable(b, key)
    held: list[str] = []
    slow = threading.Thread(target=lambda: held.append(get(b, key, ControlRequest(action="load", path="/m"),
                                                           ControlReply, timeout_s=60).message))
    slow.start()
    assert waiting.wait(10), "the first query never reached the handler"
    assert get(b, key, ControlRequest(action="save"), ControlReply, timeout_s=5).message == "save"
    assert not held, "the waiting handler answered before it was released"
    release.set()
    slow.join(30)
    assert held == ["load"] and qbl.answered == 2
    qbl.close()


# ------------------------------------------------------------------------ health / runner


def test_service_stats_fps_latency_and_snapshot() -> None:
    """Latency percentiles and counters end up in the HealthStats message."""
    stats = ServiceStats(window_s=60.0)
    for ms in range(1, 101):
        stats.record(ms / 1000.0)
    stats.add_drops(3)
    stats.add_error()
    stats.incr("blocks", 5)
    snap = stats.snapshot(service="geometry", map_id="lab")
    assert snap.latency_ms_p50 == pytest.approx(50.5) and snap.latency_ms_p99 == pytest.approx(99.01)
    assert (snap.drops, snap.errors, snap.counters) == (3, 1, {"blocks": 5.0})
    assert snap.fps > 0 and snap.uptime_s >= 0


def test_service_runner_health_liveliness_and_close(sessions, keys) -> None:
    """An in-process service: liveliness token visible, HealthStats published periodically and
    answered on query; after close, the token is gone and nothing answers."""
    _, b, port = sessions
    config = loopback_config(keys.map_id, connect=[port], health_period_s=0.1)
    published = Subscriber(b, keys.health("unit"), HealthStats, queue_size=100)
    runner = ServiceRunner(config, "unit").start()
    try:
        unit_ping = Endpoint(("unit", "ping"), PingRequest, PingReply, owner="unit")
        runner.queryable(unit_ping, lambda r: PingReply(text=r.text, pid=0, count=1))
        # A barrier on the runner's own link: a token declared before this queryable (a bug)
        # would be known to b by the time the queryable is.
        wait_for_queryable(b, unit_ping.key(keys))
        assert live_services(b, keys, timeout_s=1) == []  # not alive before ready()
        runner.ready()
        wait_until(lambda: live_services(b, keys, timeout_s=1) == ["unit"])
        first = published.recv(timeout_s=5)
        second = published.recv(timeout_s=5)
        assert first is not None and second is not None and second.stamp_ns > first.stamp_ns
        assert (first.service, first.map_id) == ("unit", keys.map_id)
        assert get(b, keys.key("unit", "ping"), PingRequest(text="hi"), PingReply).text == "hi"
        health = collect_health(b, keys, timeout_s=2)
        assert set(health) == {"unit"} and health["unit"].fps > 0  # the ping was recorded
    finally:
        runner.close()
    wait_until(lambda: live_services(b, keys, timeout_s=1) == [])
    with pytest.raises(QueryError, match="timeout|no service"):
        get(b, keys.key("unit", "ping"), PingRequest(text="hi"), PingReply, timeout_s=0.5)
    published.close()


# ------------------------------------------------------------------------ real processes


