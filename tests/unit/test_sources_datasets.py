"""Replica, TUM RGB-D, Redwood/Open3D and generic-folder readers on tiny fixtures written in each
real layout, with the bad inputs each format meets in practice."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from openfusion.frame import CameraIntrinsics
from openfusion.poses import matrix_to_quat, quat_to_matrix, rotation_angle_deg
from openfusion.sources import open_source
from openfusion.sources.base import SourceError
from openfusion.sources.folder import FolderSource
from openfusion.sources.redwood import RedwoodSource
from openfusion.sources.replica import REPLICA_INTRINSICS, ReplicaSource
from openfusion.sources.tum import TumSource, associate

DW, DH = 40, 30


def _pose(i: int, *, axis: int = 2) -> np.ndarray:
    a = 0.2 * i
    c, s = np.cos(a), np.sin(a)
    R = np.eye(3)
    j, k = [(1, 2), (0, 2), (0, 1)][axis]
    R[j, j], R[j, k], R[k, j], R[k, k] = c, -s, s, c
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.1 * i, 0.2, -0.05 * i]
    return T


def _depth(i: int, w: int = DW, h: int = DH) -> np.ndarray:
    return np.random.default_rng(100 + i).integers(1, 60000, size=(h, w), dtype=np.uint16)


def _color(i: int, w: int = DW, h: int = DH) -> np.ndarray:
    return np.random.default_rng(200 + i).integers(0, 255, size=(h, w, 3), dtype=np.uint8)


# ---------------------------------------------------------------------------------- Replica


@pytest.fixture
def replica(tmp_path: Path) -> Path:
    root = tmp_path / "Replica" / "room0"
    (root / "results").mkdir(parents=True)
    lines = []
    for i in range(5):
        Image.fromarray(_color(i)).save(root / "results" / f"frame{i:06d}.jpg", quality=95)
        Image.fromarray(_depth(i)).save(root / "results" / f"depth{i:06d}.png")
        lines.append(" ".join(f"{v:.12f}" for v in _pose(i).ravel()))
    lines[2] = "1 2 3"  # malformed line
    (root / "traj.txt").write_text("\n".join(lines) + "\n")
    (root / "results" / "depth000003.png").unlink()
    cam = {"camera": {"w": DW, "h": DH, "fx": 30.0, "fy": 30.0, "cx": 19.5, "cy": 14.5, "scale": 6553.5}}
    (tmp_path / "Replica" / "cam_params.json").write_text(json.dumps(cam))
    return root


def test_replica_reads_poses_intrinsics_and_counts_bad_frames(replica: Path) -> None:
    """Bad input: a malformed traj.txt line and a missing depth file; cam_params.json one folder up
    overrides the 1200x680 default."""
    src = open_source(f"replica:{replica}")
    frames = list(src)
    assert [f.frame_id for f in frames] == [0, 1, 4]
    assert src.stats.skipped == {"unreadable_pose": 1, "missing_depth": 1}
    assert src.intrinsics == CameraIntrinsics(DW, DH, 30.0, 30.0, 19.5, 14.5)
    for f in frames:
        np.testing.assert_allclose(f.T_world_cam, _pose(f.frame_id), atol=1e-10)
        np.testing.assert_array_equal(f.depth, _depth(f.frame_id))
        assert f.depth_scale == 6553.5
        f.validate()


def test_replica_default_camera_and_wrong_size_depth(replica: Path) -> None:
    """Without cam_params.json the release camera (1200x680) applies, so these 40x30 depth images
    are the wrong size: every frame is skipped and counted, none crashes."""
    (replica.parent / "cam_params.json").unlink()
    src = ReplicaSource(replica)
    assert src.intrinsics == REPLICA_INTRINSICS
    assert list(src) == []
    assert src.stats.skipped == {"unreadable_pose": 1, "missing_depth": 1, "depth_size": 3}


def test_replica_not_a_scene(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="traj.txt and results/"):
        ReplicaSource(tmp_path)


# -------------------------------------------------------------------------------------- TUM


def _tum_gt_pose(t: float) -> np.ndarray:
    """Ground-truth trajectory: constant-rate rotation about a tilted axis, linear translation."""
    axis = np.array([0.3, 1.0, 0.2])
    axis /= np.linalg.norm(axis)
    angle = 0.8 * (t - 100.0)
    q = np.append(axis * np.sin(angle / 2), np.cos(angle / 2))
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = [0.5 * (t - 100.0), 1.0, 2.0 - 0.25 * (t - 100.0)]
    return T


@pytest.fixture
def tum(tmp_path: Path) -> Path:
    root = tmp_path / "rgbd_dataset_freiburg2_xyz"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines = ["# color images", "# file: 'rgbd_dataset_freiburg2_xyz.bag'", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    t_rgb = [100.10, 100.20, 100.30, 100.40, 100.50, 103.00]
    t_depth = [100.105, 100.212, 100.345, 100.395, 100.507, 103.001]  # 3rd: 45 ms off -> no pair
    # TUM images are always 640x480 (the default intrinsics say so); smooth content keeps it fast
    ramp = np.add.outer(np.arange(480), np.arange(640))
    for k, (tr, td) in enumerate(zip(t_rgb, t_depth, strict=True)):
        color = np.stack([ramp % 256, (ramp // 4 + 40 * k) % 256, np.full_like(ramp, 9 * k)], axis=-1).astype(np.uint8)
        Image.fromarray(color).save(root / "rgb" / f"{tr:.6f}.png", compress_level=1)
        Image.fromarray((ramp * 7 + 1000 * k).astype(np.uint16)).save(root / "depth" / f"{td:.6f}.png", compress_level=1)
        rgb_lines.append(f"{tr:.6f} rgb/{tr:.6f}.png")
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    # 100 Hz poses from 100.00 to 100.45 only (100.507 and 103.0 are outside the range),
    # with a gap 100.20..100.35 (100.212 falls inside it)
    for t in np.arange(100.0, 100.455, 0.01):
        if 100.205 < t < 100.345:
            continue
        T = _tum_gt_pose(t)
        q = matrix_to_quat(T[:3, :3])
        gt.append(f"{t:.4f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)))
    gt.insert(5, "100.0500 1 2 3")  # malformed pose line
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    return root


def test_tum_association_interpolation_and_skips(tum: Path) -> None:
    """Bad input: an rgb image whose nearest depth is 45 ms away, a frame inside a 140 ms
    ground-truth gap, frames after the last pose, a malformed groundtruth line. Poses are
    interpolated at the depth timestamp to < 1 mm and < 0.05 degrees."""
    src = TumSource(tum, max_pose_gap_s=0.05)
    frames = list(src)
    assert [f.stamp_ns for f in frames] == [100_105_000_000, 100_395_000_000]
    assert src.stats.skipped == {"pose_gap": 1, "no_depth_match": 1, "outside_pose_range": 2}
    assert src.intrinsics.fx == 520.9  # freiburg2 picked from the folder name
    for f in frames:
        T_true = _tum_gt_pose(f.stamp_ns / 1e9)
        assert np.linalg.norm(f.T_world_cam[:3, 3] - T_true[:3, 3]) < 1e-3
        assert rotation_angle_deg(f.T_world_cam[:3, :3], T_true[:3, :3]) < 0.05
        assert f.depth_scale == 5000.0 and f.depth.shape == (480, 640) and f.color.shape == (480, 640, 3)
        f.validate()


def test_tum_pose_at_rgb_time_and_tolerance(tum: Path) -> None:
    """pose_at='rgb' stamps frames with the rgb time; a 50 ms tolerance pairs the 45 ms image."""
    src = TumSource(tum, pose_at="rgb", max_dt_s=0.05, max_pose_gap_s=1.0)
    stamps = [f.stamp_ns for f in src]
    assert stamps == [100_100_000_000, 100_200_000_000, 100_300_000_000, 100_400_000_000]
    with pytest.raises(ValueError, match="pose_at"):
        TumSource(tum, pose_at="color")


def test_tum_bad_list_file(tum: Path) -> None:
    """Bad input: a non-numeric timestamp names the file and line."""
    (tum / "rgb.txt").write_text("# header\nabc rgb/x.png\n")
    with pytest.raises(ValueError, match=r"rgb.txt:2"):
        TumSource(tum)


def test_associate_is_one_to_one() -> None:
    a = np.array([0.0, 0.01, 0.5])
    b = np.array([0.004, 0.2])
    assert associate(a, b, max_dt_s=0.02) == [(0, 0)]
    assert associate(a, b, max_dt_s=0.02, offset_s=0.005) == [(1, 0)]


# ---------------------------------------------------------------------------------- Redwood


@pytest.fixture
def redwood(tmp_path: Path) -> Path:
    root = tmp_path / "livingroom1"
    (root / "color").mkdir(parents=True)
    (root / "depth").mkdir()
    blocks = []
    for i in range(5):
        Image.fromarray(_color(i)).save(root / "color" / f"{i:06d}.jpg", quality=95)
        Image.fromarray(_depth(i)).save(root / "depth" / f"{i:06d}.png")
        T = _pose(i, axis=0)
        blocks.append(f"{i} {i} {i + 1}\n" + "\n".join(" ".join(f"{v:.10f}" for v in row) for row in T))
    blocks[3] = "3 3 4\n" + "\n".join(["inf 0 0 0", "0 1 0 0", "0 0 1 0", "0 0 0 1"])
    (root / "trajectory.log").write_text("\n".join(blocks) + "\n")
    K = [[33.0, 0, 19.0], [0, 34.0, 15.0], [0, 0, 1]]
    (root / "camera_intrinsic.json").write_text(
        json.dumps({"width": DW, "height": DH, "intrinsic_matrix": list(np.array(K).T.ravel())})
    )
    (root / "color" / "000001.jpg").write_bytes(b"garbage")
    return root


def test_redwood_reads_log_and_column_major_intrinsics(redwood: Path) -> None:
    """Bad input: an inf pose block and a corrupt JPEG; the intrinsic matrix is column-major."""
    src = open_source(f"redwood:{redwood}")
    frames = list(src)
    assert [f.frame_id for f in frames] == [0, 2, 4]
    assert src.stats.skipped == {"invalid_pose": 1, "unreadable_color": 1}
    assert src.intrinsics == CameraIntrinsics(DW, DH, 33.0, 34.0, 19.0, 15.0)
    for f in frames:
        np.testing.assert_allclose(f.T_world_cam, _pose(f.frame_id, axis=0), atol=1e-9)
        np.testing.assert_array_equal(f.depth, _depth(f.frame_id))


def test_redwood_bad_intrinsics(redwood: Path) -> None:
    (redwood / "camera_intrinsic.json").write_text('{"width": 40}')
    with pytest.raises(ValueError, match="intrinsic_matrix"):
        RedwoodSource(redwood)


# ----------------------------------------------------------------------------------- folder


def _folder_fixture(root: Path, poses: dict) -> None:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    (root / "poses").mkdir()
    for i in range(4):
        Image.fromarray(_color(i)).save(root / "rgb" / f"img_{i:04d}.png")
        if i != 2:
            Image.fromarray(_depth(i)).save(root / "depth" / f"d_{i:04d}.png")
    cfg = {
        "color": "rgb/*.png",
        "depth": "depth/*.png",
        "depth_scale": 4000.0,
        "intrinsics": {"width": DW, "height": DH, "fx": 30.0, "fy": 31.0, "cx": 20.0, "cy": 15.0},
        "poses": poses,
    }
    (root / "openfusion_source.json").write_text(json.dumps(cfg))


def test_folder_w2c_per_frame_files(tmp_path: Path) -> None:
    """World-to-camera pose files are inverted; a frame without depth is skipped and counted."""
    root = tmp_path / "capture"
    _folder_fixture(root, {"format": "matrix_per_frame", "path": "poses/*.txt", "convention": "w2c"})
    for i in range(4):
        np.savetxt(root / "poses" / f"{i}.txt", np.linalg.inv(_pose(i)))
    src = open_source(f"folder:{root}")
    frames = list(src)
    assert [f.frame_id for f in frames] == [0, 1, 3]
    assert src.stats.skipped == {"missing_depth": 1}
    for f in frames:
        np.testing.assert_allclose(f.T_world_cam, _pose(f.frame_id), atol=1e-9)
        assert f.depth_scale == 4000.0


def test_folder_opengl_tum_lines(tmp_path: Path) -> None:
    """OpenGL camera axes (y up, z back) become OpenCV axes; tum_lines timestamps become stamp_ns."""
    root = tmp_path / "nerfish"
    _folder_fixture(root, {"format": "tum_lines", "path": "traj.txt", "camera_axes": "opengl"})
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    lines = []
    for i in range(4):
        T_gl = _pose(i) @ flip  # what an OpenGL-convention writer stores for the same camera
        q = matrix_to_quat(T_gl[:3, :3])
        lines.append(f"{10 + i * 0.5} " + " ".join(f"{v:.12f}" for v in (*T_gl[:3, 3], *q)))
    (root / "traj.txt").write_text("\n".join(lines) + "\n")
    frames = list(FolderSource(root))
    assert [f.stamp_ns for f in frames] == [10_000_000_000, 10_500_000_000, 11_500_000_000]
    for f in frames:
        np.testing.assert_allclose(f.T_world_cam, _pose(f.frame_id), atol=1e-9)


def test_folder_config_errors(tmp_path: Path) -> None:
    """Bad input: no config file, a config with a typo'd key and a bad pose format, a pattern
    escaping the folder."""
    root = tmp_path / "cap"
    root.mkdir()
    with pytest.raises(FileNotFoundError, match="openfusion_source.json"):
        FolderSource(root)
    _folder_fixture(root, {"format": "matrix_rows", "path": "traj.txt"})
    cfg = json.loads((root / "openfusion_source.json").read_text())
    cfg["depth_scael"] = 1000
    (root / "openfusion_source.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match=r"poses\.format") as err:
        FolderSource(root)
    assert "depth_scael" in str(err.value)
    cfg.pop("depth_scael")
    cfg["poses"]["format"] = "matrix_lines"
    cfg["color"] = "../elsewhere/*.png"
    (root / "openfusion_source.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="stay inside"):
        FolderSource(root)


# ----------------------------------------------------------------------------------- specs


def test_unknown_scheme_suggests_the_right_one(tum: Path) -> None:
    """Bad input: a bare path or a typo'd scheme; the error lists the schemes and guesses one."""
    with pytest.raises(ValueError, match="looks like a tum source"):
        open_source(str(tum))
    with pytest.raises(ValueError, match="known: synthetic, scannet"):
        open_source("scanet:/data/x")
    with pytest.raises(ValueError, match="needs a path"):
        open_source("tum:")
    with pytest.raises(SourceError, match="recording"):
        open_source(f"replay:{tum / 'missing.ofrec'}")
