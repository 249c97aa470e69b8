"""Pose helpers: the one pose check, inversion, look-at, quaternions (x, y, z, w order, as TUM
and ROS write them), SLERP and pose interpolation.

Poses are 4x4 float64 camera-to-world matrices (``T_world_cam``) unless a name says otherwise.
Every place that accepts a pose (frames, wire messages, the volume, readers, the evaluation,
virtual cameras) checks it with :func:`check_pose`.
"""

from __future__ import annotations

import numpy as np

from openfusion.errors import OpenFusionError

#: Tolerance of the rigidity check: ``R @ R.T`` may differ from the identity by this much
#: (poses written as text with 6 decimals pass).
ROTATION_ATOL = 1e-3


class InvalidPoseError(OpenFusionError, ValueError):
    """A pose that is not a finite 4x4 rigid transform (the message says which part failed)."""


def check_pose(T: np.ndarray, *, what: str = "T_world_cam", rotation_atol: float = ROTATION_ATOL) -> np.ndarray:
    """``T`` as a float64 4x4 copy, or :class:`InvalidPoseError` naming ``what`` and the problem:
    not 4x4, inf/NaN entries, a last row other than [0 0 0 1], a rotation that is not orthonormal."""
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4) or not np.isfinite(M).all():
        raise InvalidPoseError(f"{what} must be a finite 4x4 matrix, got shape {M.shape}"
                               + ("" if M.shape != (4, 4) else " with inf/NaN entries"))
    if np.abs(M[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        raise InvalidPoseError(f"{what} last row must be [0 0 0 1], got {M[3].tolist()}")
    R = M[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > rotation_atol:
        raise InvalidPoseError(f"{what} rotation is not orthonormal (not a rigid transform)")
    return M.copy()


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (``T_cam_world`` of a ``T_world_cam``)."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """3x3 rotation of a (possibly unnormalised) quaternion ``(x, y, z, w)``; (..., 4) -> (..., 3, 3)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < 1e-12):
        raise ValueError("quaternion has zero norm")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    R = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` with w >= 0 of a 3x3 rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[0, 0], R[1, 1], R[2, 2]
    trace = m00 + m11 + m22
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif m00 > m11 and m00 > m22:
        s = 2.0 * np.sqrt(1.0 + m00 - m11 - m22)
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif m11 > m22:
        s = 2.0 * np.sqrt(1.0 + m11 - m00 - m22)
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m22 - m00 - m11)
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def pose_from_tum(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 pose from a translation and an ``(x, y, z, w)`` quaternion."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q_xyzw)
    T[:3, 3] = t_xyz
    return T


def slerp(q0_xyzw: np.ndarray, q1_xyzw: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions (shortest arc), alpha in [0, 1]."""
    q0 = np.asarray(q0_xyzw, dtype=np.float64)
    q1 = np.asarray(q1_xyzw, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly identical: normalised lerp is exact to ~1e-8 here
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(dot, 1.0))
    s = np.sin(theta)
    return (np.sin((1.0 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / s


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, alpha: float) -> np.ndarray:
    """Pose between ``T0`` (alpha 0) and ``T1`` (alpha 1): linear translation, SLERP rotation."""
    q = slerp(matrix_to_quat(T0[:3, :3]), matrix_to_quat(T1[:3, :3]), alpha)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q)
    T[:3, 3] = (1.0 - alpha) * T0[:3, 3] + alpha * T1[:3, 3]
    return T


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the relative rotation between two 3x3 rotations, in degrees."""
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


_Z_UP = (0.0, 0.0, 1.0)


def look_at(position: np.ndarray, target: np.ndarray, *, up: tuple[float, float, float] = _Z_UP) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) at ``position`` looking at ``target``."""
    up = np.asarray(up, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, position
    return T


class PoseTrack:
    """A time-sorted pose sequence answering "pose at time t" by SLERP/linear interpolation.

    ``max_gap_ns``: interpolation across a gap between samples longer than this is refused
    (returns None), so a tracking dropout never yields a made-up pose.
    """

    def __init__(self, stamps_ns: np.ndarray, poses: np.ndarray, *, max_gap_ns: int | None = None) -> None:
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        poses = np.asarray(poses, dtype=np.float64)
        if stamps.ndim != 1 or poses.shape != (stamps.size, 4, 4):
            raise ValueError(f"need N stamps and N 4x4 poses, got {stamps.shape} and {poses.shape}")
        order = np.argsort(stamps, kind="stable")
        self.stamps_ns = stamps[order]
        self.poses = poses[order]
        self.max_gap_ns = max_gap_ns
        self._quats = np.array([matrix_to_quat(T[:3, :3]) for T in self.poses]) if stamps.size else np.zeros((0, 4))

    def __len__(self) -> int:
        return int(self.stamps_ns.size)

    def interpolate(self, stamp_ns: int) -> tuple[np.ndarray | None, str]:
        """(pose, "") or (None, reason) with reason ``outside_pose_range`` or ``pose_gap``."""
        stamps = self.stamps_ns
        if stamps.size == 0 or stamp_ns < stamps[0] or stamp_ns > stamps[-1]:
            return None, "outside_pose_range"
        i = int(np.searchsorted(stamps, stamp_ns, side="left"))
        if stamps[i] == stamp_ns:
            return self.poses[i].copy(), ""
        t0, t1 = int(stamps[i - 1]), int(stamps[i])
        if self.max_gap_ns is not None and t1 - t0 > self.max_gap_ns:
            return None, "pose_gap"
        alpha = (stamp_ns - t0) / (t1 - t0)
        q = slerp(self._quats[i - 1], self._quats[i], alpha)
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(q)
        T[:3, 3] = (1.0 - alpha) * self.poses[i - 1, :3, 3] + alpha * self.poses[i, :3, 3]
        return T, ""

    def nearest(self, stamp_ns: int) -> tuple[int, int]:
        """(index, |dt| in ns) of the sample nearest in time; index -1 when empty."""
        stamps = self.stamps_ns
        if stamps.size == 0:
            return -1, 0
        i = int(np.searchsorted(stamps, stamp_ns))
        best = -1
        best_dt = None
        for j in (i - 1, i):
            if 0 <= j < stamps.size:
                dt = abs(int(stamps[j]) - stamp_ns)
                if best_dt is None or dt < best_dt:
                    best, best_dt = j, dt
        return best, int(best_dt or 0)
