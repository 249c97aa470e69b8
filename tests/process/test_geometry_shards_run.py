"""``openfusion run --geometry-shards 2`` against ``openfusion run`` (one geometry) on the same frames:
every frame integrated by both shards, each block of the map held by exactly one shard, the saved
map (a part per shard under OUT/map) loads as one map whose surface equals the single geometry's
(within 1 %), with the same quality (f-mIoU), and the run's queries answered.

The same logic without processes: tests/unit/test_mapping_shards.py (volumes) and
tests/bus/test_geometry_shards.py (services in one process)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from openfusion.testing.bus import subprocess_env

# slow: two runs of five or six service processes (the text model loads in each), ~2.5 minutes on 2 cores.
pytestmark = [pytest.mark.timeout(600), pytest.mark.slow]

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
SOURCE = "synthetic:seed=1,width=320,height=240"
FRAMES = 40


def _run(out: Path, *extra: str) -> dict:
    result = subprocess.run(
        [sys.executable, "-m", "openfusion.app.cli", "run", "--out", str(out), "--source", SOURCE, "--frames",
         str(FRAMES), "--quiet", "--query", "chair", "--query", "table", "--rate-hz", "2",
         "--set", "semantic.select=every", *extra],
        capture_output=True, text=True, timeout=500, cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"))
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads((out / "run.json").read_text())


def test_two_shards_map_what_one_geometry_maps(tmp_path: Path) -> None:
    from openfusion.encoders import make_text_encoder
    from openfusion.eval.saved_map import synthetic_map_quality
    from openfusion.mapping import load_map, load_map_summary

    one = _run(tmp_path / "one")
    two = _run(tmp_path / "two", "--geometry-shards", "2")
    assert one["frames_integrated"] == two["frames_integrated"] == FRAMES
    assert two["geometry_shards"] == 2
    assert set(two["shards"]) == {"geometry-0of2", "geometry-1of2"}
    for counts in two["shards"].values():
        assert counts["frames_integrated"] == FRAMES  # every frame reached and was taken by each shard
        assert counts["num_blocks"] > 0
    # The saved map: one part per shard, read back as one map.
    parts = sorted(p.name for p in (tmp_path / "two" / "map").iterdir())
    assert parts == ["shard-0of2", "shard-1of2"]
    single = load_map(tmp_path / "one" / "map")
    merged = load_map(tmp_path / "two" / "map")
    assert merged.volume.params.shard == "0/1" and merged.meta["geometry_shards"] == 2
    a, b = single.volume.extract_points(), merged.volume.extract_points()
    assert abs(len(a) - len(b)) <= 0.01 * len(a), (len(a), len(b))
    # The same surface: every merged point is on the single map's surface and the other way round.
    from scipy.spatial import cKDTree

    voxel = single.volume.params.voxel_size_m
    d_ab = cKDTree(b.points).query(a.points)[0]
    d_ba = cKDTree(a.points).query(b.points)[0]
    assert (d_ab <= voxel).mean() >= 0.99 and (d_ba <= voxel).mean() >= 0.99
    text = make_text_encoder("minilm")
    q1 = synthetic_map_quality(single.volume, single.dictionary, seed=1, text_encoder=text)
    q2 = synthetic_map_quality(merged.volume, merged.dictionary, seed=1, text_encoder=text)
    print(f"f-mIoU one geometry {q1['f_mIoU']:.4f}, two shards {q2['f_mIoU']:.4f}; points {len(a)} / {len(b)}")
    assert q1["f_mIoU"] > 0.3
    # Every frame encoded, in order; the semantic service renders a frame once every shard has taken
    # it (semantic.integrate_wait_s), so both runs label the same map (measured 0.9365 / 0.9328).
    assert abs(q1["f_mIoU"] - q2["f_mIoU"]) <= 0.01, (q1, q2)
    # Queries on the saved map (summaries merged from the parts) and during the run.
    summary = load_map_summary(tmp_path / "two" / "map")
    assert summary is not None and len(summary.regions) > 5
    assert np.all(summary.regions.num_points > 0)
    answers = json.loads((tmp_path / "two" / "queries.json").read_text())
    assert [a["query"] for a in answers] == ["chair", "table"]
    assert all(a["regions"] for a in answers)
