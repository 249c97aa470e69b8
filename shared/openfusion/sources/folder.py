"""Generic RGB-D folder reader driven by a small ``openfusion_source.json``.

Example config (every path is relative to the folder)::

    {
      "color": "rgb/*.png",
      "depth": "depth/*.png",
      "depth_scale": 1000.0,
      "intrinsics": {"width": 640, "height": 480, "fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5},
      "poses": {"format": "matrix_per_frame", "path": "pose/*.txt", "convention": "c2w", "camera_axes": "opencv"},
      "pair_by": "number",
      "fps": 30.0
    }

``poses.format``: ``matrix_per_frame`` (one 4x4 text file per frame, glob pattern),
``matrix_lines`` (one line of 16 numbers per frame), ``tum_lines`` (``t tx ty tz qx qy qz qw``
per frame, the timestamp becomes ``stamp_ns``) or ``open3d_log`` (``trajectory.log`` blocks).
Line/block k belongs to the k-th frame.

``pair_by``: ``number`` pairs color, depth and per-frame pose files by the last number in the
file name (a frame missing one of them is skipped and counted); ``order`` pairs by position in
the sorted lists.

What is converted: poses with ``convention: "w2c"`` are inverted to camera-to-world;
``camera_axes: "opengl"`` (x right, y up, z backward, as NeRF/Blender write) is turned into
OpenCV axes by flipping the camera's y and z axes (``T_world_cam @ diag(1, -1, -1, 1)``).
Depth stays uint16 with the configured ``depth_scale``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import pose_from_tum
from openfusion.sources.base import NOMINAL_FPS, IndexedFrameSource, SkipFrame
from openfusion.sources.files import numeric_key, pose_or_skip, read_matrix, read_rgbd_frame
from openfusion.sources.redwood import read_trajectory_log
from openfusion.sources.replica import read_trajectory_lines

logger = logging.getLogger(__name__)

CONFIG_NAME = "openfusion_source.json"
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


class IntrinsicsConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float


class PosesConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format: Literal["matrix_per_frame", "matrix_lines", "tum_lines", "open3d_log"]
    path: str
    convention: Literal["c2w", "w2c"] = "c2w"
    camera_axes: Literal["opencv", "opengl"] = "opencv"


class FolderConfig(BaseModel):
    """The schema of ``openfusion_source.json``."""

    model_config = ConfigDict(extra="forbid")
    color: str
    depth: str
    depth_scale: float = Field(gt=0)
    intrinsics: IntrinsicsConfig
    poses: PosesConfig
    pair_by: Literal["number", "order"] = "number"
    fps: float = Field(default=NOMINAL_FPS, gt=0)

    @field_validator("color", "depth")
    @classmethod
    def _relative(cls, v: str) -> str:
        if Path(v).is_absolute() or ".." in Path(v).parts:
            raise ValueError(f"pattern {v!r} must be relative to the folder and stay inside it")
        return v


def load_folder_config(path: Path) -> FolderConfig:
    try:
        raw = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read {path}: {exc}") from exc
    try:
        return FolderConfig.model_validate(raw)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise ValueError(f"{path}: invalid source config: {problems}") from None


class FolderSource(IndexedFrameSource):
    """Frames of a folder described by ``openfusion_source.json`` (see module docstring)."""

    def __init__(
        self,
        folder: str | Path,
        *,
        config: FolderConfig | None = None,
        stride: int = 1,
        max_frames: int | None = None,
    ) -> None:
        root = Path(folder)
        if not root.is_dir():
            raise FileNotFoundError(f"folder {root} does not exist")
        if config is None:
            cfg_path = root / CONFIG_NAME
            if not cfg_path.is_file():
                raise FileNotFoundError(
                    f"{root} has no {CONFIG_NAME}; write one describing the color/depth patterns, depth_scale, "
                    "intrinsics and poses (see openfusion.sources.folder)"
                )
            config = load_folder_config(cfg_path)
        super().__init__(f"folder:{root.name}", stride=stride, max_frames=max_frames)
        self.root = root
        self.config = config
        ic = config.intrinsics
        self.intrinsics = CameraIntrinsics(ic.width, ic.height, ic.fx, ic.fy, ic.cx, ic.cy)
        colors = sorted(root.glob(config.color))
        depths = sorted(root.glob(config.depth))
        if not colors and not depths:
            raise FileNotFoundError(f"{root}: no files match color {config.color!r} or depth {config.depth!r}")
        pc = config.poses
        per_frame_poses = sorted(root.glob(pc.path)) if pc.format == "matrix_per_frame" else []
        if config.pair_by == "order":
            n = max(len(colors), len(depths))
            self._frames = [
                (k, colors[k] if k < len(colors) else None, depths[k] if k < len(depths) else None) for k in range(n)
            ]
            pose_by_frame = {k: p for k, p in enumerate(per_frame_poses)}
        else:
            by_c = {numeric_key(p): p for p in colors}
            by_d = {numeric_key(p): p for p in depths}
            keys = sorted(k for k in set(by_c) | set(by_d) if k is not None)
            self._frames = [(k, by_c.get(k), by_d.get(k)) for k in keys]
            pose_by_frame = {numeric_key(p): p for p in per_frame_poses}
        self._pose_files = pose_by_frame
        self._pose_list: list[tuple[int | None, np.ndarray | None]] = []
        if pc.format != "matrix_per_frame":
            pose_path = root / pc.path
            if not pose_path.is_file():
                raise FileNotFoundError(f"{root}: pose file {pc.path!r} does not exist")
            if pc.format == "matrix_lines":
                self._pose_list = [(None, T) for T in read_trajectory_lines(pose_path)]
            elif pc.format == "open3d_log":
                self._pose_list = [(None, T) for _, T in read_trajectory_log(pose_path)]
            else:
                self._pose_list = self._read_tum_lines(pose_path)
            if len(self._pose_list) != len(self._frames):
                logger.warning(
                    "%s: %d poses for %d frames; frames without a pose are skipped",
                    root,
                    len(self._pose_list),
                    len(self._frames),
                )

    @staticmethod
    def _read_tum_lines(path: Path) -> list[tuple[int | None, np.ndarray | None]]:
        out: list[tuple[int | None, np.ndarray | None]] = []
        for line in path.read_text().splitlines():
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            try:
                v = np.array(line.split(), dtype=np.float64)
                if v.size != 8:
                    raise ValueError("need 8 numbers")
                out.append((int(round(v[0] * 1e9)), pose_from_tum(v[1:4], v[4:8])))
            except ValueError:
                out.append((None, None))
        return out

    def _num_items(self) -> int:
        return len(self._frames)

    def _load(self, index: int) -> Frame:
        key, color_path, depth_path = self._frames[index]
        ctx = f"{self.root.name} frame {key}"
        stamp = int(round(index * 1e9 / self.config.fps))
        if self.config.poses.format == "matrix_per_frame":
            pose_path = self._pose_files.get(key)
            if pose_path is None:
                raise SkipFrame("missing_pose", f"{ctx}: no pose file matching {self.config.poses.path!r}")
            raw = read_matrix(pose_path, what="pose")
        else:
            if index >= len(self._pose_list):
                raise SkipFrame("missing_pose", f"{ctx}: pose file has only {len(self._pose_list)} entries")
            pose_stamp, raw = self._pose_list[index]
            if raw is None:
                raise SkipFrame("unreadable_pose", f"{ctx}: pose entry {index} is malformed")
            if pose_stamp is not None:
                stamp = pose_stamp
        T = pose_or_skip(raw, context=ctx)
        if self.config.poses.convention == "w2c":
            T = np.linalg.inv(T)
        if self.config.poses.camera_axes == "opengl":
            T = T @ _OPENGL_TO_OPENCV
        if depth_path is None:
            raise SkipFrame("missing_depth", f"{ctx}: no depth file matching {self.config.depth!r}")
        if color_path is None:
            raise SkipFrame("missing_color", f"{ctx}: no color file matching {self.config.color!r}")
        return read_rgbd_frame(
            frame_id=int(key),
            stamp_ns=stamp,
            color_path=color_path,
            depth_path=depth_path,
            intrinsics=self.intrinsics,
            depth_scale=self.config.depth_scale,
            T_world_cam=T,
            source=self.name,
        )
