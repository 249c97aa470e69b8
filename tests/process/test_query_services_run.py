"""``openfusion run --query-services 2``: two query service processes on the run's map; health
lists both, a client's queries are answered by both, one is killed with SIGKILL mid-run and the
queries keep being answered (by the other; supervision restarts the killed one), and the run
completes.

Waiting is on events: the run's health is read over the bus (the endpoint its services were
started with); the kill happens once both query services have answered."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from supervision_support import pid_of, run_endpoint

from openfusion.bus import QueryError
from openfusion.client import OpenFusionClient
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.testing.bus import processes_mentioning, scaled, subprocess_env, unique_map_id, wait_until
from openfusion.wire.counters import QueryCounter

# slow: five service processes load the text model (about a minute on 2 cores); the same logic runs
# in the default suite in tests/bus/test_query_services.py (two query services in one process).
pytestmark = [pytest.mark.timeout(400), pytest.mark.slow]

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())


def test_two_query_services_one_killed_mid_run(tmp_path: Path) -> None:
    out, map_id = tmp_path / "out", unique_map_id("queries")
    err = (tmp_path / "stderr.txt").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "openfusion.app.cli", "run", "--out", str(out), "--map", map_id, "--source",
         "synthetic:seed=1,width=160,height=120", "--frames", "120", "--rate-hz", "5", "--query-services", "2",
         "--quiet", "--query", "chair"],
        stdout=subprocess.DEVNULL, stderr=err, cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"))
    client = None
    try:
        def endpoint() -> str | None:
            assert proc.poll() is None, (tmp_path / "stderr.txt").read_text()[-3000:]
            return run_endpoint(map_id)

        client = OpenFusionClient.from_config(ServiceConfig(map_id=map_id, zenoh=ZenohSettings(
            mode="client", connect=[wait_until(endpoint, timeout_s=120)], multicast_scouting=False)), timeout_s=30.0)

        def answered(name: str) -> float:
            assert proc.poll() is None, (tmp_path / "stderr.txt").read_text()[-3000:]
            stats = client.health(timeout_s=1.0).get(name)
            return stats.counter(QueryCounter.QUERIES) if stats is not None else -1.0

        wait_until(lambda: answered("query") >= 0 and answered("query-2") >= 0, timeout_s=240, interval_s=0.5)
        def both_answered() -> bool:
            try:
                client.query_text("chair")
            except QueryError as exc:  # no dictionary yet (the semantic service has not published one)
                assert exc.code == "no_map", exc
                return False
            return answered("query") >= 1 and answered("query-2") >= 1

        wait_until(both_answered, timeout_s=120, interval_s=0.2)
        victim = pid_of("query", "--instance", "2", "--map", map_id)
        assert victim is not None
        os.kill(victim, signal.SIGKILL)
        # every one answered (by the other, or the restarted one once it is back), none lost
        for text in ("chair", "table", "lamp", "sofa", "chair", "table"):
            assert client.query_text(text).query == text
        assert proc.wait(scaled(300)) == 0, (tmp_path / "stderr.txt").read_text()[-3000:]
    finally:
        if client is not None:
            client.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
        err.close()
    summary = json.loads((out / "run.json").read_text())
    assert summary["frames_integrated"] == 120 and summary["query_services"] == 2
    assert not processes_mentioning(map_id)
