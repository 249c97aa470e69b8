"""``openfusion run`` (the embedded default) as a user runs it, as a subprocess: all services on
loopback, the synthetic scene through the bus, the map saved, queries answered, outputs written.
The map's region for "chair" must overlap a ground-truth chair (IoU >= 0.5 on surface points).
Bad input tried: --frames 0 and a map id with a '/' (one clear line, exit 2, no traceback)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from openfusion.encoders import make_text_encoder
from openfusion.io.ply import read_ply
from openfusion.mapping import load_map, query_regions
from openfusion.sources.synthetic import SyntheticWorld
from openfusion.testing.bus import subprocess_env

#: The repository root (deploy files, docs, the README's commands).
ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())

SOURCE = "synthetic:seed=1,frames=40,width=320,height=240"


def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "openfusion.app.cli", "run", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"))


def chair_iou(map_dir: Path, *, seed: int) -> float:
    """IoU, over reconstructed surface points, between the best "chair" region and the ground-truth
    instance most of its points lie on."""
    loaded = load_map(map_dir)
    text = make_text_encoder("minilm")
    best = query_regions(loaded.dictionary, loaded.volume, text.encode(["chair"])[0], 1)[0]
    surface = loaded.volume.extract_points()
    gt = SyntheticWorld(seed).ground_truth_surface(0.02)
    dist, idx = cKDTree(gt.points).query(surface.points)
    on_gt = dist < 0.05
    inst = np.where(on_gt, gt.instance_ids[idx], 0)
    in_region = surface.keys == best.key
    target = np.bincount(inst[in_region & on_gt]).argmax()
    assert "chair" in gt.categories[int(target)]
    in_gt = inst == target
    return float((in_region & in_gt).sum() / max((in_region | in_gt).sum(), 1))


def test_embedded_run_maps_the_scene_over_the_bus_and_answers_queries(tmp_path: Path) -> None:
    out = tmp_path / "out"
    rerun_args = ["--rerun", f"save:{tmp_path / 'run.rrd'}"] if importlib.util.find_spec("rerun") else []
    result = _run("--out", str(out), "--source", SOURCE, "--frames", "40", "--rate-hz", "6", "--quiet", *rerun_args)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "run.json").read_text())
    assert summary["frames_read"] == 40 and summary["frames_integrated"] == 40
    assert summary["frames_skipped"] == {}
    assert summary["map_saved"] == str((out / "map").resolve())  # where the map went
    # The semantic service takes the latest frame only, so how many of the 40 it encodes depends on
    # the machine's speed (4 under a full load): the test asks for semantics, and the chair below.
    assert 1 <= summary["semantic_frames"] <= 40 and summary["regions"] > 5
    assert summary["rec_fps"] > 0 and summary["sem_rec_fps"] > 0
    queries = json.loads((out / "queries.json").read_text())
    chair = next(q for q in queries if q["query"] == "chair")
    assert chair["regions"][0]["label"] in ("chair", "office chair")
    mesh = read_ply(out / "mesh.ply")
    assert len(mesh.vertices["x"]) > 1000 and mesh.triangles is not None and len(mesh.triangles) > 1000
    assert chair_iou(out / "map", seed=1) >= 0.5
    if rerun_args:  # frames from the bus, the mesh and the query results went to the recording
        assert (tmp_path / "run.rrd").stat().st_size > 1_000_000
        if importlib.util.find_spec("rerun.chunk"):  # reading .rrd back needs rerun-sdk >= 0.41
            from rerun.chunk import RrdReader

            entities = set(RrdReader(str(tmp_path / "run.rrd")).store().schema().entity_paths())
            # The instance images came on their own key and were joined to their frames.
            for wanted in ("/world/camera/image", "/world/camera/instances", "/world/map/mesh"):
                assert wanted in entities, (wanted, sorted(entities))


@pytest.mark.parametrize(("args", "needle"), [(["--frames", "0"], "--frames"), (["--map", "a/b"], "a/b")])
def test_embedded_run_refuses_bad_options_with_one_line(tmp_path: Path, args: list[str], needle: str) -> None:
    result = _run("--out", str(tmp_path / "o"), *args, timeout=120)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr and needle in result.stderr


def test_in_process_mode_writes_the_same_outputs_without_a_bus(tmp_path: Path) -> None:
    out = tmp_path / "ip"
    rerun_args = ["--rerun", f"save:{tmp_path / 'run.rrd'}"] if importlib.util.find_spec("rerun") else []
    result = _run("--in-process", "--out", str(out), "--source", "synthetic:seed=1,frames=20,width=320,height=240",
                  "--frames", "20", "--quiet", *rerun_args)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "run.json").read_text())
    assert summary["mode"] == "in-process"
    # coverage selection (the default): every frame is scored, those that add something are encoded
    assert summary["select"] == "coverage" and summary["frames_integrated"] == 20
    assert summary["semantic_frames"] == summary["encoder_calls"] >= 2
    assert summary["semantic_frames"] + summary["skipped_no_gain"] == 20
    assert summary["rec_fps"] > 0 and summary["sem_rec_fps"] > 0
    assert (out / "mesh.ply").exists() and (out / "queries.json").exists()
    loaded = load_map(out / "map")
    assert len(loaded.dictionary) == summary["regions"] > 5
    if rerun_args:  # the viz extra is installed: the rerun recording was written
        assert (tmp_path / "run.rrd").stat().st_size > 100_000
