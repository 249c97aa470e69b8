"""Two hosts on one machine for the process tests (test_deploy_two_host.py, test_shards_two_host.py):
a network namespace joined to this host by a veth pair, with its own address (10.231.x.0/30), so a
service started in it reaches the router by that address as another host would. Traffic stays on
this machine. The ``netns`` fixture (conftest.py) skips with the reason when namespaces cannot be created (not
root, no iproute2)."""

from __future__ import annotations

import os
import shutil
import subprocess
import uuid

from openfusion.bus import collect_health
from openfusion.client import OpenFusionClient


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
