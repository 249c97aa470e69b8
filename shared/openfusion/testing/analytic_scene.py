"""Analytic box scenes rendered exactly, for the map core's tests and benchmarks.

A scene is a room (the inside of a box, one instance per face) plus axis-aligned boxes (furniture).
Depth is the exact ray/box intersection, so reconstructions can be compared with the true surface.
World frame: metres, z up, floor at z = 0. Cameras use OpenCV axes (x right, y down, z forward).

This is a test fixture, not the project's synthetic world (``openfusion.sources.synthetic``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import look_at

_FACE_NAMES = ("wall", "wall", "wall", "wall", "floor", "ceiling")  # -x, +x, -y, +y, -z, +z


@dataclass(frozen=True)
class Box:
    """Axis-aligned box seen from outside, one instance id and category."""

    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]
    instance_id: int
    category: str
    color: tuple[int, int, int] = (180, 120, 60)

    def contains(self, points: np.ndarray, *, tol_m: float = 0.0) -> np.ndarray:
        lo = np.asarray(self.min_m) - tol_m
        hi = np.asarray(self.max_m) + tol_m
        return ((points >= lo) & (points <= hi)).all(axis=1)

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance of points to the box surface."""
        lo, hi = np.asarray(self.min_m), np.asarray(self.max_m)
        outside = np.maximum(np.maximum(lo - points, points - hi), 0.0)
        d_out = np.linalg.norm(outside, axis=1)
        d_in = np.minimum(points - lo, hi - points).min(axis=1)
        inside = (points >= lo).all(axis=1) & (points <= hi).all(axis=1)
        return np.where(inside, np.abs(d_in), d_out)


@dataclass(frozen=True)
class Room:
    """The inside of a box; faces -x, +x, -y, +y get ``wall_ids``, -z floor, +z ceiling."""

    size_m: tuple[float, float, float] = (6.0, 5.0, 2.8)
    face_ids: tuple[int, int, int, int, int, int] = (1, 2, 3, 4, 5, 6)
    color: tuple[int, int, int] = (200, 200, 190)

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        size = np.asarray(self.size_m)
        return np.minimum(points, size - points).min(axis=1)


@dataclass
class AnalyticScene:
    """A room plus boxes; :meth:`render` gives exact depth (m), instance ids and colors."""

    room: Room | None = field(default_factory=Room)
    boxes: list[Box] = field(default_factory=list)

    @property
    def categories(self) -> dict[int, str]:
        cats: dict[int, str] = {}
        if self.room is not None:
            for face, iid in enumerate(self.room.face_ids):
                cats[iid] = _FACE_NAMES[face]
        for box in self.boxes:
            cats[box.instance_id] = box.category
        return cats

    def render(
        self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(depth (h, w) float32 metres, 0 = nothing; instance (h, w) int32; color (h, w, 3) uint8)."""
        h, w = intrinsics.height_px, intrinsics.width_px
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        d_cam = np.stack(
            [(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones_like(u)], -1
        )
        d_cam = d_cam.reshape(-1, 3)
        R = np.asarray(T_world_cam)[:3, :3]
        origin = np.asarray(T_world_cam)[:3, 3]
        d = d_cam @ R.T  # world directions scaled so that t == camera depth
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
        n = len(d)
        best_t = np.full(n, np.inf)
        inst = np.zeros(n, np.int32)
        color = np.zeros((n, 3), np.uint8)
        if self.room is not None:
            lo = np.zeros(3)
            hi = np.asarray(self.room.size_m, dtype=np.float64)
            t1 = (lo - origin) * inv
            t2 = (hi - origin) * inv
            tfar = np.maximum(t1, t2)
            t_exit = tfar.min(axis=1)
            axis = tfar.argmin(axis=1)
            positive = d[np.arange(n), axis] > 0
            face = axis * 2 + positive.astype(np.int64)
            ok = np.isfinite(t_exit) & (t_exit > 0)
            best_t[ok] = t_exit[ok]
            inst[ok] = np.asarray(self.room.face_ids, np.int32)[face[ok]]
            color[ok] = self.room.color
        for box in self.boxes:
            lo = np.asarray(box.min_m, np.float64)
            hi = np.asarray(box.max_m, np.float64)
            t1 = (lo - origin) * inv
            t2 = (hi - origin) * inv
            t_near = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf).max(axis=1)
            t_far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf).min(axis=1)
            hit = (t_near <= t_far) & (t_near > 1e-6) & (t_near < best_t)
            best_t[hit] = t_near[hit]
            inst[hit] = box.instance_id
            color[hit] = box.color
        depth = np.where(np.isfinite(best_t), best_t, 0.0).astype(np.float32).reshape(h, w)
        inst[depth.reshape(-1) <= 0] = 0
        return depth, inst.reshape(h, w), color.reshape(h, w, 3)

    def make_frame(
        self,
        T_world_cam: np.ndarray,
        intrinsics: CameraIntrinsics,
        *,
        frame_id: int = 0,
        depth_scale: float = 1000.0,
    ) -> Frame:
        """A :class:`Frame` with uint16 depth (``depth_scale`` units per metre) and ground-truth instances."""
        depth_m, inst, color = self.render(T_world_cam, intrinsics)
        depth = np.clip(np.round(depth_m * depth_scale), 0, 65535).astype(np.uint16)
        return Frame(
            frame_id=frame_id,
            stamp_ns=frame_id * 33_333_333,
            color=color,
            depth=depth,
            depth_scale=depth_scale,
            intrinsics=intrinsics,
            T_world_cam=np.asarray(T_world_cam, np.float64),
            instance=inst,
            instance_categories=self.categories,
            source="analytic",
        )

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) of points to the nearest scene surface."""
        dists = []
        if self.room is not None:
            dists.append(self.room.surface_distance(points))
        dists.extend(box.surface_distance(points) for box in self.boxes)
        return np.min(np.stack(dists), axis=0)

    def instance_at(self, points: np.ndarray) -> np.ndarray:
        """Instance id of the nearest surface to each point (0 when the scene is empty)."""
        candidates = []
        ids = []
        if self.room is not None:
            size = np.asarray(self.room.size_m)
            face_d = np.stack(
                [
                    points[:, 0],
                    size[0] - points[:, 0],
                    points[:, 1],
                    size[1] - points[:, 1],
                    points[:, 2],
                    size[2] - points[:, 2],
                ],
                axis=1,
            )
            face = face_d.argmin(axis=1)
            candidates.append(face_d.min(axis=1))
            ids.append(np.asarray(self.room.face_ids)[face])
        for box in self.boxes:
            candidates.append(box.surface_distance(points))
            ids.append(np.full(len(points), box.instance_id))
        if not candidates:
            return np.zeros(len(points), np.int32)
        stacked = np.stack(candidates)
        nearest = stacked.argmin(axis=0)
        return np.stack(ids)[nearest, np.arange(len(points))].astype(np.int32)


def furnished_room(seed: int = 0) -> AnalyticScene:
    """A 6 x 5 x 2.8 m room with ten pieces of furniture (deterministic for a seed)."""
    rng = np.random.default_rng(seed)
    pieces = [
        ((0.3, 0.3, 0.0), (1.9, 1.1, 0.75), "table"),
        ((4.6, 0.2, 0.0), (5.8, 0.8, 1.9), "cabinet"),
        ((0.2, 3.6, 0.0), (2.2, 4.8, 0.5), "bed"),
        ((2.6, 2.0, 0.0), (3.1, 2.5, 0.9), "chair"),
        ((3.4, 2.0, 0.0), (3.9, 2.5, 0.9), "chair"),
        ((2.4, 2.8, 0.0), (4.0, 3.6, 0.72), "desk"),
        ((5.3, 3.0, 0.0), (5.8, 4.8, 1.2), "shelf"),
        ((0.2, 2.0, 0.0), (0.6, 2.6, 1.1), "lamp"),
        ((4.4, 4.3, 0.0), (5.0, 4.8, 0.45), "box"),
        ((1.2, 0.5, 0.75), (1.5, 0.8, 1.05), "monitor"),
    ]
    boxes = []
    for i, (lo, hi, cat) in enumerate(pieces):
        color = tuple(int(c) for c in rng.integers(40, 230, size=3))
        boxes.append(Box(lo, hi, instance_id=10 + i, category=cat, color=color))
    return AnalyticScene(room=Room(), boxes=boxes)


def two_objects_room() -> AnalyticScene:
    """A 3 x 3 x 2.5 m room with a chair and a table, and four poses that see both
    (:data:`TWO_OBJECTS_POSES`): the semantic step's tests map it."""
    return AnalyticScene(
        room=Room(size_m=(3.0, 3.0, 2.5), face_ids=(1, 1, 1, 1, 2, 3)),
        boxes=[
            Box((0.7, 1.8, 0.0), (1.3, 2.3, 0.8), 10, "chair", (200, 40, 40)),
            Box((1.8, 1.6, 0.0), (2.5, 2.2, 0.5), 11, "table", (40, 200, 40)),
        ],
    )


#: The camera the semantic step's tests map :func:`two_objects_room` with, and the size and
#: embedding space of their observations (:func:`observation_from_instances`).
TWO_OBJECTS_CAMERA = CameraIntrinsics(320, 240, 262.5, 262.5, 159.5, 119.5)
TWO_OBJECTS_OBS_HW = (60, 80)
ANALYTIC_SPACE = "analytic-test"

#: Four poses of :func:`two_objects_room` that see the chair and the table from different sides.
TWO_OBJECTS_POSES = [
    look_at((1.5, 0.3, 1.4), (1.5, 2.0, 0.4)),
    look_at((0.5, 0.5, 1.3), (1.4, 2.0, 0.4)),
    look_at((2.6, 0.6, 1.3), (1.6, 2.0, 0.4)),
    look_at((1.5, 0.2, 1.6), (1.5, 2.2, 0.2)),
]


def orbit_poses(
    num_frames: int, *, center=(3.0, 2.5, 1.4), radius_m: float = 1.2, height_m: float = 1.5
) -> list[np.ndarray]:
    """Poses on a circle around ``center`` looking outward at the walls (a room scan)."""
    poses = []
    c = np.asarray(center, np.float64)
    for i in range(num_frames):
        a = 2 * np.pi * i / max(num_frames, 1)
        eye = c + np.array([radius_m * np.cos(a) * 0.3, radius_m * np.sin(a) * 0.3, height_m - c[2]])
        target = c + np.array([np.cos(a) * 3.0, np.sin(a) * 3.0, -0.9])
        poses.append(look_at(eye, target))
    return poses


@dataclass
class SimpleObservation:
    """Region observation (same fields as ``openfusion.encoders.RegionObservation``)."""

    conf_maps: np.ndarray  # (n, h, w) float32 in [0, 1]
    embeddings: np.ndarray  # (n, d) float32 unit norm
    embedding_space: str
    labels: list[str] | None = None


def category_embedding(category: str, dim: int = 32) -> np.ndarray:
    """Deterministic unit vector per category name (a stand-in for a text encoder)."""
    seed = int.from_bytes(category.encode()[:8].ljust(8, b"\0"), "little") ^ len(category)
    v = np.random.default_rng(seed).standard_normal(dim).astype(np.float32)
    return v / np.linalg.norm(v)


def observation_from_instances(
    instance: np.ndarray,
    categories: dict[int, str],
    *,
    out_size: tuple[int, int],
    dim: int = 32,
    conf: float = 0.9,
    min_pixels: int = 4,
    embedding_space: str = ANALYTIC_SPACE,
) -> SimpleObservation:
    """Ground-truth regions: one confidence map per instance at ``out_size`` (h, w), nearest-sampled."""
    h, w = out_size
    H, W = instance.shape
    rows = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    small = instance[rows][:, cols]
    ids = [int(i) for i in np.unique(small) if i != 0 and (small == i).sum() >= min_pixels]
    maps = (
        np.stack([(small == i).astype(np.float32) * conf for i in ids])
        if ids
        else np.zeros((0, h, w), np.float32)
    )
    labels = [categories.get(i, f"instance {i}") for i in ids]
    emb = (
        np.stack([category_embedding(lab, dim) for lab in labels]) if ids else np.zeros((0, dim), np.float32)
    )
    return SimpleObservation(maps, emb, embedding_space, labels)
