"""Joining the Zenoh network: a session from a service config, a free loopback port, and the
error a failed join raises."""

from __future__ import annotations

import socket
from typing import Any

import zenoh

from openfusion.config import ServiceConfig, zenoh_config
from openfusion.errors import OpenFusionError


class BusError(OpenFusionError):
    """The Zenoh network could not be joined or an entity could not be declared."""


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the embedded run's router, tests)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def open_session(config: ServiceConfig) -> zenoh.Session:
    """A Zenoh session joined as ``config.zenoh`` says; BusError with the endpoints when it fails."""
    conf = zenoh_config(config)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        z = config.zenoh
        raise BusError(
            f"cannot open a Zenoh session (mode={z.mode or 'peer'}, listen={z.listen or 'default'}, "
            f"connect={z.connect or 'none'}): {exc}"
        ) from None


def is_matching(status: Any) -> bool:
    """Whether a zenoh matching status (or a plain bool) says a subscriber matches."""
    return bool(getattr(status, "matching", status))
