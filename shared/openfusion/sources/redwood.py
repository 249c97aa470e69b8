"""Redwood / Open3D capture reader (the layout of Open3D's reconstruction system datasets).

Layout::

    color/*.jpg|png              sorted by name
    depth/*.png                  sorted by name, uint16, 1000 units per metre (``depth_scale``)
    camera_intrinsic.json        Open3D PinholeCameraIntrinsic: {"width", "height",
                                 "intrinsic_matrix": [9 numbers, column-major]}
    trajectory.log               blocks: "id id n" metadata line + 4 lines of a 4x4 camera-to-world

What is converted: ``trajectory.log`` poses are camera-to-world with OpenCV camera axes in
metres, used as they are. The first metadata number of a block is the frame index into the
sorted image lists (Open3D writes "i i i+1"). Color and depth are paired by position in the
sorted lists (Open3D's own convention); when the counts differ the frame numbers in the file
names pair them instead. Without ``camera_intrinsic.json`` the PrimeSense default
(640 x 480, fx = fy = 525, cx = 319.5, cy = 239.5, Open3D's default) is used and logged.
No timestamps: ``stamp_ns = index * 1e9 / 30``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.sources.base import NOMINAL_FPS, IndexedFrameSource, SkipFrame
from openfusion.sources.files import numeric_key, pose_or_skip, read_rgbd_frame

logger = logging.getLogger(__name__)

REDWOOD_DEPTH_SCALE = 1000.0
PRIMESENSE_DEFAULT = CameraIntrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)


def read_open3d_intrinsic(path: Path) -> CameraIntrinsics:
    """An Open3D ``PinholeCameraIntrinsic`` json (column-major ``intrinsic_matrix``)."""
    try:
        data = json.loads(Path(path).read_text())
        m = np.array(data["intrinsic_matrix"], dtype=np.float64)
        if m.size != 9:
            raise ValueError(f"intrinsic_matrix has {m.size} numbers, expected 9")
        K = m.reshape(3, 3).T  # stored column-major
        return CameraIntrinsics.from_matrix(K, int(data["width"]), int(data["height"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(
            f"{path}: not an Open3D camera intrinsic json ({exc}); expected width, height, intrinsic_matrix (9, column-major)"
        ) from exc


def read_trajectory_log(path: Path) -> list[tuple[int, np.ndarray | None]]:
    """(frame index, 4x4 or None when the block is malformed) per block of a ``.log`` trajectory."""
    lines = [ln.strip() for ln in Path(path).read_text().splitlines() if ln.strip()]
    if len(lines) % 5 != 0:
        logger.warning("%s: %d non-empty lines is not a multiple of 5; the last block is incomplete", path, len(lines))
    out: list[tuple[int, np.ndarray | None]] = []
    for b in range(len(lines) // 5):
        block = lines[5 * b : 5 * b + 5]
        try:
            meta = [int(v) for v in block[0].split()]
            frame = meta[0]
        except (ValueError, IndexError):
            frame = b
            out.append((frame, None))
            continue
        try:
            T = np.array(" ".join(block[1:]).split(), dtype=np.float64)
            out.append((frame, T.reshape(4, 4) if T.size == 16 else None))
        except ValueError:
            out.append((frame, None))
    return out


def _sorted_images(folder: Path, exts: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in exts) if folder.is_dir() else []


class RedwoodSource(IndexedFrameSource):
    """Frames of a Redwood / Open3D RGB-D capture folder (see module docstring)."""

    def __init__(
        self,
        folder: str | Path,
        *,
        intrinsics: CameraIntrinsics | None = None,
        depth_scale: float = REDWOOD_DEPTH_SCALE,
        trajectory: str | Path | None = None,
        fps: float = NOMINAL_FPS,
        stride: int = 1,
        max_frames: int | None = None,
    ) -> None:
        root = Path(folder)
        if not root.is_dir():
            raise FileNotFoundError(f"Redwood/Open3D capture folder {root} does not exist")
        traj_path = Path(trajectory) if trajectory is not None else root / "trajectory.log"
        if not (root / "color").is_dir() or not (root / "depth").is_dir() or not traj_path.is_file():
            raise FileNotFoundError(
                f"{root} is not a Redwood/Open3D capture: expected color/, depth/ and {traj_path.name} "
                "(pass trajectory=PATH for a trajectory stored elsewhere)"
            )
        super().__init__(f"redwood:{root.name}", stride=stride, max_frames=max_frames)
        self.root = root
        self.fps = float(fps)
        self.depth_scale = float(depth_scale)
        if intrinsics is None:
            json_path = root / "camera_intrinsic.json"
            if json_path.is_file():
                intrinsics = read_open3d_intrinsic(json_path)
            else:
                logger.warning("%s: no camera_intrinsic.json, using the PrimeSense default %s", root, PRIMESENSE_DEFAULT)
                intrinsics = PRIMESENSE_DEFAULT
        self.intrinsics = intrinsics
        colors = _sorted_images(root / "color", (".jpg", ".jpeg", ".png"))
        depths = _sorted_images(root / "depth", (".png",))
        if len(colors) == len(depths):
            self._pairs: list[tuple[Path | None, Path | None]] = list(zip(colors, depths, strict=True))
        else:
            by_c = {numeric_key(p): p for p in colors}
            by_d = {numeric_key(p): p for p in depths}
            keys = sorted(k for k in set(by_c) | set(by_d) if k is not None)
            logger.warning(
                "%s: %d color vs %d depth images; pairing by the frame number in the file names", root, len(colors), len(depths)
            )
            self._pairs = [(by_c.get(k), by_d.get(k)) for k in keys]
        self._blocks = read_trajectory_log(traj_path)
        if not self._blocks:
            raise ValueError(f"{traj_path} holds no pose blocks")

    def _num_items(self) -> int:
        return len(self._blocks)

    def _load(self, index: int) -> Frame:
        frame_idx, raw = self._blocks[index]
        ctx = f"{self.root.name} frame {frame_idx}"
        if raw is None:
            raise SkipFrame("unreadable_pose", f"{ctx}: trajectory block {index} is malformed")
        T = pose_or_skip(raw, context=ctx)
        if not 0 <= frame_idx < len(self._pairs):
            raise SkipFrame("missing_color", f"{ctx}: trajectory refers to frame {frame_idx}, only {len(self._pairs)} images")
        color_path, depth_path = self._pairs[frame_idx]
        if depth_path is None:
            raise SkipFrame("missing_depth", f"{ctx}: no depth image for this frame")
        if color_path is None:
            raise SkipFrame("missing_color", f"{ctx}: no color image for this frame")
        return read_rgbd_frame(
            frame_id=frame_idx,
            stamp_ns=int(round(frame_idx * 1e9 / self.fps)),
            color_path=color_path,
            depth_path=depth_path,
            intrinsics=self.intrinsics,
            depth_scale=self.depth_scale,
            T_world_cam=T,
            source=self.name,
        )
