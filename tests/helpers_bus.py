"""Shared helpers for bus tests: free loopback ports, isolated configs and sessions, a runner
for service subprocesses, and polling.

Every session these helpers make is peer mode on tcp/127.0.0.1 with multicast scouting OFF,
so tests never discover other runs on the same machine; map ids are unique per call.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh

from openfusion.bus import open_session
from openfusion.config import ServiceConfig

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def unique_map_id(stem: str = "test") -> str:
    """A map id no other test (or concurrent run) uses."""
    return f"{stem}-{uuid.uuid4().hex[:10]}"


def loopback_config(
    map_id: str, *, listen: Sequence[int] = (), connect: Sequence[int] = (), **fields: Any
) -> ServiceConfig:
    """Peer config on loopback, multicast off, listening/connecting on the given ports."""
    return ServiceConfig.model_validate(
        {
            "map_id": map_id,
            "zenoh": {
                "mode": "peer",
                "listen": [endpoint(p) for p in listen],
                "connect": [endpoint(p) for p in connect],
                "multicast_scouting": False,
            },
            **fields,
        }
    )


def loopback_args(map_id: str, *, listen: Sequence[int] = (), connect: Sequence[int] = ()) -> list[str]:
    """The same as CLI options for a subprocess."""
    args = ["--map", map_id, "--mode", "peer", "--no-multicast"]
    for p in listen:
        args += ["--listen", endpoint(p)]
    for p in connect:
        args += ["--connect", endpoint(p)]
    return args


def open_pair(map_id: str) -> tuple[zenoh.Session, zenoh.Session, int]:
    """Two connected sessions (A listens, B connects) and A's port."""
    port = free_port()
    a = open_session(loopback_config(map_id, listen=[port]))
    b = open_session(loopback_config(map_id, connect=[port]))
    return a, b, port


def wait_until(predicate: Callable[[], Any], *, timeout_s: float = 10.0, interval_s: float = 0.05) -> Any:
    """Poll ``predicate`` until it returns something truthy (returned) or fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout_s} s: {getattr(predicate, '__name__', predicate)}")
        time.sleep(interval_s)


def subprocess_env(**extra: str) -> dict[str, str]:
    """The environment for a child Python: no OPENFUSION_* leaking in from the caller."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENFUSION_")}
    env.setdefault("PYTHONUNBUFFERED", "1")
    env.update(extra)
    return env


class ServiceProcess:
    """A service (``python -m MODULE ARGS``) as a child process with its output in a temp file.

    Use as a context manager; on exit the process is killed if still running. ``output()``
    returns what it printed (for assertion messages).
    """

    def __init__(self, module: str, args: Sequence[str], *, env: dict[str, str] | None = None) -> None:
        self._log = tempfile.NamedTemporaryFile(prefix="svc-", suffix=".log", delete=False)  # noqa: SIM115
        self.proc = subprocess.Popen(
            [sys.executable, "-m", module, *args],
            stdout=self._log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
            env=env or subprocess_env(),
        )

    @property
    def pid(self) -> int:
        return self.proc.pid

    def output(self) -> str:
        self._log.flush()
        return Path(self._log.name).read_text(errors="replace")

    def signal(self, signum: int) -> None:
        self.proc.send_signal(signum)

    def terminate(self) -> None:
        self.signal(signal.SIGTERM)

    def kill(self) -> None:
        self.proc.kill()

    def wait(self, timeout_s: float) -> int:
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"process {self.pid} still running after {timeout_s} s:\n{self.output()}") from None

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._log.close()
        Path(self._log.name).unlink(missing_ok=True)

    def __enter__(self) -> ServiceProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
