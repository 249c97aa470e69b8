"""Replica reader for the NICE-SLAM release (``Replica/<scene>/``).

Layout::

    results/frame000000.jpg    1200 x 680 RGB
    results/depth000000.png    uint16, 6553.5 units per metre
    traj.txt                   one camera-to-world 4x4 per line (16 numbers, row-major)
    ../cam_params.json         optional (Co-SLAM style: {"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}})

What is converted: nothing in the pose: ``traj.txt`` holds camera-to-world matrices with OpenCV
camera axes in metres (NICE-SLAM flips y and z only *after* loading, for its own renderer; we
do not). Defaults are the release's camera: 1200 x 680, fx = fy = 600, cx = 599.5,
cy = 339.5, depth scale 6553.5; a ``cam_params.json`` in the scene folder or its parent, or
explicit options, override them. Depth stays uint16 with ``depth_scale = 6553.5``. There are
no timestamps: ``stamp_ns = index * 1e9 / 30``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.sources.base import NOMINAL_FPS, IndexedFrameSource, SkipFrame
from openfusion.sources.files import pose_or_skip, read_rgbd_frame

logger = logging.getLogger(__name__)

REPLICA_DEPTH_SCALE = 6553.5
REPLICA_INTRINSICS = CameraIntrinsics(1200, 680, 600.0, 600.0, 599.5, 339.5)


def _read_cam_params(scene_dir: Path) -> tuple[CameraIntrinsics | None, float | None]:
    for d in (scene_dir, scene_dir.parent):
        p = d / "cam_params.json"
        if not p.is_file():
            continue
        try:
            cam = json.loads(p.read_text())["camera"]
            intr = CameraIntrinsics(
                int(cam["w"]), int(cam["h"]), float(cam["fx"]), float(cam["fy"]), float(cam["cx"]), float(cam["cy"])
            )
            scale = float(cam["scale"]) if "scale" in cam else None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{p}: not a usable cam_params.json ({exc}); expected {{'camera': {{'w','h','fx','fy','cx','cy','scale'}}}}") from exc
        logger.info("Replica camera from %s: %s, depth scale %s", p, intr, scale)
        return intr, scale
    return None, None


def read_trajectory_lines(path: Path) -> list[np.ndarray | None]:
    """One 4x4 per non-empty line (16 numbers); a malformed line gives None (counted later)."""
    out: list[np.ndarray | None] = []
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            values = np.array(line.split(), dtype=np.float64)
        except ValueError:
            out.append(None)
            continue
        out.append(values.reshape(4, 4) if values.size == 16 else None)
    return out


class ReplicaSource(IndexedFrameSource):
    """Frames of one Replica scene of the NICE-SLAM release (see module docstring)."""

    def __init__(
        self,
        scene_dir: str | Path,
        *,
        intrinsics: CameraIntrinsics | None = None,
        depth_scale: float | None = None,
        fps: float = NOMINAL_FPS,
        stride: int = 1,
        max_frames: int | None = None,
    ) -> None:
        scene_dir = Path(scene_dir)
        if not scene_dir.is_dir():
            raise FileNotFoundError(f"Replica scene folder {scene_dir} does not exist")
        traj = scene_dir / "traj.txt"
        if not traj.is_file() or not (scene_dir / "results").is_dir():
            raise FileNotFoundError(
                f"{scene_dir} is not a NICE-SLAM Replica scene: expected traj.txt and results/ (frame%06d.jpg, depth%06d.png)"
            )
        super().__init__(f"replica:{scene_dir.name}", stride=stride, max_frames=max_frames)
        self.scene_dir = scene_dir
        self.fps = float(fps)
        file_intr, file_scale = _read_cam_params(scene_dir)
        self.intrinsics = intrinsics or file_intr or REPLICA_INTRINSICS
        self.depth_scale = float(depth_scale or file_scale or REPLICA_DEPTH_SCALE)
        self._poses = read_trajectory_lines(traj)
        if not self._poses:
            raise ValueError(f"{traj} holds no poses")

    def _num_items(self) -> int:
        return len(self._poses)

    def _load(self, index: int) -> Frame:
        results = self.scene_dir / "results"
        ctx = f"{self.scene_dir.name} frame {index}"
        raw = self._poses[index]
        if raw is None:
            raise SkipFrame("unreadable_pose", f"{ctx}: traj.txt line {index + 1} is not 16 numbers")
        T = pose_or_skip(raw, context=ctx)
        color_path = results / f"frame{index:06d}.jpg"
        if not color_path.exists() and (results / f"frame{index:06d}.png").exists():
            color_path = results / f"frame{index:06d}.png"
        return read_rgbd_frame(
            frame_id=index,
            stamp_ns=int(round(index * 1e9 / self.fps)),
            color_path=color_path,
            depth_path=results / f"depth{index:06d}.png",
            intrinsics=self.intrinsics,
            depth_scale=self.depth_scale,
            T_world_cam=T,
            source=self.name,
        )
