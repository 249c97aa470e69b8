"""The plain deploy configs on real Zenoh sessions: a router relays between clients, dev peers find
each other through the hub without multicast."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh
from compose_support import load_compose

from openfusion.bus import free_loopback_port
from openfusion.testing.bus import wait_until

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())


ZENOH_DIR = ROOT / "deploy" / "zenoh"


pytestmark = pytest.mark.timeout(60)


@contextmanager
def _session(config: zenoh.Config) -> Iterator[zenoh.Session]:
    session = zenoh.open(config)
    try:
        yield session
    finally:
        session.close()


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return load_compose(ROOT / "docker-compose.yml")


def test_plain_router_and_clients_route_between_clients() -> None:
    """Two sessions from client.json5 talk through one from router.json5 (endpoints moved to a
    free loopback port). Bad input guarded: a router config that cannot open, clients that need
    multicast to find it."""
    port = free_loopback_port()
    router_cfg = zenoh.Config.from_file(ZENOH_DIR / "router.json5")
    router_cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))

    def client_cfg() -> zenoh.Config:
        config = zenoh.Config.from_file(ZENOH_DIR / "client.json5")
        config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        return config

    received: list[bytes] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received.append(sample.payload.to_bytes())

    with ExitStack() as stack:
        stack.enter_context(_session(router_cfg))
        subscriber_session = stack.enter_context(_session(client_cfg()))
        publisher_session = stack.enter_context(_session(client_cfg()))
        subscriber_session.declare_subscriber("openfusion/demo/sensor/rgbd", on_sample)
        publisher = publisher_session.declare_publisher("openfusion/demo/sensor/rgbd")
        wait_until(lambda: publisher.matching_status.matching)
        publisher.put(b"frame")
        wait_until(lambda: received == [b"frame"])


def test_dev_peers_find_each_other_through_the_hub_without_multicast() -> None:
    """Three dev.json5 peers: a hub listening on the port the others connect to, and two peers
    that only know the hub. A put from one peer reaches the other (gossip over the hub link,
    then a direct loopback link). Bad input guarded: a dev config that needs multicast."""
    port = free_loopback_port()

    def dev_cfg(*, hub: bool) -> zenoh.Config:
        config = zenoh.Config.from_file(ZENOH_DIR / "dev.json5")
        if hub:
            config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
            config.insert_json5("connect/endpoints", "[]")
        else:
            config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        return config

    received: list[bytes] = []
    with ExitStack() as stack:
        stack.enter_context(_session(dev_cfg(hub=True)))
        sender = stack.enter_context(_session(dev_cfg(hub=False)))
        receiver = stack.enter_context(_session(dev_cfg(hub=False)))
        receiver.declare_subscriber(
            "openfusion/demo/sensor/rgbd", lambda sample: received.append(sample.payload.to_bytes())
        )
        publisher = sender.declare_publisher("openfusion/demo/sensor/rgbd")
        wait_until(lambda: publisher.matching_status.matching)
        publisher.put(b"frame")
        wait_until(lambda: received == [b"frame"])
        assert len(list(sender.info.peers_zid())) == 2
