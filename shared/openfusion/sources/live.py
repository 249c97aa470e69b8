"""Live Azure Kinect (RGB-D) + Intel RealSense T265 (pose) source.

Optional extra ``live``: ``pip install 'openfusion-z[live]'`` installs ``pyk4a`` (needs the
Azure Kinect Sensor SDK 1.4, ``libk4a1.4``, on the system) and ``pyrealsense2``. The T265 is
only supported by librealsense **<= 2.53.1** (support was removed in 2.54): pin
``pyrealsense2==2.53.1.4623``. Both drivers are imported lazily, only when a device is opened,
and a missing one raises ``LiveDependencyError`` saying what to install.

The driver wrappers are thin: they read a capture (color + depth transformed into the color
camera, device timestamp, host receive time) or a pose (T265 body in T265 world, device
timestamp, tracker confidence). Everything else (clock offset, pairing within 10 ms or SLERP,
the camera<->T265 extrinsic, T265 axes -> OpenCV, 1280x720 -> 640x360) is
``openfusion.sources.sync``, tested without hardware.

What is converted: Kinect BGRA -> RGB; depth stays uint16 millimetres (``depth_scale = 1000``),
registered to the color camera by the SDK (``transformed_depth``); T265 poses as described in
``openfusion.sources.sync``.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from openfusion.errors import UserError
from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import pose_from_tum
from openfusion.sources.base import FrameSource, Skip
from openfusion.sources.sync import FrameSynchronizer, SyncConfig

logger = logging.getLogger(__name__)

KINECT_DEPTH_SCALE = 1000.0
T265_MAX_LIBREALSENSE = (2, 53, 1)


class LiveDependencyError(UserError, ImportError):
    """A live-sensor driver package is missing (the message says what to install)."""


def _import_pyk4a() -> Any:
    try:
        import pyk4a  # type: ignore[import-not-found]
    except ImportError as exc:
        raise LiveDependencyError(
            "Azure Kinect support needs the optional 'live' extra: pip install 'openfusion-z[live]' "
            f"(pyk4a, which also needs the Azure Kinect Sensor SDK 1.4 / libk4a1.4 installed); import failed: {exc}"
        ) from exc
    return pyk4a


def _import_pyrealsense2() -> Any:
    try:
        import pyrealsense2 as rs  # type: ignore[import-not-found]
    except ImportError as exc:
        raise LiveDependencyError(
            "Intel T265 support needs pyrealsense2 <= 2.53.1 (T265 support was removed in librealsense 2.54): "
            f"pip install 'pyrealsense2==2.53.1.4623'; import failed: {exc}"
        ) from exc
    version = getattr(rs, "__version__", "")
    try:
        parts = tuple(int(p) for p in version.split(".")[:3])
    except ValueError:
        parts = ()
    if len(parts) == 3 and parts > T265_MAX_LIBREALSENSE:
        raise LiveDependencyError(
            f"pyrealsense2 {version} no longer supports the T265 (removed in librealsense 2.54); "
            "install pyrealsense2==2.53.1.4623"
        )
    return rs


@dataclass
class ImageSample:
    """One registered RGB-D capture: stamps in ns (device clock, host clock at receipt)."""

    device_ns: int
    host_ns: int
    color: np.ndarray  # HxWx3 uint8 RGB
    depth: np.ndarray  # HxW uint16
    depth_scale: float = KINECT_DEPTH_SCALE


@dataclass
class PoseSample:
    """One tracker pose: T265 body in T265 world (x right, y up, z back), stamps in ns."""

    device_ns: int
    host_ns: int
    T_t265world_body: np.ndarray
    confidence: int = 3


class ImageDriver(Protocol):
    intrinsics: CameraIntrinsics

    def start(self) -> None: ...
    def read(self, timeout_s: float) -> ImageSample | None: ...
    def stop(self) -> None: ...


class PoseDriver(Protocol):
    def start(self, on_pose: Callable[[PoseSample], None]) -> None: ...
    def stop(self) -> None: ...


class AzureKinectDriver:
    """pyk4a wrapper: 30 fps, color 720p BGRA, NFOV unbinned depth transformed to color."""

    def __init__(self, *, device_id: int = 0, color_resolution: str = "720p", fps: int = 30) -> None:
        self._pyk4a = _import_pyk4a()
        pk = self._pyk4a
        res = {"720p": pk.ColorResolution.RES_720P, "1080p": pk.ColorResolution.RES_1080P}.get(color_resolution)
        if res is None:
            raise ValueError(f"color_resolution must be '720p' or '1080p', got {color_resolution!r}")
        fps_enum = {5: pk.FPS.FPS_5, 15: pk.FPS.FPS_15, 30: pk.FPS.FPS_30}.get(fps)
        if fps_enum is None:
            raise ValueError(f"fps must be 5, 15 or 30, got {fps}")
        config = pk.Config(
            color_resolution=res,
            color_format=pk.ImageFormat.COLOR_BGRA32,
            depth_mode=pk.DepthMode.NFOV_UNBINNED,
            camera_fps=fps_enum,
            synchronized_images_only=True,
        )
        self._device = pk.PyK4A(config, device_id=device_id)
        self._size = {"720p": (1280, 720), "1080p": (1920, 1080)}[color_resolution]
        self.intrinsics: CameraIntrinsics | None = None

    def start(self) -> None:
        self._device.start()
        K = self._device.calibration.get_camera_matrix(self._pyk4a.CalibrationType.COLOR)
        self.intrinsics = CameraIntrinsics.from_matrix(np.asarray(K), *self._size)
        logger.info("Azure Kinect started: %s", self.intrinsics)

    def read(self, timeout_s: float) -> ImageSample | None:
        capture = self._device.get_capture(timeout=int(timeout_s * 1000))
        host_ns = time.time_ns()
        color, depth = capture.color, capture.transformed_depth
        if color is None or depth is None:
            return None
        return ImageSample(
            device_ns=int(capture.color_timestamp_usec) * 1000,
            host_ns=host_ns,
            color=np.ascontiguousarray(color[..., 2::-1]),
            depth=np.asarray(depth, dtype=np.uint16),
        )

    def stop(self) -> None:
        self._device.stop()


class T265Driver:
    """pyrealsense2 wrapper: the pose stream, delivered by librealsense's callback thread."""

    def __init__(self, *, serial: str | None = None) -> None:
        self._rs = _import_pyrealsense2()
        self._pipeline = self._rs.pipeline()
        self._config = self._rs.config()
        if serial:
            self._config.enable_device(serial)
        self._config.enable_stream(self._rs.stream.pose)

    def start(self, on_pose: Callable[[PoseSample], None]) -> None:
        def callback(frame: Any) -> None:
            pose_frame = frame.as_pose_frame() if frame.is_pose_frame() else None
            if pose_frame is None:
                return
            d = pose_frame.get_pose_data()
            T = pose_from_tum(
                np.array([d.translation.x, d.translation.y, d.translation.z]),
                np.array([d.rotation.x, d.rotation.y, d.rotation.z, d.rotation.w]),
            )
            on_pose(PoseSample(int(pose_frame.get_timestamp() * 1e6), time.time_ns(), T, int(d.tracker_confidence)))

        self._pipeline.start(self._config, callback)
        logger.info("T265 pose stream started")

    def stop(self) -> None:
        self._pipeline.stop()


class KinectT265Source(FrameSource):
    """Live frames: Kinect RGB-D paired with T265 poses by ``FrameSynchronizer``.

    Default sync: nearest pose within 10 ms, clock offset estimated from host receive times,
    output 640x360. ``min_confidence``: T265 poses below it (0 failed .. 3 high) are dropped.
    ``image_driver``/``pose_driver`` replace the hardware (tests, other sensors).
    """

    live = True

    def __init__(
        self,
        *,
        sync: SyncConfig | None = None,
        image_driver: ImageDriver | None = None,
        pose_driver: PoseDriver | None = None,
        min_confidence: int = 2,
        read_timeout_s: float = 1.0,
        max_frames: int | None = None,
    ) -> None:
        super().__init__("live:kinect-t265", max_frames=max_frames)
        self.sync_config = sync or SyncConfig(estimate_clock_offset=True)
        self._image_driver = image_driver
        self._pose_driver = pose_driver
        self.min_confidence = min_confidence
        self.read_timeout_s = read_timeout_s
        self._poses: queue.Queue[PoseSample] = queue.Queue(maxsize=4096)
        self._stop = threading.Event()
        self.low_confidence_poses = 0
        self.dropped_poses = 0

    def _on_pose(self, sample: PoseSample) -> None:
        # runs on the driver's thread: never block it
        if sample.confidence < self.min_confidence:
            self.low_confidence_poses += 1
            return
        try:
            self._poses.put_nowait(sample)
        except queue.Full:
            self.dropped_poses += 1

    def stop(self) -> None:
        """Ask a running iteration to end after the current capture."""
        self._stop.set()

    def _produce(self) -> Iterator[Frame | Skip]:
        images = self._image_driver or AzureKinectDriver()
        poses = self._pose_driver or T265Driver()
        self._stop.clear()
        poses.start(self._on_pose)
        images.start()
        try:
            if images.intrinsics is None:
                raise RuntimeError("image driver reported no intrinsics after start()")
            sync = FrameSynchronizer(self.sync_config, images.intrinsics, source=self.name)
            seen: dict[str, int] = {}
            while not self._stop.is_set():
                sample = images.read(self.read_timeout_s)
                out: list[Frame] = []
                while True:
                    try:
                        p = self._poses.get_nowait()
                    except queue.Empty:
                        break
                    out += sync.add_pose(p.device_ns, p.T_t265world_body, host_ns=p.host_ns)
                if sample is None:
                    if images_done(images):
                        break
                    continue
                out += sync.add_image(
                    sample.device_ns, sample.color, sample.depth, depth_scale=sample.depth_scale, host_ns=sample.host_ns
                )
                yield from out
                yield from _new_drops(sync, seen)
            yield from sync.flush()
            yield from _new_drops(sync, seen)
        finally:
            images.stop()
            poses.stop()


def images_done(driver: object) -> bool:
    """A driver may expose ``finished`` (recorded/fake streams); live cameras never finish."""
    return bool(getattr(driver, "finished", False))


def _new_drops(sync: FrameSynchronizer, seen: dict[str, int]) -> list[Skip]:
    out = []
    for reason, count in sync.stats.images_dropped.items():
        out += [Skip(reason, "image dropped by the pose synchroniser")] * (count - seen.get(reason, 0))
        seen[reason] = count
    return out
