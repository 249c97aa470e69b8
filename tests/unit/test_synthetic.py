"""The synthetic world: determinism, realistic depth, smooth trajectory, ground truth that agrees
with the rendered instance images, and a lossless round trip through the ScanNet layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from openfusion.io.ply import read_ply_vertices
from openfusion.poses import rotation_angle_deg
from openfusion.sources import open_source
from openfusion.sources.scannet import ScanNetSource
from openfusion.sources.synthetic import (
    CATEGORIES,
    LAP_FRAMES,
    SyntheticSource,
    SyntheticWorld,
    default_intrinsics,
    write_scannet_layout,
)

W, H = 160, 120


@pytest.fixture(scope="module")
def world() -> SyntheticWorld:
    return SyntheticWorld(seed=3)


def test_same_seed_same_world_and_frames(world: SyntheticWorld) -> None:
    """Two worlds from one seed give identical rooms and bit-identical frames (noise included);
    another seed gives another room."""
    again = SyntheticWorld(seed=3)
    assert again.categories == world.categories and again.room_size_m == world.room_size_m
    a = SyntheticSource(world, num_frames=20, width_px=W, height_px=H)
    b = SyntheticSource(again, num_frames=20, width_px=W, height_px=H)
    for i in (0, 13):
        fa, fb = a.frame_at(i), b.frame_at(i)
        np.testing.assert_array_equal(fa.color, fb.color)
        np.testing.assert_array_equal(fa.depth, fb.depth)
        np.testing.assert_array_equal(fa.instance, fb.instance)
        np.testing.assert_array_equal(fa.T_world_cam, fb.T_world_cam)
    other = SyntheticWorld(seed=4)
    assert (other.room_size_m, other.categories) != (world.room_size_m, world.categories)


def test_world_is_furnished_with_many_kinds(world: SyntheticWorld) -> None:
    """About a dozen furniture kinds plus walls/floor/ceiling, all named from CATEGORIES."""
    kinds = set(world.categories.values())
    assert {"wall", "floor", "ceiling", "door"} <= kinds
    assert len(kinds - {"wall", "floor", "ceiling"}) >= 10
    assert kinds <= set(CATEGORIES)
    assert sorted(world.categories) == list(range(1, len(world.categories) + 1))


def test_frames_are_valid_rgbd_with_instances(world: SyntheticWorld) -> None:
    """Every frame validates, sees several instances, has a few holes but mostly valid depth
    in a room-sized range, and lists exactly the categories of the instances it shows."""
    src = SyntheticSource(world, num_frames=40, width_px=W, height_px=H, stride=10)
    frames = list(src)
    assert len(frames) == 4 and src.stats.skipped == {}
    for f in frames:
        f.validate()
        assert f.depth.dtype == np.uint16 and f.depth_scale == 1000.0
        holes = float((f.depth == 0).mean())
        assert 0.001 < holes < 0.15
        z = f.depth_m()[f.depth > 0]
        assert 0.25 <= z.min() and z.max() < 8.0
        ids = set(np.unique(f.instance).tolist()) - {0}
        assert len(ids) >= 3
        assert set(f.instance_categories) == ids
        assert all(f.instance_categories[i] == world.categories[i] for i in ids)
        assert f.color.std() > 10  # shaded and textured, not flat


def test_depth_noise_follows_the_kinect_model(world: SyntheticWorld) -> None:
    """Noisy minus clean depth between 1.8 and 2.2 m has the model's sigma
    0.0012 + 0.0019 (z - 0.4)^2 (about 6 mm) within 25 %; grazing pixels are holes."""
    noisy = SyntheticSource(world, num_frames=8, width_px=320, height_px=240)
    clean = SyntheticSource(world, num_frames=8, width_px=320, height_px=240, depth_noise=False)
    diffs = []
    for i in range(0, 8, 2):
        a, b = noisy.frame_at(i).depth_m(), clean.frame_at(i).depth_m()
        m = (a > 0) & (b > 1.8) & (b < 2.2)
        diffs.append((a - b)[m])
    d = np.concatenate(diffs)
    assert d.size > 2000
    sigma_model = 0.0012 + 0.0019 * (2.0 - 0.4) ** 2
    assert abs(d.std() - sigma_model) < 0.25 * sigma_model
    assert abs(d.mean()) < 0.002
    view = world.render(noisy.poses[0], noisy.intrinsics)
    grazing = (view.view_cos < 0.1) & (view.depth_m > 0.3)
    assert grazing.any()
    assert (noisy.frame_at(0).depth[grazing] == 0).all()


def test_trajectory_is_smooth_and_inside_the_room(world: SyntheticWorld) -> None:
    """Consecutive poses move < 5 cm and turn < 3 degrees; the camera stays inside the room."""
    poses = world.camera_path(240)
    Wm, Dm, Hm = world.room_size_m
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    turns = [rotation_angle_deg(poses[i, :3, :3], poses[i + 1, :3, :3]) for i in range(len(poses) - 1)]
    assert steps.max() < 0.05 and max(turns) < 3.0
    assert steps.min() > 0.001  # it does move
    p = poses[:, :3, 3]
    assert (p[:, 0] > 0.5).all() and (p[:, 0] < Wm - 0.5).all() and (p[:, 1] > 0.5).all() and (p[:, 1] < Dm - 0.5).all()
    assert (p[:, 2] > 1.2).all() and (p[:, 2] < Hm - 0.5).all()
    for T in poses[::30]:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)


def test_instance_images_agree_with_ground_truth_surface(world: SyntheticWorld) -> None:
    """Back-projected labelled pixels land next to ground-truth points of the same instance,
    and the surface's categories are the world's."""
    gt = world.ground_truth_surface(0.05)
    assert gt.points.dtype == np.float32 and gt.instance_ids.dtype == np.int32
    assert (gt.instance_ids > 0).all()
    assert all(gt.categories[i] == world.categories[i] for i in gt.categories)
    tree = cKDTree(gt.points)
    K = default_intrinsics(W, H)
    src = SyntheticSource(world, num_frames=60, width_px=W, height_px=H, depth_noise=False, stride=20)
    for f in src:
        v, u = np.nonzero((f.instance > 0) & (f.depth > 0))
        z = f.depth_m()[v, u]
        cam = np.stack([(u - K.cx) / K.fx * z, (v - K.cy) / K.fy * z, z], axis=1)
        pts = cam @ f.T_world_cam[:3, :3].T + f.T_world_cam[:3, 3]
        dist, idx = tree.query(pts)
        assert np.median(dist) < 0.035
        agree = gt.instance_ids[idx] == f.instance[v, u]
        assert agree.mean() > 0.95, f"frame {f.frame_id}: {agree.mean():.3f} of pixels match the GT instance"


def test_visible_only_drops_hidden_surfaces(world: SyntheticWorld) -> None:
    """Hidden faces (box bottoms on the floor, floor under furniture) are not ground truth."""
    all_pts = world.ground_truth_surface(0.05, visible_only=False)
    vis = world.ground_truth_surface(0.05)
    assert 0.4 * len(all_pts.points) < len(vis.points) < len(all_pts.points)
    floor_id = next(i for i, c in world.categories.items() if c == "floor")
    # nothing visible lies just above the floor facing down: sample points within 2 mm of z=0
    # that belong to non-floor objects are bottoms resting on the floor
    low = (vis.points[:, 2] < 0.002) & (vis.instance_ids != floor_id)
    assert low.sum() < 0.001 * len(vis.points)


@pytest.mark.parametrize("color_format", ["png", "jpg"])
def test_scannet_layout_round_trip(world: SyntheticWorld, tmp_path: Path, color_format: str) -> None:
    """The ScanNet reader reads the written scene back: depth, pose, intrinsics, instances and
    categories exactly; color exactly for PNG and within JPEG loss (quality 100: mean absolute
    error < 1 level, max < 24) for JPG. The GT surface PLY has NYU40 labels."""
    src = SyntheticSource(world, num_frames=4, width_px=W, height_px=H)
    out = tmp_path / "synth0003_00"
    written = write_scannet_layout(src, out, color_format=color_format, ground_truth_spacing_m=0.1)
    assert written.num_frames == 4 and written.ground_truth_points > 0
    back = ScanNetSource(out)
    pairs = list(zip(src, back, strict=True))
    assert len(pairs) == 4 and back.stats.skipped == {}
    for a, b in pairs:
        assert a.frame_id == b.frame_id and a.intrinsics == b.intrinsics
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
        np.testing.assert_array_equal(a.instance, b.instance)
        assert a.instance_categories == b.instance_categories
        if color_format == "png":
            np.testing.assert_array_equal(a.color, b.color)
        else:
            err = np.abs(a.color.astype(int) - b.color.astype(int))
            assert err.mean() < 1.0 and err.max() < 24
    verts = read_ply_vertices(out / "synth0003_00_vh_clean_2.labels.ply")
    assert {"x", "y", "z", "label", "instance"} <= set(verts)
    chair_ids = {i for i, c in world.categories.items() if c == "chair"}
    labels_of_chairs = set(verts["label"][np.isin(verts["instance"], list(chair_ids))].tolist())
    assert labels_of_chairs <= {5}  # NYU40 'chair'


def test_write_refuses_existing_folder_and_leaves_nothing_half_written(world: SyntheticWorld, tmp_path: Path) -> None:
    """Bad input: an existing output folder (refused) and a source that fails mid-way (no
    partial scene left behind)."""
    out = tmp_path / "scene"
    out.mkdir()
    src = SyntheticSource(world, num_frames=2, width_px=W, height_px=H)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_scannet_layout(src, out)

    class Exploding(SyntheticSource):
        def _load(self, index: int):  # noqa: ANN202 - test double
            if index == 1:
                raise RuntimeError("disk on fire")
            return super()._load(index)

    bad = Exploding(world, num_frames=3, width_px=W, height_px=H)
    with pytest.raises(RuntimeError, match="disk on fire"):
        write_scannet_layout(bad, tmp_path / "never", ground_truth_spacing_m=None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_synthetic_spec_options() -> None:
    """open_source('synthetic:...') parses options; unknown or malformed ones are refused by name."""
    src = open_source("synthetic:seed=5,frames=7,width=32,height=24,noise=0")
    assert len(src) == 7 and src.intrinsics.width_px == 32 and src.world.seed == 5 and not src.depth_noise
    with pytest.raises(ValueError, match="unknown synthetic option 'colour'"):
        open_source("synthetic:colour=red")
    with pytest.raises(ValueError, match="frames='many'"):
        open_source("synthetic:frames=many")
    with pytest.raises(ValueError, match="key=value"):
        open_source("synthetic:seed")


def test_a_source_longer_than_a_lap_walks_the_lap_again(world: SyntheticWorld) -> None:
    """More frames than a lap: every frame is played, the poses of lap 2 are lap 1's exactly, frame
    ids and stamps keep increasing, and the depth noise is drawn anew. Without ``lap=`` a lap is
    LAP_FRAMES frames whatever the length (it used to stretch one lap over a long source)."""
    src = open_source("synthetic:seed=3,frames=10,lap=4,width=32,height=24")
    frames = list(src)
    assert len(frames) == len(src) == 10 and src.lap == 4
    assert [f.frame_id for f in frames] == list(range(10))
    stamps = [f.stamp_ns for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))
    for i in range(4, 10):
        np.testing.assert_array_equal(frames[i].T_world_cam, frames[i - 4].T_world_cam)
    assert not np.array_equal(frames[1].T_world_cam, frames[0].T_world_cam)
    assert not np.array_equal(frames[5].depth, frames[1].depth)  # same pose, fresh noise
    long = world.camera_path(LAP_FRAMES + 3)
    np.testing.assert_array_equal(long[LAP_FRAMES:], long[:3])
    np.testing.assert_array_equal(world.camera_path(LAP_FRAMES)[:50], world.camera_path(50))


def test_stop_holds_the_camera_still_at_the_start_and_each_quarter_of_the_lap() -> None:
    frames = list(open_source("synthetic:frames=12,width=80,height=60,lap=8,stop=2"))
    xs = [round(float(f.T_world_cam[0, 3]), 6) for f in frames]
    # poses 0, 2, 4 (the start and the first two quarters) held for 2 more frames each
    assert xs[0] == xs[1] == xs[2] != xs[3] != xs[4] == xs[5] == xs[6] != xs[7]
    assert [f.frame_id for f in frames] == list(range(12))
    assert not np.array_equal(frames[0].depth, frames[1].depth)  # a fresh draw of depth noise each frame
    plain = list(open_source("synthetic:frames=4,width=80,height=60,lap=8"))
    assert np.array_equal(frames[3].T_world_cam, plain[1].T_world_cam)
    with pytest.raises(ValueError, match="stop"):
        open_source("synthetic:stop=-1")
