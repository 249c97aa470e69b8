"""``openfusion run --source synthetic:building,...`` over the services, as a user runs it: the
bridge opens the building from the spec it is given, every frame of the walk is integrated, the
map is saved and a query finds the room's door. Small (one room's walk, 128x96, 12 frames)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from openfusion.testing.bus import scaled, subprocess_env, unique_map_id

pytestmark = pytest.mark.timeout(300)

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
SPEC = "synthetic:building,rooms=2,route=1,revisit=0,width=128,height=96"


@pytest.mark.slow  # about 25 s of CPU (services start, encoder load); the fast suite runs eval on a building
def test_run_maps_a_walk_through_the_building(tmp_path: Path) -> None:
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "openfusion.app.cli", "run", "--out", str(out), "--map", unique_map_id("building"),
         # A walk that looks down the corridor maps more than max_points_reply's 500,000 vertices (its
         # limit: it may not be raised): the end of the run builds that mesh from the saved map.
         "--source", SPEC, "--frames", "12", "--rate-hz", "0", "--quiet", "--query", "door"],
        capture_output=True, text=True, timeout=scaled(240), cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "run.json").read_text())
    assert summary["source"] == f"{SPEC},frames=12"  # --frames spreads 12 frames over the walk
    assert summary["frames_requested"] == summary["frames_played"] == summary["frames_integrated"] == 12
    assert summary["frames_skipped"] == {} and summary["regions"] > 5
    door = json.loads((out / "queries.json").read_text())[0]
    assert door["query"] == "door" and door["regions"][0]["label"] == "door"
    assert (out / "map").is_dir() and (out / "mesh.ply").stat().st_size > 10_000
