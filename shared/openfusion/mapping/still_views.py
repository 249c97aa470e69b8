"""A candidate frame's render, reused while its camera stands still (``select_still_s``).

Scoring a candidate (:mod:`openfusion.mapping.coverage`) needs the map's region keys and
confidences rendered at the frame's pose: a ray cast, in one process or as a ``geometry/render``
request. On a large map that ray cast is the scoring's whole cost: Open3D 0.20's CPU ray cast
costs in proportion to the blocks the grid holds (docs/EVAL.md, "Scoring cost against the gt
encoder"), 50-75 ms at 90,000 resident blocks on a 2-core box. A robot that stands still (waiting
at a door, while its arm works, while it charges) sends 30 frames a second from one pose, and each
of them asked for the same render.

What a candidate's render shows changes only with the pose, the labels or the surface in view; the
kept render is reused while none of them changed, and only for a while:
    - the pose: the kept render is reused only within ``select_still_m`` and
      ``select_still_deg`` of the pose it was rendered at (compared with that pose, not the last
      frame's, so a slow drift cannot creep away from it);
    - the labels: a semantic update or a merge. The caller passes a ``labels_version``
      that changes with them (:class:`~openfusion.mapping.selection.FrameSelector` counts the
      updates and merges it is told of; the semantic service the updates it sent and its
      dictionary's version), and a render kept under another version is not reused;
    - the surface in view: a person walks into view, a door opens. The frames' own depth
      shows that, compared with the depth of the frame the kept render was made for (the same pose,
      so the same pixels): of the pixels both see surface at, at most :data:`CHANGED_SHARE` may
      differ by more than :data:`DEPTH_TOL_M` + :data:`DEPTH_TOL_PER_M` x depth, and at most
      :data:`NEW_SHARE` of this frame's surface pixels may be where that frame saw none. The
      tolerance is about 4 sigma of a Kinect's axial noise (sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2
      m: 2.6 cm at 4 m). Measured on the built-in room with its depth noise, frames of a still
      camera at 64 px: 0.1-0.5 % of the pixels differ, 2.1-2.6 % are surface where the other frame
      had a hole; something that steps in front of the camera changes far more. (Comparing with the
      rendered depth instead was measured too: the map's holes and depth edges, where a 64 px
      sample of the frame and the render's ray fall on either side, made 3-6 % disagree.)
    - for a while: at most ``select_still_s`` of frame time; whatever the rules above miss (a robot's join
      transform corrected by a re-check, an update geometry had not applied yet when the kept
      render was made, the map reset or loaded by a control request) lasts no longer than that.
      2 s at 30 fps replaces 60 ray casts with one.

A render made before its frame's surface was integrated (the services score a frame as it comes)
needs no rule of its own: the scorer reads only the render's keys and confidences, and a pixel
where the render has a hole scores as one where it shows surface without a label; labels come
only with updates, which change the version.

A reused render gives the same score the scorer would give the same maps: only the render is
reused; the frame's own depth, its stamp (staleness) and the record of what was encoded are the
frame's and the scorer's own. One view kept per robot: a few tens of kilobytes.

Written here: no library keeps renders of a semantic map.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np

from openfusion.frame import CameraIntrinsics

#: Two frames' depths at one pixel agree within this many metres plus DEPTH_TOL_PER_M x depth.
DEPTH_TOL_M = 0.03
DEPTH_TOL_PER_M = 0.02
#: A still camera's frame reuses the kept render when at most this share of the pixels both frames
#: see surface at disagree...
CHANGED_SHARE = 0.02
#: ...and at most this share of its surface pixels are where the kept frame saw none.
NEW_SHARE = 0.1


@dataclass
class _Kept:
    T_world_cam: np.ndarray
    size: tuple[int, int, float, float, float, float]  # the scored view's intrinsics
    labels_version: Hashable
    stamp_s: float  # frame time it was rendered for
    depth_m: np.ndarray  # the frame's own depth at the scored size
    rendered: Any  # a RenderedView or a render reply: key_map, conf_map, depth_m (0 = none), maybe T_map_cam


def pose_moved(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two camera poses."""
    dt = float(np.linalg.norm(np.asarray(T_a)[:3, 3] - np.asarray(T_b)[:3, 3]))
    R = np.asarray(T_a)[:3, :3].T @ np.asarray(T_b)[:3, :3]
    cos = (float(np.trace(R)) - 1.0) / 2.0
    return dt, math.degrees(math.acos(max(-1.0, min(1.0, cos))))


def _valid(depth_m: np.ndarray) -> np.ndarray:
    d = np.asarray(depth_m, np.float32)
    return np.isfinite(d) & (d > 0)


def same_surface(kept_depth_m: np.ndarray, depth_m: np.ndarray) -> bool:
    """Whether two frames from one pose see the same surface (module docstring)."""
    a = np.asarray(kept_depth_m, np.float32)
    b = np.asarray(depth_m, np.float32)
    if a.shape != b.shape:
        return False
    va, vb = _valid(a), _valid(b)
    both = va & vb
    n_b, n_both = int(vb.sum()), int(both.sum())
    if n_b == 0 or n_both == 0:
        return False
    changed = np.abs(b[both] - a[both]) > DEPTH_TOL_M + DEPTH_TOL_PER_M * a[both]
    return int(changed.sum()) <= CHANGED_SHARE * n_both and int((vb & ~va).sum()) <= NEW_SHARE * n_b


class StillViews:
    """The last render of each robot's candidate view, and whether the next candidate may reuse it
    (module docstring). Thread-safe: the semantic service scores several candidates at once."""

    def __init__(self, *, still_s: float | None, still_m: float, still_deg: float) -> None:
        self.still_s = still_s
        self.still_m = float(still_m)
        self.still_deg = float(still_deg)
        self._lock = threading.Lock()
        self._kept: dict[str, _Kept] = {}
        self.reused = 0  # candidates scored on a kept render (not rendered again)

    @property
    def enabled(self) -> bool:
        return self.still_s is not None and self.still_s > 0

    @staticmethod
    def _size(K: CameraIntrinsics) -> tuple[int, int, float, float, float, float]:
        return (K.width_px, K.height_px, K.fx, K.fy, K.cx, K.cy)

    def render(self, render: Callable[[np.ndarray, CameraIntrinsics], Any], robot: str, T_world_cam: np.ndarray,
               K: CameraIntrinsics, depth_m: np.ndarray, stamp_s: float, labels_version: Hashable | None) -> Any:
        """The map's render of this candidate's view: the robot's kept one when :meth:`reuse` allows,
        else ``render(T_world_cam, K)``, kept for the next candidates. ``labels_version`` None (a
        caller that does not know it): always rendered, nothing kept."""
        if labels_version is None:
            return render(T_world_cam, K)
        rendered = self.reuse(robot, T_world_cam, K, depth_m, stamp_s, labels_version)
        if rendered is None:
            rendered = render(T_world_cam, K)
            self.keep(robot, T_world_cam, K, depth_m, stamp_s, labels_version, rendered)
        return rendered

    def reuse(self, robot: str, T_world_cam: np.ndarray, K: CameraIntrinsics, depth_m: np.ndarray, stamp_s: float,
              labels_version: Hashable) -> Any | None:
        """The kept render of ``robot``'s view when this candidate (pose, scored-size depth, frame
        time, the caller's labels version) may use it, else None."""
        if not self.enabled:
            return None
        with self._lock:
            kept = self._kept.get(robot)
        if (kept is None or kept.labels_version != labels_version or kept.size != self._size(K)
                or not 0.0 <= stamp_s - kept.stamp_s <= float(self.still_s)):  # type: ignore[arg-type]
            return None
        moved_m, turned_deg = pose_moved(kept.T_world_cam, T_world_cam)
        if moved_m > self.still_m or turned_deg > self.still_deg:
            return None
        if not same_surface(kept.depth_m, depth_m):
            return None
        with self._lock:
            self.reused += 1
        return kept.rendered

    def keep(self, robot: str, T_world_cam: np.ndarray, K: CameraIntrinsics, depth_m: np.ndarray, stamp_s: float,
             labels_version: Hashable, rendered: Any) -> None:
        """``rendered`` was just made for this view (``depth_m``: the frame's at the scored size): the
        one the robot's next candidates compare with."""
        if not self.enabled:
            return
        kept = _Kept(np.array(T_world_cam, np.float64), self._size(K), labels_version, float(stamp_s),
                     np.array(depth_m, np.float32), rendered)
        with self._lock:
            self._kept[robot] = kept

    def forget(self) -> None:
        """Drop every kept render (the map was reset or loaded)."""
        with self._lock:
            self._kept.clear()
