"""Live Kinect + T265 source with fake drivers (no hardware): the whole path from driver
samples on two clocks to canonical frames, and clear errors when the extra is missing."""

from __future__ import annotations

import sys
from collections.abc import Callable

import numpy as np
import pytest

from openfusion.frame import CameraIntrinsics
from openfusion.poses import look_at, rotation_angle_deg
from openfusion.sources import open_source
from openfusion.sources.live import (
    AzureKinectDriver,
    ImageSample,
    KinectT265Source,
    LiveDependencyError,
    PoseSample,
    T265Driver,
)
from openfusion.sources.sync import T265_FROM_OPENCV, ZUP_FROM_T265_WORLD, SyncConfig

MS = 1_000_000
K_IN = CameraIntrinsics(128, 72, 100.0, 100.0, 63.5, 35.5)
EXT = T265_FROM_OPENCV.copy()
EXT[:3, 3] = [0.05, -0.02, 0.01]  # camera 5 cm right of the T265 etc.
POSE_CLOCK_NS = 3_000_000_000  # T265 device clock runs 3 s ahead of the Kinect's
HOST_NS = 100_000_000_000


def true_cam(t_ns: int) -> np.ndarray:
    t = t_ns / 1e9
    pos = np.array([1.0 + 0.5 * np.cos(t), 2.0 + 0.5 * np.sin(t), 1.4])
    return look_at(pos, np.array([1.0, 2.0, 0.8]) + 0.2 * np.array([np.sin(t), 0, 0]))


class FakeT265:
    def __init__(self) -> None:
        self.on_pose: Callable[[PoseSample], None] | None = None
        self.next_k = 0
        self.stopped = False

    def start(self, on_pose: Callable[[PoseSample], None]) -> None:
        self.on_pose = on_pose

    def emit_until(self, t_ns: int) -> None:
        while self.next_k * 5 * MS <= t_ns:
            t = self.next_k * 5 * MS
            self.next_k += 1
            # what a T265 reports for the camera pose true_cam(t) given the extrinsic
            T_body = np.linalg.inv(ZUP_FROM_T265_WORLD) @ true_cam(t) @ np.linalg.inv(EXT)
            confidence = 1 if 500 * MS <= t < 700 * MS else 3  # tracking degraded for 200 ms
            assert self.on_pose is not None
            self.on_pose(PoseSample(t + POSE_CLOCK_NS, t + HOST_NS + 2 * MS + (self.next_k % 3) * MS // 10, T_body, confidence))

    def stop(self) -> None:
        self.stopped = True


class FakeKinect:
    def __init__(self, poses: FakeT265, n: int) -> None:
        self.poses, self.n, self.k = poses, n, 0
        self.intrinsics: CameraIntrinsics | None = None
        self.finished = False
        self.stopped = False

    def start(self) -> None:
        self.intrinsics = K_IN

    def read(self, timeout_s: float) -> ImageSample | None:
        if self.k >= self.n:
            self.finished = True
            return None
        t = 20 * MS + self.k * 33 * MS
        self.k += 1
        self.poses.emit_until(t + 30 * MS)  # poses arrive with less latency than images
        color = np.full((72, 128, 3), self.k % 255, np.uint8)
        depth = np.full((72, 128), 1000 + self.k, np.uint16)
        return ImageSample(t, t + HOST_NS + 25 * MS + (self.k % 4) * MS // 10, color, depth)

    def stop(self) -> None:
        self.stopped = True


def test_fake_drivers_end_to_end() -> None:
    """Two device clocks 3 s apart, the clock offset estimated from host receive times, the
    camera<->T265 extrinsic, T265 axes -> OpenCV/z-up, 128x72 -> 64x36: every frame's pose is
    the true camera pose; frames while the T265 reported low confidence are dropped and counted."""
    t265 = FakeT265()
    kinect = FakeKinect(t265, n=40)
    cfg = SyncConfig(
        estimate_clock_offset=True,
        image_latency_ns=25 * MS,
        pose_latency_ns=2 * MS,
        T_tracker_cam=tuple(map(tuple, EXT)),
        output_size=(64, 36),
    )
    src = KinectT265Source(sync=cfg, image_driver=kinect, pose_driver=t265)
    frames = list(src)
    assert kinect.stopped and t265.stopped
    assert src.low_confidence_poses == 40
    in_outage = [20 + k * 33 for k in range(40) if 500 - 10 < 20 + k * 33 < 700 + 10]
    assert src.stats.skipped.get("no_pose_within_tolerance", 0) >= len(in_outage) - 1
    assert len(frames) >= 40 - len(in_outage) - src.sync_config.min_offset_samples
    assert len(frames) > 15
    for f in frames:
        f.validate()
        assert f.color.shape == (36, 64, 3) and f.intrinsics == K_IN.scaled(64, 36)
        T = true_cam(f.stamp_ns)
        # nearest pose within 10 ms at ~0.5 m/s and 1 rad/s: < 3 mm / 0.2 deg from the truth
        assert np.linalg.norm(f.T_world_cam[:3, 3] - T[:3, 3]) < 0.003
        assert rotation_angle_deg(f.T_world_cam[:3, :3], T[:3, :3]) < 0.2


def test_missing_extras_name_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bad input: the 'live' extra is not installed. Opening a device raises LiveDependencyError
    (an ImportError) that names the package, the extra and the T265's librealsense limit."""
    monkeypatch.setitem(sys.modules, "pyk4a", None)
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    with pytest.raises(LiveDependencyError, match=r"openfusion-z\[live\]"):
        AzureKinectDriver()
    with pytest.raises(LiveDependencyError, match="2.53.1"):
        T265Driver()
    with pytest.raises(LiveDependencyError):
        list(open_source("live:kinect-t265"))
    with pytest.raises(ValueError, match="live:kinect-t265"):
        open_source("live:oak-d")


def test_too_new_librealsense_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bad input: pyrealsense2 2.55 (no T265 support) is refused with the version to install."""
    fake = type(sys)("pyrealsense2")
    fake.__version__ = "2.55.1"
    monkeypatch.setitem(sys.modules, "pyrealsense2", fake)
    with pytest.raises(LiveDependencyError, match="2.53.1.4623"):
        T265Driver()


def test_bridge_never_blocks_or_waits_for_a_live_source_but_does_for_playback() -> None:
    """A live camera must not be slowed down by geometry: the bridge drops under congestion and
    has no flow control for it; a dataset/synthetic source gets both. The config overrides."""
    from openfusion.services.bridge.service import BridgeConfig, BridgeService

    t265 = FakeT265()
    live = KinectT265Source(sync=SyncConfig(), image_driver=FakeKinect(t265, n=2), pose_driver=t265)
    assert live.live
    from openfusion.sources.ros2 import Ros2Source

    assert Ros2Source.live  # ROS 2 topics are live too
    bridge = BridgeService(BridgeConfig(), source=live)
    assert bridge.blocking is False and bridge.window is None
    playback = BridgeService(BridgeConfig(), source=open_source("synthetic:frames=2,width=80,height=60"))
    assert playback.blocking is True and playback.window is not None and playback.window.limit == 16
    forced = BridgeService(BridgeConfig.model_validate({"bridge": {"block_when_congested": True}}), source=live)
    assert forced.blocking is True and forced.window is not None
    no_flow = BridgeService(BridgeConfig.model_validate({"bridge": {"max_in_flight": 0}}),
                            source=open_source("synthetic:frames=2,width=80,height=60"))
    assert no_flow.blocking is True and no_flow.window is None
