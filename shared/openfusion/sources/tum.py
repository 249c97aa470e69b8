"""TUM RGB-D benchmark reader (``rgbd_dataset_freiburg*`` folders).

Layout::

    rgb.txt, depth.txt     "timestamp filename" per line ('#' comments), timestamps in seconds
    groundtruth.txt        "timestamp tx ty tz qx qy qz qw" per line
    rgb/*.png, depth/*.png 640 x 480; depth uint16, 5000 units per metre

What is converted: ``groundtruth.txt`` gives the camera-to-world pose of the optical centre
(OpenCV camera axes, metres) as translation + unit quaternion (x, y, z, w): turned into a 4x4
``T_world_cam``. Each rgb image is paired with the depth image nearest in time (one-to-one,
greedy by time difference like TUM's ``associate.py``) when within ``max_dt_s`` (20 ms);
unpaired images are skipped (``no_depth_match``). The pose is interpolated at the *depth*
timestamp (``pose_at="depth"``, or ``"rgb"``), linear in translation and SLERP in rotation;
frames outside the ground-truth time range (``outside_pose_range``) or inside a ground-truth gap
longer than ``max_pose_gap_s`` (``pose_gap``) are skipped. ``stamp_ns`` is that timestamp.
Intrinsics: the Freiburg 1/2/3 defaults picked from the folder name (fr1 when unknown),
overridable with ``intrinsics=``. Depth stays uint16 with ``depth_scale = 5000``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import PoseTrack, pose_from_tum
from openfusion.sources.base import IndexedFrameSource, SkipFrame
from openfusion.sources.files import pose_or_skip, read_color, read_depth_u16

logger = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0
TUM_INTRINSICS = {
    "freiburg1": CameraIntrinsics(640, 480, 517.3, 516.5, 318.6, 255.3),
    "freiburg2": CameraIntrinsics(640, 480, 520.9, 521.0, 325.1, 249.7),
    "freiburg3": CameraIntrinsics(640, 480, 535.4, 539.2, 320.1, 247.6),
}


def read_timestamped_list(path: Path) -> list[tuple[float, list[str]]]:
    """Lines ``timestamp value...`` of a TUM list file, comments and blank lines dropped.

    Raises ValueError naming the file and line for a malformed timestamp.
    """
    out = []
    for line_no, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            stamp = float(parts[0])
        except ValueError as exc:
            raise ValueError(f"{path}:{line_no}: timestamp {parts[0]!r} is not a number") from exc
        out.append((stamp, parts[1:]))
    return out


def associate(
    first_s: np.ndarray, second_s: np.ndarray, *, max_dt_s: float, offset_s: float = 0.0
) -> list[tuple[int, int]]:
    """One-to-one pairs (i, j) of ``first_s[i]`` and ``second_s[j] + offset_s`` within ``max_dt_s``,
    chosen greedily by smallest time difference (TUM ``associate.py``); sorted by i."""
    a = np.asarray(first_s, dtype=np.float64)
    b = np.asarray(second_s, dtype=np.float64) + offset_s
    if a.size == 0 or b.size == 0:
        return []
    order = np.argsort(b)
    b_sorted = b[order]
    candidates = []
    for i, t in enumerate(a):
        lo = np.searchsorted(b_sorted, t - max_dt_s, side="left")
        hi = np.searchsorted(b_sorted, t + max_dt_s, side="right")
        for k in range(lo, hi):
            candidates.append((abs(b_sorted[k] - t), i, int(order[k])))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in candidates:
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        pairs.append((i, j))
    return sorted(pairs)


def _stamp_ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


class TumSource(IndexedFrameSource):
    """Frames of one TUM RGB-D sequence folder (see module docstring)."""

    def __init__(
        self,
        sequence_dir: str | Path,
        *,
        intrinsics: CameraIntrinsics | None = None,
        depth_scale: float = TUM_DEPTH_SCALE,
        max_dt_s: float = 0.02,
        pose_at: str = "depth",
        max_pose_gap_s: float = 0.1,
        stride: int = 1,
        max_frames: int | None = None,
    ) -> None:
        seq = Path(sequence_dir)
        if not seq.is_dir():
            raise FileNotFoundError(f"TUM sequence folder {seq} does not exist")
        missing = [f for f in ("rgb.txt", "depth.txt", "groundtruth.txt") if not (seq / f).is_file()]
        if missing:
            raise FileNotFoundError(f"{seq} is not a TUM RGB-D sequence: missing {missing}")
        if pose_at not in ("depth", "rgb"):
            raise ValueError(f"pose_at must be 'depth' or 'rgb', got {pose_at!r}")
        if max_dt_s <= 0:
            raise ValueError(f"max_dt_s must be positive, got {max_dt_s}")
        super().__init__(f"tum:{seq.name}", stride=stride, max_frames=max_frames)
        self.sequence_dir = seq
        self.depth_scale = float(depth_scale)
        self.pose_at = pose_at
        if intrinsics is None:
            key = next((k for k in TUM_INTRINSICS if k in seq.name), "freiburg1")
            intrinsics = TUM_INTRINSICS[key]
            logger.info("TUM %s: using %s default intrinsics", seq.name, key)
        self.intrinsics = intrinsics
        rgb = read_timestamped_list(seq / "rgb.txt")
        depth = read_timestamped_list(seq / "depth.txt")
        self._track, bad_pose_lines = self._read_groundtruth(seq / "groundtruth.txt", max_pose_gap_s)
        pairs = associate(np.array([t for t, _ in rgb]), np.array([t for t, _ in depth]), max_dt_s=max_dt_s)
        paired_rgb = {i for i, _ in pairs}
        # items: every rgb image; unpaired ones are counted as skips when iterated
        by_rgb = dict(pairs)
        self._items: list[tuple[float, str, float | None, str | None]] = []
        for i, (t_rgb, rest) in enumerate(rgb):
            j = by_rgb.get(i)
            name = rest[0] if rest else ""
            if j is None:
                self._items.append((t_rgb, name, None, None))
            else:
                self._items.append((t_rgb, name, depth[j][0], depth[j][1][0] if depth[j][1] else ""))
        if not self._items:
            raise ValueError(f"{seq / 'rgb.txt'} lists no images")
        logger.info(
            "TUM %s: %d rgb, %d depth, %d pairs within %.0f ms, %d poses (%d malformed lines)",
            seq.name,
            len(rgb),
            len(depth),
            len(paired_rgb),
            max_dt_s * 1e3,
            len(self._track),
            bad_pose_lines,
        )

    @staticmethod
    def _read_groundtruth(path: Path, max_gap_s: float) -> tuple[PoseTrack, int]:
        stamps, poses = [], []
        bad = 0
        for t, values in read_timestamped_list(path):
            try:
                v = np.array(values, dtype=np.float64)
                if v.size != 7 or not np.isfinite(v).all():
                    raise ValueError("need 7 finite numbers")
                poses.append(pose_from_tum(v[:3], v[3:]))
            except ValueError:
                bad += 1
                continue
            stamps.append(_stamp_ns(t))
        if not poses:
            raise ValueError(f"{path} holds no usable pose ('timestamp tx ty tz qx qy qz qw')")
        track = PoseTrack(np.array(stamps), np.array(poses), max_gap_ns=int(max_gap_s * 1e9))
        return track, bad

    def _num_items(self) -> int:
        return len(self._items)

    def _load(self, index: int) -> Frame:
        t_rgb, rgb_name, t_depth, depth_name = self._items[index]
        ctx = f"{self.sequence_dir.name} rgb {rgb_name} (t={t_rgb:.6f})"
        if t_depth is None or depth_name is None:
            raise SkipFrame("no_depth_match", f"{ctx}: no depth image within the association tolerance")
        t = t_depth if self.pose_at == "depth" else t_rgb
        stamp = _stamp_ns(t)
        T, reason = self._track.interpolate(stamp)
        if T is None:
            raise SkipFrame(reason, f"{ctx}: no ground-truth pose at t={t:.6f}")
        T = pose_or_skip(T, context=ctx)
        size = (self.intrinsics.width_px, self.intrinsics.height_px)
        depth = read_depth_u16(self.sequence_dir / depth_name, size=size)
        color = read_color(self.sequence_dir / rgb_name, size=size)
        return Frame(
            frame_id=index,
            stamp_ns=stamp,
            color=color,
            depth=depth,
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            T_world_cam=T,
            source=self.name,
        )
