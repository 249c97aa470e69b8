"""``openfusion run`` in the background with its services killed on purpose (SIGKILL): the run's
endpoint and the services' pids found from ``/proc`` (the launcher starts each service with
``--map MAP_ID --connect ENDPOINT``), their health read over the bus.

Waiting is on events (a health counter, a process's pid changing), never on a fixed time."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from openfusion.bus import collect_health, open_session
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.testing.bus import subprocess_env, unique_map_id, wait_until
from openfusion.wire.counters import CommonCounter
from openfusion.wire.keys import KeySpace
from openfusion.wire.schemas import HealthStats

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
OPENFUSION = [sys.executable, "-m", "openfusion.app.cli"]


def _cmdlines() -> list[tuple[int, list[str]]]:
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            args = cmdline.read_bytes().decode(errors="replace").split("\0")
        except OSError:
            continue
        found.append((int(cmdline.parent.name), args))
    return found


def pid_of(*words: str) -> int | None:
    """The pid of a process with every one of ``words`` among its arguments (None while there is none)."""
    return next((pid for pid, args in _cmdlines() if all(w in args for w in words)), None)


def run_endpoint(map_id: str) -> str | None:
    """The endpoint of the router of the run of ``map_id``: its services are started with ``--map
    MAP_ID --connect ENDPOINT`` (None until one is)."""
    return next((args[args.index("--connect") + 1] for _pid, args in _cmdlines()
                 if map_id in args and "--connect" in args and args.index("--connect") + 1 < len(args)), None)


class BackgroundRun:
    """``openfusion run --out OUT --map <unique> ARGS`` in the background (stderr in a file)."""

    def __init__(self, tmp_path: Path, *args: str, name: str = "run", quiet: bool = True) -> None:
        self.out = tmp_path / name
        self.map_id = unique_map_id(name)
        self.err_path = tmp_path / f"{name}-stderr.txt"
        self._err = self.err_path.open("w")
        self.proc = subprocess.Popen(
            [*OPENFUSION, "run", "--out", str(self.out), "--map", self.map_id, *(["--quiet"] if quiet else []), *args],
            stdout=subprocess.PIPE, stderr=self._err, text=True, cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"))
        self.session: Any = None

    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace")

    def service_pid(self, service: str) -> int | None:
        """The pid of the run's ``service`` process now (None while there is none)."""
        for pid, args in _cmdlines():
            if self.map_id in args and "service" in args and service in args and pid != self.proc.pid:
                return pid
        return None

    def health(self) -> dict[str, HealthStats]:
        """The services' last health stats ({} until the run's services are up)."""
        if self.session is None:
            endpoint = run_endpoint(self.map_id)
            if endpoint is None:
                return {}
            self.session = open_session(ServiceConfig(map_id=self.map_id, zenoh=ZenohSettings(
                mode="client", connect=[endpoint], multicast_scouting=False)))
        return collect_health(self.session, KeySpace("openfusion", self.map_id), timeout_s=1.0)

    def wait_for(self, predicate: Any, *, timeout_s: float = 240.0) -> dict[str, HealthStats]:
        """Wait until ``predicate(health)`` holds (the run must still be going); the health then."""
        last: dict[str, HealthStats] = {}

        def check() -> dict[str, HealthStats] | None:
            assert self.proc.poll() is None, f"the run ended early:\n{self.stderr()[-3000:]}"
            health = self.health()
            last.update(health)
            return health if health and predicate(health) else None

        def describe() -> str:  # what the services said last, and what the run said: a timeout's evidence
            said = {name: {k: v for k, v in stats.counters.items() if v} for name, stats in sorted(last.items())}
            robots = {name: stats.robots for name, stats in last.items() if stats.robots}
            return f"last health {said}; robots {robots}; the run's stderr:\n{self.stderr()[-3000:]}"

        return wait_until(check, timeout_s=timeout_s, interval_s=0.2, describe=describe)

    def kill(self, service: str, *, restarts_before: int) -> None:
        """SIGKILL the service's current process once it runs as restart number ``restarts_before``
        (its health says so), and wait until it is gone."""
        self.wait_for(lambda h: service in h and h[service].counter(CommonCounter.RESTARTS) == restarts_before)
        pid = self.service_pid(service)
        assert pid is not None, f"no {service} process"
        os.kill(pid, signal.SIGKILL)
        wait_until(lambda: self.service_pid(service) != pid, timeout_s=60)

    def finish(self, timeout_s: float = 600.0, *, returncode: int = 0) -> dict[str, Any]:
        """Wait for the run to end (exit ``returncode`` asserted); its run.json."""
        stdout, _ = self.proc.communicate(timeout=timeout_s)
        assert self.proc.returncode == returncode, self.stderr()[-4000:]
        if returncode:
            return json.loads((self.out / "run.json").read_text())
        summary = json.loads((self.out / "run.json").read_text())
        assert json.loads(stdout) == summary
        return summary

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(30)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._err.close()
