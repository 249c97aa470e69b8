"""Several robots in one ``openfusion run``: one bridge per ``--source``, each robot's frames integrated
exactly once, and a SIGKILL of geometry mid-run resumes both robots' streams from the checkpoint
(each bridge replays what its robot's chain lacks; neither robot's frames disturb the other's).

Two robots walk different rooms of a two-room building (a shared corridor) with poses in one frame
(both ``fixed``: joining by registration is covered without processes in
tests/bus/test_two_robots.py, and at full size in the slow tests below). Small frames (160x120),
4 cm voxels and a 1 s checkpoint period keep the small one short (slow all the same since CI's
time on 2 cores grew past its budget);
4 frames/s (8 s of playback per robot) leaves a loaded machine time for a checkpoint before playback
ends (at 8 frames/s, 3 s, one busy run checkpointed only after the last frame).

Bad input tried: two sources naming the same robot, a robot name with a '/', several sources with
--in-process (each refused with one line, exit 2, before anything starts)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from supervision_support import OPENFUSION, ROOT, BackgroundRun

from openfusion.mapping import load_map
from openfusion.testing.bus import subprocess_env
from openfusion.wire.counters import CommonCounter, GeometryCounter

pytestmark = pytest.mark.timeout(600)

FRAMES = 32
ROOM = "synthetic:building,rooms=2,revisit=0,width=160,height=120,frames=" + str(FRAMES)


def _robots_integrated(health: dict, at_least: int) -> bool:
    geometry = health.get("geometry")
    return (geometry is not None and len(geometry.robots) == 2
            and all(r.frames_integrated >= at_least for r in geometry.robots.values()))


@pytest.mark.slow  # ~42 s on 2 cores; two robots' frames each integrated once and both resumed after a kill
# of geometry are also the slow full-size test below; the fast suite keeps the bus tests of two
# robots (tests/bus/test_two_robots.py) and the refusals of bad robot sources here
def test_two_robots_each_frame_once_and_both_resume_after_geometry_is_killed(tmp_path: Path) -> None:
    run = BackgroundRun(tmp_path, "--source", f"{ROOM},route=0", "--source", f"{ROOM},route=1,name=robot1",
                        "--rate-hz", "4", "--query", "chair", "--set", "supervision.checkpoint_period_s=1",
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


# --------------------------------------------------------------------------- the figures (slow)
RATE_HZ = "3"  # slow enough that the semantic service fuses every frame: runs differ by what was seen
# These figures compare maps, so every frame is encoded (``semantic.select=every``): under frame
# selection (the default, ``coverage``) which frames the services choose depends on timing, and two
# robots at once landed 0.001-0.011 f-mIoU under one robot walking both routes in five runs (one
# robot: 0.836 every run), the spread of the choice, not of the robots (docs/MULTI_ROBOT.md).
SELECT = "every"


@pytest.fixture(scope="module")
def two_walks(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A two-room building; robot 0 walks room 0, robot 1 room 1, both from the corridor's start;
    the one-robot walk (room 0's walk, then room 1's) and robot 1's walk 0.3 m / 5 deg off, as
    ScanNet-layout scenes."""
    from openfusion.sources.synthetic.building import SyntheticBuilding
    from openfusion.sources.synthetic.source import BuildingSource
    from openfusion.testing.robots import offset, one_after_the_other, record_scene

    building = SyntheticBuilding(0, rooms=2)
    walk = {"width_px": 160, "height_px": 120, "revisit": 0}
    walk_a = list(BuildingSource(building, route=[0], **walk))
    walk_b = list(BuildingSource(building, route=[1], **walk))
    work = tmp_path_factory.mktemp("walks")
    return {"building": building, "walk_a": walk_a, "walk_b": walk_b,
            "one": record_scene(one_after_the_other(walk_a, walk_b), work / "scene0000_00"),
            "b_offset": record_scene(offset(walk_b), work / "scene0001_00")}


def _run(tmp_path: Path, name: str, sources: list[str], robot_frames: str, frames: int | None = None,
         kill_geometry: bool = False) -> tuple[dict, Path]:
    args = [a for spec in sources for a in ("--source", spec)]
    args += ["--rate-hz", RATE_HZ, "--query", "chair", "--set", "geometry.voxel_size_m=0.04",
             "--set", "supervision.checkpoint_period_s=2", "--set", f"semantic.select={SELECT}",
             "--restart-backoff-s", "0.2"]
    if robot_frames:
        args += ["--set", f"geometry.robot_frames={robot_frames}"]
    if frames is not None:
        args += ["--frames", str(frames)]
    run = BackgroundRun(tmp_path, *args, name=name)
    try:
        if kill_geometry:
            run.wait_for(lambda h: "geometry" in h and h["geometry"].counter(GeometryCounter.CHECKPOINTS) >= 1
                         and _robots_integrated(h, 20))
            run.kill("geometry", restarts_before=0)
        summary = run.finish()
    finally:
        run.close()
    return summary, run.out / "map"


@pytest.mark.slow
def test_two_robots_map_as_one_robot_walking_both_routes_and_resume_after_a_kill(tmp_path: Path, two_walks) -> None:
    """Issue 31's first figure: two robots at once, poses in one frame, geometry killed mid-run,
    against one robot walking both routes: surface within 1 %, f-mIoU within 0.01, regions per
    object <= 1.1, every frame of both robots integrated exactly once."""
    from openfusion.testing.robots import building_map_quality

    frames_a, frames_b = len(two_walks["walk_a"]), len(two_walks["walk_b"])
    one, one_map = _run(tmp_path, "one", [two_walks["one"]], "", frames=frames_a + frames_b)
    spec = "synthetic:building,rooms=2,revisit=0,width=160,height=120"
    two, two_map = _run(tmp_path, "two", [f"{spec},route=0", f"{spec},route=1,name=robot1"],
                        "robot0=fixed;robot1=fixed", kill_geometry=True)
    assert two["restarts"]["geometry"] == 1 and two["error"] is None
    assert {n: r["frames_integrated"] for n, r in two["robots"].items()} == {"robot0": frames_a, "robot1": frames_b}
    assert one["frames_integrated"] == two["frames_integrated"] == frames_a + frames_b
    q_one = building_map_quality(one_map, two_walks["building"])
    q_two = building_map_quality(two_map, two_walks["building"])
    assert abs(q_two["points"] / q_one["points"] - 1.0) <= 0.01, (q_one, q_two)
    assert abs(q_two["f_mIoU"] - q_one["f_mIoU"]) <= 0.01, (q_one, q_two)
    assert q_two["regions_per_object"] <= 1.1, q_two


@pytest.mark.slow
def test_a_robot_off_the_maps_frame_is_found_and_no_wall_is_fused_twice(tmp_path: Path, two_walks) -> None:
    """Issue 31's second figure: robot 1's poses 0.3 m / 5 deg off the map's frame, no guess: the
    offset is found to <= 3 cm and <= 0.5 deg, and robot 1's surface through it lies on the true
    surface as through the true transform (within 0.5 % of its points farther than two voxels)."""
    from openfusion.mapping.robot_join import pose_difference
    from openfusion.testing.robots import T_MAP_ODOM, building_map_quality, off_surface_share, offset

    spec = "synthetic:building,rooms=2,revisit=0,width=160,height=120"
    summary, map_dir = _run(tmp_path, "offset", [f"{spec},route=0", f"{two_walks['b_offset']},name=robot1"],
                            "robot0=fixed")
    robot1 = summary["robots"]["robot1"]
    assert robot1["state"] == "joined" and robot1["join_method"] == "global"
    assert robot1["frames_integrated"] == len(two_walks["walk_b"])
    found = np.asarray(robot1["T_map_odom"]).reshape(4, 4)
    metres, degrees = pose_difference(T_MAP_ODOM, found)
    assert metres <= 0.03 and degrees <= 0.5, (metres, degrees)
    walk_b = offset(two_walks["walk_b"])
    as_joined = off_surface_share(walk_b, found, two_walks["building"], 0.04)
    truth = off_surface_share(walk_b, T_MAP_ODOM, two_walks["building"], 0.04)
    assert as_joined <= truth + 0.005, (as_joined, truth)
    assert building_map_quality(map_dir, two_walks["building"])["regions_per_object"] <= 1.1
