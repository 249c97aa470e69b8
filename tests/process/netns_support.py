"""Two hosts on one machine for the process tests (test_deploy_two_host.py, test_shards_two_host.py):
a network namespace joined to this host by a veth pair, with its own address (10.231.x.0/30), so a
service started in it reaches the router by that address as another host would. Traffic stays on
this machine. The ``netns`` fixture (conftest.py) skips with the reason when namespaces cannot be created (not
root, no iproute2). :class:`TwoHosts` is this host's side of such a test: the router both hosts
join, this host's services, a client, and the services started in the namespace."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path
from typing import IO

from openfusion.app.launcher import Cluster
from openfusion.bus import collect_health, open_session
from openfusion.bus import free_loopback_port as free_port
from openfusion.client import OpenFusionClient
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.testing.bus import subprocess_env, unique_map_id

#: The repository root (the working folder of the services started in the namespace).
ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


class NetNs:
    """A namespace ``name`` with address ``ns_addr`` on a veth pair to this host's ``host_addr``."""

    def __init__(self) -> None:
        tag = uuid.uuid4().hex[:6]
        self.name = f"ofz-{tag}"
        self.host_if, self.ns_if = f"ofh{tag}", f"ofn{tag}"
        octet = int(tag[:2], 16) % 250 + 1
        self.host_addr, self.ns_addr = f"10.231.{octet}.1", f"10.231.{octet}.2"

    def create(self) -> None:
        _ip("netns", "add", self.name)
        _ip("link", "add", self.host_if, "type", "veth", "peer", "name", self.ns_if)
        _ip("link", "set", self.ns_if, "netns", self.name)
        _ip("addr", "add", f"{self.host_addr}/30", "dev", self.host_if)
        _ip("link", "set", self.host_if, "up")
        for cmd in (["addr", "add", f"{self.ns_addr}/30", "dev", self.ns_if], ["link", "set", self.ns_if, "up"],
                    ["link", "set", "lo", "up"]):
            _ip("netns", "exec", self.name, "ip", *cmd)

    def link(self, up: bool) -> None:
        _ip("link", "set", self.host_if, "up" if up else "down")

    def delete(self) -> None:
        _ip("link", "del", self.host_if, check=False)
        _ip("netns", "del", self.name, check=False)


def netns_unavailable() -> str | None:
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 (`ip`) is not installed"
    probe = NetNs()
    try:
        probe.create()
    except (subprocess.CalledProcessError, OSError) as exc:
        return f"cannot create a network namespace here: {getattr(exc, 'stderr', exc)}"
    finally:
        probe.delete()
    return None


def counter(client: OpenFusionClient, service: str, name: str) -> float:
    stats = collect_health(client.session, client.keys, timeout_s=1.5).get(service)
    return float(stats.counters.get(name, 0.0)) if stats else 0.0


class TwoHosts:
    """This host's side of a two-host test: a router listening on loopback and on the veth address
    (a service in ``netns`` reaches it by that address, as another host would), the
    :class:`~openfusion.app.launcher.Cluster` of this host's services (logs under ``logs``), a
    client of the router, and the services started in the namespace (:meth:`start_remote`). Used
    as a context: everything is stopped and closed on the way out, the namespace's services first
    (SIGTERM, then SIGKILL after 20 s), then the cluster, the client and the router."""

    def __init__(self, netns: NetNs, stem: str, logs: Path) -> None:
        self.netns = netns
        self.map_id = unique_map_id(stem)
        port = free_port()
        self.local, self.remote = f"tcp/127.0.0.1:{port}", f"tcp/{netns.host_addr}:{port}"
        self.env = subprocess_env(HF_HUB_OFFLINE="1")
        self.remote_procs: list[subprocess.Popen[bytes]] = []
        self._logs: list[IO[bytes]] = []
        self.router = open_session(ServiceConfig(map_id=self.map_id, zenoh=ZenohSettings(
            mode="router", listen=[self.local, self.remote], multicast_scouting=False)))
        try:
            self.cluster = Cluster(self.map_id, self.local, logs)
            self.client = OpenFusionClient.from_config(ServiceConfig(map_id=self.map_id, zenoh=ZenohSettings(
                mode="client", connect=[self.local], multicast_scouting=False)), timeout_s=20)
        except BaseException:
            self.router.close()
            raise

    def start_remote(self, service: str, args: list[str], log: Path) -> subprocess.Popen[bytes]:
        """``openfusion service SERVICE ARGS`` in the namespace, a client of the router by its veth
        address; its output goes to ``log``."""
        out = log.open("wb")
        self._logs.append(out)
        proc = subprocess.Popen(
            ["ip", "netns", "exec", self.netns.name, sys.executable, "-m", "openfusion.app.cli", "service", service,
             "--map", self.map_id, "--mode", "client", "--connect", self.remote, "--no-multicast", *args],
            stdout=out, stderr=subprocess.STDOUT, cwd=ROOT, env=self.env)
        self.remote_procs.append(proc)
        return proc

    def close(self) -> None:
        for proc in self.remote_procs:
            proc.terminate()
        for proc in self.remote_procs:
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
        for out in self._logs:
            out.close()
        self.cluster.stop()
        self.client.close()
        self.router.close()

    def __enter__(self) -> TwoHosts:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
