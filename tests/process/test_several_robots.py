"""Several robots in one ``openfusion run``: one bridge per ``--source``, each robot's frames integrated
exactly once, and a SIGKILL of geometry mid-run resumes both robots' streams from the checkpoint
(each bridge replays what its robot's chain lacks; neither robot's frames disturb the other's).

Two robots walk different rooms of a two-room building (a shared corridor) with poses in one frame
(both ``fixed``: joining by registration is covered without processes in
tests/bus/test_two_robots.py, and at full size in the slow tests below). Small frames (160x120),
4 cm voxels and a 1 s checkpoint period keep the fast one within the default suite's budget.

Bad input tried: two sources naming the same robot, a robot name with a '/', several sources with
--in-process (each refused with one line, exit 2, before anything starts)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from supervision_support import OPENFUSION, ROOT, BackgroundRun

from openfusion.mapping import load_map
from openfusion.testing.bus import subprocess_env
from openfusion.wire.counters import CommonCounter, GeometryCounter

pytestmark = pytest.mark.timeout(600)

FRAMES = 24
ROOM = "synthetic:building,rooms=2,revisit=0,width=160,height=120,frames=" + str(FRAMES)


def _robots_integrated(health: dict, at_least: int) -> bool:
    geometry = health.get("geometry")
    return (geometry is not None and len(geometry.robots) == 2
            and all(r.frames_integrated >= at_least for r in geometry.robots.values()))


def test_two_robots_each_frame_once_and_both_resume_after_geometry_is_killed(tmp_path: Path) -> None:
    run = BackgroundRun(tmp_path, "--source", f"{ROOM},route=0", "--source", f"{ROOM},route=1,name=robot1",
                        "--rate-hz", "8", "--query", "chair", "--set", "supervision.checkpoint_period_s=1",
                        "--set", "geometry.voxel_size_m=0.04", "--set", "geometry.robot_frames=robot0=fixed;robot1=fixed",
                        "--restart-backoff-s", "0.2", name="robots")
    try:
        def checkpointed_and_past_it(h: dict) -> bool:
            g = h.get("geometry")
            return (g is not None and g.counter(GeometryCounter.CHECKPOINTS) >= 1 and _robots_integrated(h, 6)
                    and g.counter(GeometryCounter.FRAMES_INTEGRATED) >= g.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) + 6)

        before = run.wait_for(checkpointed_and_past_it)["geometry"]
        assert before.counter(GeometryCounter.FRAMES_INTEGRATED) < 2 * FRAMES, "playback ended before the kill"
        run.kill("geometry", restarts_before=0)
        run.wait_for(lambda h: "geometry" in h and h["geometry"].counter(CommonCounter.RESTARTS) == 1)
        summary = run.finish()
    finally:
        run.close()
    assert summary["restarts"] == {"geometry": 1, "semantic": 0, "query": 0, "bridge": 0, "bridge-robot1": 0}
    assert summary["error"] is None
    robots = summary["robots"]
    assert set(robots) == {"robot0", "robot1"}
    for name, robot in robots.items():
        assert robot["state"] == "joined", name
        assert robot["frames_published"] == robot["frames_integrated"] == FRAMES, (name, robot)
    assert summary["frames_integrated"] == 2 * FRAMES
    assert summary["frames_replayed"] >= 1  # what the crash lost of at least one robot, sent again
    assert robots["robot1"]["join_method"] == robots["robot0"]["join_method"] == "fixed"
    saved = load_map(run.out / "map")
    assert {name: entry["last_frame_id"] for name, entry in saved.meta["robots"].items()} == {
        "robot0": FRAMES - 1, "robot1": FRAMES - 1}
    assert saved.meta["frames_integrated"] == 2 * FRAMES


@pytest.mark.parametrize(("args", "says"), [
    (["--source", "synthetic", "--source", "synthetic:seed=2,name=robot0"], "robot 'robot0' has a source already"),
    (["--source", "synthetic:seed=2,name=a/b"], "robot name 'a/b' is not valid"),
    (["--source", "synthetic", "--source", "synthetic:seed=2", "--in-process"], "--in-process plays one source"),
])
def test_bad_robot_sources_are_refused_before_anything_starts(tmp_path: Path, args: list[str], says: str) -> None:
    done = subprocess.run([*OPENFUSION, "run", "--out", str(tmp_path / "out"), *args], capture_output=True,
                          text=True, cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"), timeout=120)
    assert done.returncode == 2, done.stderr
    assert says in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
