"""Two hosts on one machine: the semantic service runs in its own network namespace (its own
address, joined to this host by a veth pair the test creates) and reaches the router by that
address. Mapping and queries work across the link; cutting the link (veth down) leaves geometry
and query serving; when the link returns the semantic service reconnects and mapping resumes.
Traffic stays on this machine: loopback plus the test's own namespace addresses (10.231.x.0/30).

Skipped with the reason when namespaces cannot be created (not root, no iproute2)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from netns_support import NetNs, TwoHosts, counter

from openfusion.app.launcher import wait_for_services
from openfusion.bus import live_services
from openfusion.testing.bus import wait_until

pytestmark = [pytest.mark.netns, pytest.mark.timeout(600)]


def test_semantic_on_a_second_host_maps_survives_a_link_cut_and_reconnects(netns: NetNs, tmp_path: Path) -> None:
    with TwoHosts(netns, "twohost", tmp_path / "logs") as hosts:
        cluster, client, env = hosts.cluster, hosts.client, hosts.env
        semantic = hosts.start_remote("semantic", [], tmp_path / "semantic-netns.log")
        cluster.start("geometry", ["--checkpoint-period-s", "0"], env=env)
        cluster.start("query", [], env=env)
        wait_for_services(client, cluster, {"geometry", "query"}, 240)
        wait_until(lambda: "semantic" in live_services(client.session, client.keys), timeout_s=240)

        def play(frames: int) -> None:
            before = counter(client, "geometry", "frames_integrated")
            cluster.start("bridge", ["--source", f"synthetic:seed=2,frames={frames},width=320,height=240",
                                     "--rate-hz", "8"], env=env)
            wait_until(lambda: counter(client, "geometry", "frames_integrated") >= before + frames, timeout_s=240)
            cluster.stop("bridge")
            cluster.processes.pop("bridge")

        # Across the link: semantic maps, the query service answers from its dictionary.
        play(16)
        wait_until(lambda: counter(client, "semantic", "semantic_frames") >= 2, timeout_s=60)
        assert client.query_text("chair", top_k=1).regions

        # Link cut: geometry keeps integrating and query keeps answering.
        netns.link(up=False)
        integrated = counter(client, "geometry", "frames_integrated")
        play(8)
        assert counter(client, "geometry", "frames_integrated") >= integrated + 8
        assert client.query_text("table", top_k=1).regions
        assert semantic.poll() is None, "the semantic service died while the link was down"
        # The cut is real: once Zenoh's lease expires the router drops the semantic session.
        wait_until(lambda: "semantic" not in live_services(client.session, client.keys), timeout_s=60)
        assert client.query_text("chair", top_k=1).regions

        # Link back: semantic reconnects (liveliness returns) and processes new frames again: it scores
        # them (coverage selection; a replay of frames it already encoded adds nothing, so it is counted
        # as no gain rather than encoded).
        netns.link(up=True)
        wait_until(lambda: "semantic" in live_services(client.session, client.keys), timeout_s=120)

        def decided() -> float:
            return counter(client, "semantic", "semantic_frames") + counter(client, "semantic", "skipped_no_gain")

        before = decided()
        deadline = time.monotonic() + 120
        while decided() <= before and time.monotonic() < deadline:
            play(6)
        assert decided() > before
