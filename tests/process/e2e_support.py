"""A cluster of real service processes on loopback for the end-to-end tests (multicast off):
geometry, semantic and query as processes connected to a router session of the test process, a
client, and a bridge started per playback.

Waiting is on events, never on time: :meth:`Env.play` returns once geometry integrated every
frame of the playback and, when the semantic service runs, once it fused frames of this playback,
was done with its last frame (``last_frame_handled``: fused, or skipped for a reason it counted,
e.g. a render that timed out on a busy machine) and geometry applied every update it sent
(``updates_applied >= semantic_frames``): the map has settled, so what a test reads next is what
a checkpoint would hold. (Waiting for the last frame to be *fused* hung when that one frame was
skipped: the semantic service never sees it again.)
"""

from __future__ import annotations

from pathlib import Path

from openfusion.app.launcher import Cluster, wait_for_services
from openfusion.bus import collect_health, open_session
from openfusion.bus import free_loopback_port as free_port
from openfusion.client import OpenFusionClient
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.testing.bus import subprocess_env, unique_map_id, wait_until
from openfusion.wire.counters import GeometryCounter, SemanticCounter
from openfusion.wire.schemas import HealthStats

SOURCE = "synthetic:seed=1,frames={n},width=320,height=240"
START_TIMEOUT_S = 240.0
SERVICES = ("geometry", "semantic", "query")


class Env:
    def __init__(self, tmp: Path) -> None:
        self.map_id = unique_map_id("e2e")
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.map_dir = tmp / "maps"
        self.router = open_session(ServiceConfig(map_id=self.map_id, zenoh=ZenohSettings(
            mode="router", listen=[self.endpoint], multicast_scouting=False)))
        self.cluster = Cluster(self.map_id, self.endpoint, tmp / "logs")
        self.client = OpenFusionClient.from_config(ServiceConfig(map_id=self.map_id, zenoh=ZenohSettings(
            mode="client", connect=[self.endpoint], multicast_scouting=False)), timeout_s=60.0)

    def start(self, name: str, *extra: str) -> None:
        if name == "geometry":
            extra = ("--map-dir", str(self.map_dir), "--checkpoint-period-s", "0", *extra)
        if name == "semantic" and "--select" not in extra:
            # These tests replay the same frames and count fused frames: the latest frame whenever the
            # encoder is free (coverage would skip a replay that adds nothing; tests/bus/test_semantic_selection.py)
            extra = ("--select", "latest", *extra)
        self.cluster.start(name, list(extra), env=subprocess_env(HF_HUB_OFFLINE="1"))

    def start_all(self) -> None:
        for name in SERVICES:
            self.start(name)
        self.wait_alive(*SERVICES)

    def wait_alive(self, *names: str) -> None:
        wait_for_services(self.client, self.cluster, set(names), START_TIMEOUT_S)

    def restart(self, name: str, *extra: str, kill: bool = False) -> None:
        """Stop ``name`` (SIGKILL with ``kill``, else SIGTERM), start it again, wait until it is alive."""
        process = self.cluster.processes.pop(name)
        if kill:
            process.proc.kill()
            process.proc.wait(30)
        else:
            process.proc.terminate()
            process.proc.wait(60)
        self.start(name, *extra)
        self.wait_alive(name)

    def health(self) -> dict[str, HealthStats]:
        return collect_health(self.client.session, self.client.keys, timeout_s=2.0)

    def counter(self, service: str, name: str) -> float:
        stats = self.health().get(service)
        return stats.counter(name) if stats else 0.0

    def play(self, frames: int, *extra: str, source: str = SOURCE, semantic: bool = True) -> None:
        """Run a bridge for ``frames`` frames and wait until the map settled (module docstring);
        ``semantic=False`` when the semantic service is not running."""
        integrated = self.counter("geometry", GeometryCounter.FRAMES_INTEGRATED)
        fused = self.counter("semantic", SemanticCounter.SEMANTIC_FRAMES)
        self.cluster.start("bridge", ["--source", source.format(n=frames), "--rate-hz", "0", *extra],
                           env=subprocess_env(HF_HUB_OFFLINE="1"))
        try:
            wait_until(lambda: self.counter("geometry", GeometryCounter.FRAMES_INTEGRATED) >= integrated + frames,
                       timeout_s=START_TIMEOUT_S)
        finally:
            self.cluster.stop("bridge")
            self.cluster.processes.pop("bridge")
        if not semantic:
            return

        def settled() -> bool:
            health = self.health()
            sem, geo = health.get("semantic"), health.get("geometry")
            return (sem is not None and geo is not None
                    and sem.counter(SemanticCounter.SEMANTIC_FRAMES) > fused
                    and sem.counter(SemanticCounter.LAST_FRAME_HANDLED) == frames - 1
                    and geo.counter(GeometryCounter.UPDATES_APPLIED) >= sem.counter(SemanticCounter.SEMANTIC_FRAMES))

        try:
            wait_until(settled, timeout_s=START_TIMEOUT_S, interval_s=0.2)
        except AssertionError as exc:  # say what was not met: the counters, the drops
            health = self.health()
            seen = {name: {**{k: v for k, v in stats.counters.items() if not k.startswith("encoded_by")},
                           "drops": stats.drops, "errors": stats.errors} for name, stats in health.items()}
            raise AssertionError(f"{exc}; fused before: {fused}; health: {seen}") from None

    def close(self) -> None:
        self.cluster.stop()
        self.client.close()
        self.router.close()
