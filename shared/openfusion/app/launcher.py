"""Service processes of one ``openfusion run`` on this machine: start, watch, stop.

The launcher starts each service as ``python -m openfusion.app.cli service NAME`` connected to
the run's router session, with its output in ``OUT/logs/NAME.log``, and stops them with
SIGTERM (then SIGKILL after a grace period).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from openfusion.errors import OpenFusionError

logger = logging.getLogger(__name__)


class RunError(OpenFusionError):
    """The run cannot continue: a service died or did not come up (the message says which)."""


@dataclass
class ServiceProcess:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path

    def alive(self) -> bool:
        return self.proc.poll() is None

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


@dataclass
class Cluster:
    """Service processes of one embedded run, connected to a router session of this process."""

    map_id: str
    endpoint: str
    log_dir: Path
    #: The run's config file (``RunConfig``); when set, children get it and no OPENFUSION_* variables
    #: (the file already holds them, and the environment must not override the launcher's options).
    config_file: Path | None = None
    processes: dict[str, ServiceProcess] = field(default_factory=dict)

    def base_args(self) -> list[str]:
        args = ["--map", self.map_id, "--mode", "peer", "--connect", self.endpoint, "--no-multicast",
                "--listen", "tcp/127.0.0.1:0"]
        return args + (["--config", str(self.config_file)] if self.config_file is not None else [])

    def _environment(self, extra: dict[str, str] | None) -> dict[str, str]:
        env = dict(os.environ)
        if self.config_file is not None:
            env = {k: v for k, v in env.items() if not k.startswith("OPENFUSION_") or k == "OPENFUSION_DEBUG"}
        return {**env, **(extra or {})}

    def start(self, name: str, extra: Sequence[str] = (), env: dict[str, str] | None = None) -> ServiceProcess:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{name}.log"
        log = open(log_path, "ab")  # noqa: SIM115 - closed when the process ends (child keeps its fd)
        cmd = [sys.executable, "-m", "openfusion.app.cli", "service", name, *self.base_args(), *extra]
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=self._environment(env))
        log.close()
        sp = ServiceProcess(name, proc, log_path)
        self.processes[name] = sp
        return sp

    def check_alive(self) -> None:
        for sp in self.processes.values():
            if not sp.alive():
                raise RunError(f"the {sp.name} service exited with code {sp.proc.returncode}; "
                               f"last lines of {sp.log_path}:\n{sp.tail()}")

    def stop(self, name: str | None = None, *, timeout_s: float = 15.0) -> None:
        targets = [self.processes[name]] if name else list(self.processes.values())
        for sp in targets:
            if sp.alive():
                sp.proc.send_signal(signal.SIGTERM)
        for sp in targets:
            try:
                sp.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                logger.warning("%s did not stop within %.0f s; killing it", sp.name, timeout_s)
                sp.proc.kill()
                sp.proc.wait(5)


def wait_for_services(client: Any, cluster: Cluster, names: set[str], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        cluster.check_alive()
        live = set(client.live_services(timeout_s=1.0))
        if names <= live:
            return
        if time.monotonic() > deadline:
            raise RunError(f"services {sorted(names - live)} did not come up within {timeout_s:.0f} s "
                           f"(logs in {cluster.log_dir})")
        time.sleep(0.3)


