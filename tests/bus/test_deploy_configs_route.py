"""The plain deploy configs on real Zenoh sessions: a router relays between clients, dev peers find
each other through the hub without multicast."""

from __future__ import annotations

import json
import re
import socket
import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml
import zenoh

from openfusion.testing.bus import wait_until

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())


ZENOH_DIR = ROOT / "deploy" / "zenoh"


pytestmark = pytest.mark.timeout(60)


_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:-|:\?)([^}]*))?\}")


def interpolate(value: Any, env: dict[str, str]) -> Any:
    """Compose-style ${VAR}, ${VAR:-default}, ${VAR:?error} substitution, recursively.

    Raises KeyError for ${VAR:?...} with VAR unset, like `docker compose` refusing to start.
    """
    if isinstance(value, dict):
        return {key: interpolate(item, env) for key, item in value.items()}
    if isinstance(value, list):
        return [interpolate(item, env) for item in value]
    if not isinstance(value, str):
        return value

    def substitute(match: re.Match[str]) -> str:
        name, op, arg = match.group(1), match.group(2), match.group(3)
        if env.get(name):
            return env[name]
        if op == ":-":
            return arg
        if op == ":?":
            raise KeyError(f"{name} must be set: {arg}")
        return ""

    if "$" in _VAR.sub("", value).replace("$$", ""):
        raise ValueError(f"unsupported variable syntax in {value!r}")
    return _VAR.sub(substitute, value)


def load_compose(*paths: Path, env: dict[str, str] | None = None) -> dict[str, Any]:
    """Load compose files like `docker compose -f a -f b`: later files merge into earlier ones."""
    merged: dict[str, Any] = {}
    for path in paths:
        data = interpolate(yaml.safe_load(path.read_text()), env or {})
        _merge(merged, data)
    return merged


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> None:
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            _merge(base[key], value)
        else:
            base[key] = value


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


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
    port = _free_port()
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
    port = _free_port()

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
