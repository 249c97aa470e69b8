"""The demo service as a real process: its liveliness token disappears when it is killed (kill -9),
and it exits 0 on SIGINT/SIGTERM after undeclaring everything."""

from __future__ import annotations

import signal

import pytest

from openfusion.bus import (
    QueryError,
    get,
    live_services,
)
from openfusion.testing.bus import (
    ServiceProcess,
    loopback_args,
    wait_until,
)
from openfusion.testing.demo_service import PingReply, PingRequest
from openfusion.wire.keys import KeySpace

pytestmark = pytest.mark.timeout(120)


def _demo(keys: KeySpace, port: int) -> ServiceProcess:
    return ServiceProcess("openfusion.testing.demo_service", [*loopback_args(keys.map_id, connect=[port]), "--set", "health_period_s=0.2"])


def test_demo_service_liveliness_disappears_on_kill_9(sessions, keys) -> None:
    """The token appears when the process is up (and it answers pings); kill -9 removes it."""
    _, b, port = sessions
    with _demo(keys, port) as svc:
        wait_until(lambda: live_services(b, keys, timeout_s=1) == ["demo"], timeout_s=30)
        reply = get(b, keys.key("demo", "ping"), PingRequest(text="hello"), PingReply)
        assert reply.pid == svc.pid and reply.count == 1
        svc.kill()
        svc.wait(10)
        wait_until(lambda: live_services(b, keys, timeout_s=1) == [], timeout_s=15)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_demo_service_exits_0_on_signal_and_leaves(sessions, keys, signum: int) -> None:
    """SIGTERM / SIGINT: the service undeclares, closes and exits 0 within a few seconds; its
    liveliness is gone and its handler errors were survived before."""
    _, b, port = sessions
    with _demo(keys, port) as svc:
        wait_until(lambda: live_services(b, keys, timeout_s=1) == ["demo"], timeout_s=30)
        with pytest.raises(QueryError, match="handler_error"):
            get(b, keys.key("demo", "ping"), PingRequest(text="x", fail=True), PingReply)
        assert get(b, keys.key("demo", "ping"), PingRequest(text="still here"), PingReply).text == "still here"
        svc.signal(signum)
        rc = svc.wait(10)
        assert rc == 0, svc.output()
        assert live_services(b, keys, timeout_s=1) == []
        assert "stopped" in svc.output()
