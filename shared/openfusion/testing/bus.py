"""Bus doubles for tests and benches: free loopback ports, isolated configs and sessions, a
runner for service subprocesses, and waiting on events instead of sleeping.

Part of :mod:`openfusion.testing` (shipped so that benches and users' own tests can use it; no
product code imports it). Every session these helpers make is on tcp/127.0.0.1 with multicast
scouting OFF (peer mode, or a router and its clients: :class:`LoopbackRouter`), so tests never
discover other runs on the same machine; map ids are unique per call.

Waiting: tests wait for the state they need (a liveliness token, a counter, a reply), never for
a fixed time. Deadlines are generous (a busy 2-core machine is slow, not broken) and scale with
``OPENFUSION_TEST_TIMEOUT_SCALE`` (default 1).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh

from openfusion.bus import (
    Publisher,
    ServiceRunner,
    ServiceStats,
    free_loopback_port,
    live_services,
    open_session,
)
from openfusion.config import ServiceConfig

#: Multiplies every deadline of these helpers (set it > 1 on a very slow machine).
TIMEOUT_SCALE = float(os.environ.get("OPENFUSION_TEST_TIMEOUT_SCALE", "1") or 1)


def scaled(timeout_s: float) -> float:
    """``timeout_s`` times :data:`TIMEOUT_SCALE`."""
    return timeout_s * TIMEOUT_SCALE


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    return free_loopback_port()


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def unique_map_id(stem: str = "test") -> str:
    """A map id no other test (or concurrent run) uses."""
    return f"{stem}-{uuid.uuid4().hex[:10]}"


def loopback_config(
    map_id: str, *, listen: Sequence[int] = (), connect: Sequence[int] = (), model: type[ServiceConfig] = ServiceConfig,
    mode: str = "peer", **fields: Any,
) -> Any:
    """Config on loopback, multicast off, listening/connecting on the given ports: a ``model``
    (a service's config class, e.g. ``SemanticConfig``) with ``fields`` (its section:
    ``semantic={"select": "latest"}``). ``mode``: the Zenoh mode (peer; a router and its clients:
    :class:`LoopbackRouter`)."""
    return model.model_validate(
        {
            "map_id": map_id,
            "zenoh": {
                "mode": mode,
                "listen": [endpoint(p) for p in listen],
                "connect": [endpoint(p) for p in connect],
                "multicast_scouting": False,
            },
            **fields,
        }
    )


class LoopbackRouter:
    """A Zenoh router on a free loopback port, and the configs of services and clients that join it
    in client mode: a deployment's layout (every process a client of one router) inside one test
    process. ``health_period_s`` (default 0.2 s) goes into every client config, so health and
    liveliness show within a test's patience. Close it (or use ``with``) after its clients."""

    def __init__(self, stem: str = "test", *, health_period_s: float = 0.2) -> None:
        self.map_id = unique_map_id(stem)
        self.port = free_port()
        self.health_period_s = health_period_s
        self.session = open_session(loopback_config(self.map_id, listen=[self.port], mode="router"))

    def config(self, model: type[ServiceConfig] = ServiceConfig, **fields: Any) -> Any:
        """A ``model`` config of a client of this router, with ``fields`` (a service's section)."""
        return loopback_config(self.map_id, connect=[self.port], model=model, mode="client",
                               health_period_s=self.health_period_s, **fields)

    @property
    def keys(self) -> Any:
        """The map's key space (``ServiceConfig.keys``) its clients use."""
        return self.config().keys

    def open_client(self) -> zenoh.Session:
        """A session of a client of this router (the caller closes it)."""
        return open_session(self.config())

    def close(self) -> None:
        self.session.close()

    def __enter__(self) -> LoopbackRouter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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


def wait_until(predicate: Callable[[], Any], *, timeout_s: float = 60.0, interval_s: float = 0.05,
               describe: Callable[[], str] | None = None) -> Any:
    """Wait until ``predicate`` returns something truthy (returned); fail after ``timeout_s``
    (scaled), with ``describe()`` (the state waited on) in the message. The state waited for is the
    event: no test assumes a fixed time is enough."""
    deadline = time.monotonic() + scaled(timeout_s)
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(
                f"condition not met within {scaled(timeout_s):g} s: {getattr(predicate, '__name__', predicate)}"
                + (f"; {describe()}" if describe is not None else "")
            )
        time.sleep(interval_s)


def frame_publisher(session: zenoh.Session, key: str, message: type) -> Publisher:
    """A test's publisher of sensor frames, blocking as a playback bridge's is: Zenoh's default
    drops a put when its queue is full, and a burst of frames on a loaded CI box once lost one
    before any service saw it (the test then waited for a frame that never came)."""
    return Publisher(session, key, message=message, congestion_control=zenoh.CongestionControl.BLOCK)


def send_until_handled(send: Callable[[], Any], handled: Callable[[], Any], *, attempts: int = 10,
                       timeout_s: float = 10.0) -> None:
    """Call ``send()`` until ``handled()`` holds, waiting ``timeout_s`` after each try.

    A put from a session that joined a moment ago can go nowhere even once its publisher matches
    a subscriber: in peer mode the subscriber seen may be another peer's (geometry's), and the
    direct link to a peer learnt by gossip (the semantic service) comes a little later. Tests
    send a first frame with this, then count from there."""
    for _attempt in range(attempts):
        send()
        try:
            wait_until(handled, timeout_s=timeout_s)
            return
        except AssertionError:
            continue
    raise AssertionError(f"not handled after {attempts} sends: {getattr(handled, '__name__', handled)}")


def processes_mentioning(text: str) -> list[str]:
    """Command lines of the processes on this machine that contain ``text``
    (Linux ``/proc``): what a test checks to prove no process of a run outlived it."""
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            args = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue
        if any(text.encode() in a for a in args):
            found.append(b" ".join(args).decode(errors="replace"))
    return found


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


def wait_for_services(
    session: zenoh.Session, map_id: str, names: Sequence[str], *, timeout_s: float = 120.0
) -> list[str]:
    """Wait until the liveliness tokens of ``names`` on map ``map_id`` are present (a service
    declares its token only once its queryables and subscribers exist); returns the live names."""
    keys = ServiceConfig(map_id=map_id).keys

    def all_live() -> list[str] | None:
        live = live_services(session, keys, timeout_s=1.0)
        return live if set(names) <= set(live) else None

    return wait_until(all_live, timeout_s=timeout_s, interval_s=0.2)


class ServiceThread:
    """A service object (``setup(runner)``, optional ``loop(runner)``, ``close()``) run with a real
    :class:`~openfusion.bus.ServiceRunner` on a thread of this process: the service's own logic
    on a real bus, with its stats readable directly (``.stats``), no subprocess. Use as a
    context manager; on exit the loop is stopped and everything undeclared."""

    def __init__(self, app: Any, config: ServiceConfig, service: str) -> None:
        self.app = app
        self.runner = ServiceRunner(config, service)
        self._thread: threading.Thread | None = None

    @property
    def stats(self) -> ServiceStats:
        return self.runner.stats

    def counter(self, name: str) -> float:
        """One named counter of the service (names: :mod:`openfusion.wire.counters`)."""
        return float(self.runner.stats.counters.get(str(name), 0.0))

    def __enter__(self) -> ServiceThread:
        self.runner.start()
        self.app.setup(self.runner)
        self.runner.ready()
        loop = getattr(self.app, "loop", None)
        if loop is not None:
            self._thread = threading.Thread(target=loop, args=(self.runner,), name=f"svc:{self.runner.service}",
                                            daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.runner.stop()
        if self._thread is not None:
            self._thread.join(scaled(30.0))
        self.runner.close()
        self.app.close()


def wait_for_subscriber(session: zenoh.Session, key: str, *, timeout_s: float = 60.0) -> None:
    """Wait until ``session`` knows a subscriber matching ``key`` (its declaration has arrived):
    from then on, what this session puts on ``key`` reaches it."""
    publisher = session.declare_publisher(key)
    try:
        wait_until(lambda: publisher.matching_status.matching, timeout_s=timeout_s, interval_s=0.01)
    finally:
        publisher.undeclare()


def wait_for_queryable(session: zenoh.Session, key: str, *, timeout_s: float = 60.0) -> None:
    """Wait until ``session`` knows a queryable matching ``key``: from then on its queries reach it."""
    querier = session.declare_querier(key)
    try:
        wait_until(lambda: querier.matching_status.matching, timeout_s=timeout_s, interval_s=0.01)
    finally:
        querier.undeclare()
