"""Image/pose synchronisation on generated streams: jitter, a tracking gap, out-of-order arrival,
clock offsets (configured and estimated), SLERP accuracy, T265 axes, downsampling."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from openfusion.frame import CameraIntrinsics
from openfusion.poses import (
    interpolate_pose,
    matrix_to_quat,
    quat_to_matrix,
    rotation_angle_deg,
    slerp,
)
from openfusion.sources.sync import (
    T265_FROM_OPENCV,
    FrameSynchronizer,
    SyncConfig,
    downsample_rgbd,
)

MS = 1_000_000
AXIS = np.array([0.2, 1.0, 0.4]) / np.linalg.norm([0.2, 1.0, 0.4])
OMEGA = 1.0  # rad/s about a fixed axis: SLERP reproduces it exactly
K = CameraIntrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
POSE_CLOCK_LAG_NS = 250 * MS  # pose device clock = true time - 0.25 s


def gt_pose(t_ns: int) -> np.ndarray:
    t = t_ns / 1e9
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(AXIS * OMEGA * t).as_matrix()
    T[:3, 3] = [0.5 * t, 0.3 * np.sin(t), 0.1 * t]
    return T


def make_streams(seed: int = 0, *, duration_s: float = 3.0):
    """Poses at 200 Hz (±1 ms sample jitter, 1-8 ms latency, none in 1.0-1.3 s), images at 30 Hz
    (±3 ms jitter, 20 ms latency + exponential jitter). Returns events sorted by host arrival:
    (host_ns, kind, device_stamp_ns, true_ns)."""
    rng = np.random.default_rng(seed)
    host_offset = 5_000_000_000
    events = []
    for k in range(int(duration_s * 200)):
        t = int(k * 5 * MS + rng.uniform(-1, 1) * MS) + 50 * MS
        if 1_000 * MS < t < 1_300 * MS:
            continue
        lat = int(2 * MS + rng.exponential(0.5 * MS) + rng.uniform(0, 6) * MS)
        events.append((t + host_offset + lat, "pose", t - POSE_CLOCK_LAG_NS, t))
    for k in range(int(duration_s * 30)):
        t = int(k * 1e9 / 30 + rng.uniform(-3, 3) * MS) + 100 * MS
        lat = int(20 * MS + rng.exponential(2 * MS))
        events.append((t + host_offset + lat, "image", t, t))
    events.sort()
    return events


def run(config: SyncConfig, events, *, with_host: bool = False):
    sync = FrameSynchronizer(config, K, source="test")
    frames = []
    color = np.zeros((48, 64, 3), np.uint8)
    depth = np.ones((48, 64), np.uint16)
    for host, kind, stamp, _true in events:
        kw = {"host_ns": host} if with_host else {}
        if kind == "pose":
            frames += sync.add_pose(stamp, gt_pose(stamp + POSE_CLOCK_LAG_NS), **kw)
        else:
            frames += sync.add_image(stamp, color, depth, depth_scale=1000.0, **kw)
    frames += sync.flush()
    return sync, frames


OPENCV_NO_RESIZE = {"pose_axes": "opencv", "output_size": None}


def test_nearest_pairs_exactly_and_drops_the_gap() -> None:
    """Every output frame carries the pose nearest in time (brute force over all poses); the
    images with no pose within 10 ms (the tracking gap) are dropped and counted, no others."""
    events = make_streams()
    sync, frames = run(SyncConfig(clock_offset_ns=POSE_CLOCK_LAG_NS, **OPENCV_NO_RESIZE), events)
    pose_true = np.array(sorted(e[3] for e in events if e[1] == "pose"))
    images = [e[3] for e in events if e[1] == "image"]
    nearest_dt = {t: int(np.abs(pose_true - t).min()) for t in images}
    expected_out = sorted(t for t in images if nearest_dt[t] <= 10 * MS)
    assert [f.stamp_ns for f in frames] == expected_out
    assert sync.stats.images_dropped == {"no_pose_within_tolerance": len(images) - len(expected_out)}
    assert len(images) - len(expected_out) >= 8  # the 300 ms gap
    assert sync.stats.poses_out_of_order > 0  # latency jitter reordered poses, all accepted
    assert sync.stats.poses_rejected == {}
    for f in frames:
        best = pose_true[np.argmin(np.abs(pose_true - f.stamp_ns))]
        np.testing.assert_allclose(f.T_world_cam, gt_pose(int(best)), atol=1e-9)
        f.validate()


def test_wrong_offset_pairs_wrong_poses() -> None:
    """Control for the test above: with the 250 ms clock offset left at 0 the poses are off by
    a quarter second of motion (> 10 cm), so the configured offset is what made pairing right."""
    _, frames = run(SyncConfig(**OPENCV_NO_RESIZE), make_streams())
    errors = [np.linalg.norm(f.T_world_cam[:3, 3] - gt_pose(f.stamp_ns)[:3, 3]) for f in frames]
    assert len(errors) > 20 and min(errors) > 0.1


def test_interpolation_accuracy_and_gap() -> None:
    """SLERP + linear interpolation reproduces the true pose at the image time (< 0.05 mm,
    < 0.001 deg); images inside the 300 ms gap or after the last pose are dropped and counted."""
    events = make_streams(1)
    cfg = SyncConfig(mode="interpolate", clock_offset_ns=POSE_CLOCK_LAG_NS, **OPENCV_NO_RESIZE)
    sync, frames = run(cfg, events)
    pose_true = np.array(sorted(e[3] for e in events if e[1] == "pose"))
    images = [e[3] for e in events if e[1] == "image"]
    outside = [t for t in images if not pose_true[0] <= t <= pose_true[-1]]
    in_gap = [t for t in images if pose_true[0] <= t <= pose_true[-1] and np.diff(pose_true[pose_true <= t][-1:].tolist() + pose_true[pose_true >= t][:1].tolist())[0] > 100 * MS]
    assert len(in_gap) >= 8 and len(outside) >= 1
    assert len(frames) == len(images) - len(in_gap) - len(outside)
    # gap images resolved while the tracker is silent (200 ms of newer images waiting) time
    # out; the rest see both sides of the gap
    dropped = sync.stats.images_dropped
    assert set(dropped) == {"pose_gap", "pose_timeout"} and dropped["pose_gap"] >= 1
    assert sum(dropped.values()) == len(in_gap) + len(outside)
    for f in frames:
        T = gt_pose(f.stamp_ns)
        assert np.linalg.norm(f.T_world_cam[:3, 3] - T[:3, 3]) < 5e-5
        assert rotation_angle_deg(f.T_world_cam[:3, :3], T[:3, :3]) < 1e-3


def test_estimated_clock_offset() -> None:
    """With host receive times and the streams' known fixed latencies the offset is estimated to
    < 1 ms and pairing matches the configured-offset run frame for frame."""
    events = make_streams(2)
    cfg = SyncConfig(estimate_clock_offset=True, image_latency_ns=20 * MS, pose_latency_ns=2 * MS, **OPENCV_NO_RESIZE)
    sync, frames = run(cfg, events, with_host=True)
    assert abs(sync.stats.clock_offset_ns - POSE_CLOCK_LAG_NS) < 1 * MS
    _, reference = run(SyncConfig(clock_offset_ns=POSE_CLOCK_LAG_NS, **OPENCV_NO_RESIZE), events)
    assert [f.stamp_ns for f in frames] == [f.stamp_ns for f in reference][-len(frames) :]
    # images that arrive before min_offset_samples of each stream are dropped (counted)
    lost = sync.stats.images_dropped.get("clock_offset_unknown", 0)
    assert 0 < lost <= cfg.min_offset_samples and len(frames) == len(reference) - lost
    with pytest.raises(ValueError, match="host_ns"):
        FrameSynchronizer(cfg, K).add_pose(0, np.eye(4))


def test_disorder_late_and_duplicate_samples_are_counted() -> None:
    """Bad input: a pose older than the reorder window, a duplicate pose, a non-finite pose, an
    image older than one already emitted, and a duplicate image."""
    sync = FrameSynchronizer(SyncConfig(**OPENCV_NO_RESIZE), K)
    c, d = np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.uint16)
    for k in range(30):
        sync.add_pose(k * 5 * MS, gt_pose(k * 5 * MS))
    sync.add_pose(10 * MS, gt_pose(10 * MS))  # 135 ms late: outside the 50 ms window
    sync.add_pose(145 * MS, gt_pose(145 * MS))  # duplicate stamp
    bad = np.eye(4)
    bad[0, 3] = np.nan
    sync.add_pose(146 * MS, bad)
    out = sync.add_image(100 * MS, c, d, depth_scale=1000.0)
    assert [f.stamp_ns for f in out] == [100 * MS]
    assert sync.add_image(90 * MS, c, d, depth_scale=1000.0) == []  # older than an emitted image
    sync.add_image(140 * MS, c, d, depth_scale=1000.0)  # waits for a pose >= 150 ms
    sync.add_image(140 * MS, c, d, depth_scale=1000.0)
    assert sync.pending == 1
    assert sync.stats.poses_rejected == {"late": 1, "duplicate": 1, "invalid": 1}
    assert sync.stats.images_dropped == {"out_of_order_image": 1, "duplicate_image": 1}
    assert [f.stamp_ns for f in sync.add_pose(150 * MS, gt_pose(150 * MS))] == [140 * MS]


def test_images_do_not_wait_forever_for_a_stalled_tracker() -> None:
    """Bad input: the pose stream stops. Waiting images are resolved (and counted as dropped)
    once 200 ms of newer images pile up, so memory stays bounded."""
    sync = FrameSynchronizer(SyncConfig(**OPENCV_NO_RESIZE), K)
    c, d = np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64), np.uint16)
    for k in range(10):
        sync.add_pose(k * 5 * MS, gt_pose(k * 5 * MS))
    for k in range(30):
        sync.add_image(40 * MS + k * 33 * MS, c, d, depth_scale=1000.0)
    assert sync.pending <= 8
    assert sync.stats.frames_out == 1  # the image at 40 ms had a pose 5 ms away
    assert sync.stats.images_dropped["no_pose_within_tolerance"] >= 20


def test_t265_axes_and_extrinsic() -> None:
    """T265 at its origin: the camera looks along world +y (forward) with image-down = world -z.
    T265 moved 1 m along its -z (forward): the camera moved 1 m forward. A camera 10 cm to the
    right of the T265, after the T265 turns 90 degrees left, sits 10 cm forward and looks left."""
    sync = FrameSynchronizer(SyncConfig(output_size=None), K)
    T = sync.camera_pose(np.eye(4))
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    fwd = np.eye(4)
    fwd[2, 3] = -1.0
    np.testing.assert_allclose(sync.camera_pose(fwd)[:3, 3], [0, 1, 0], atol=1e-12)
    ext = T265_FROM_OPENCV.copy()
    ext[0, 3] = 0.1
    sync = FrameSynchronizer(SyncConfig(output_size=None, T_tracker_cam=tuple(map(tuple, ext))), K)
    left = np.eye(4)
    left[:3, :3] = Rotation.from_rotvec([0, np.pi / 2, 0]).as_matrix()  # yaw left about T265 y-up
    T = sync.camera_pose(left)
    np.testing.assert_allclose(T[:3, 3], [0, 0.1, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [-1, 0, 0], atol=1e-12)  # optical axis points left (-x)
    with pytest.raises(ValueError, match="rigid"):
        SyncConfig(T_tracker_cam=((2, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1)))


def test_downsample_to_paper_size() -> None:
    """1280x720 -> 640x360: intrinsics scaled with pixel centres; depth takes original values
    only (nearest, never blended); color shape and mean preserved."""
    K720 = CameraIntrinsics(1280, 720, 600.0, 601.0, 639.5, 359.5)
    rng = np.random.default_rng(0)
    depth = rng.choice(np.array([0, 1000, 3000], np.uint16), size=(720, 1280))
    color = rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8)
    c, d, k = downsample_rgbd(color, depth, K720, (640, 360))
    assert c.shape == (360, 640, 3) and d.shape == (360, 640) and d.dtype == np.uint16
    assert set(np.unique(d)) <= {0, 1000, 3000}
    assert abs(float(c.mean()) - float(color.mean())) < 1.0
    assert k == CameraIntrinsics(640, 360, 300.0, 300.5, 319.5, 179.5)
    sync = FrameSynchronizer(SyncConfig(pose_axes="opencv"), K720)
    sync.add_pose(0, np.eye(4))
    sync.add_pose(20 * MS, np.eye(4))
    (f,) = sync.add_image(10 * MS, color, depth, depth_scale=1000.0)
    assert f.intrinsics == k and f.color.shape == (360, 640, 3)
    f.validate()


def test_slerp_against_known_rotation_and_scipy() -> None:
    """SLERP between samples of a constant-rate rotation is the true rotation (< 1e-5 deg), takes
    the shortest arc when the quaternions have opposite signs, and agrees with scipy's Slerp."""
    T0, T1 = gt_pose(0), gt_pose(400 * MS)
    for a in (0.0, 0.25, 0.5, 0.9, 1.0):
        T = interpolate_pose(T0, T1, a)
        assert rotation_angle_deg(T[:3, :3], gt_pose(int(a * 400 * MS))[:3, :3]) < 1e-5
    q0 = matrix_to_quat(T0[:3, :3])
    q1 = matrix_to_quat(T1[:3, :3])
    np.testing.assert_allclose(quat_to_matrix(slerp(q0, -q1, 0.3)), quat_to_matrix(slerp(q0, q1, 0.3)), atol=1e-12)
    rng = np.random.default_rng(3)
    for _ in range(20):
        ra, rb = Rotation.random(random_state=rng), Rotation.random(random_state=rng)
        a = float(rng.random())
        ref = Slerp([0, 1], Rotation.concatenate([ra, rb]))([a])[0].as_matrix()
        ours = quat_to_matrix(slerp(ra.as_quat(), rb.as_quat(), a))
        assert rotation_angle_deg(ours, ref) < 1e-5
