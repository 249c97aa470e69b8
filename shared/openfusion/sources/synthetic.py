"""The embedded synthetic world: a procedurally furnished room rendered to RGB-D on the CPU.

What it is
    ``SyntheticWorld(seed=N)`` builds one closed room (walls, floor, ceiling) and furnishes it
    with about a dozen kinds of objects (door, window, picture, bed + pillows, sofa,
    bookshelf with books, cabinet, desk + monitor + office chair, table + chairs, lamp,
    plant, trash can), each made of Open3D boxes/cylinders/spheres. Everything is
    deterministic by seed: the same seed gives the same room, frames and ground truth,
    bit for bit, on the same machine.

Conventions (canonical, design §3; nothing is converted): world metres, z up, the room spans
``[0, W] x [0, D] x [0, H]``; cameras use OpenCV axes; poses are camera-to-world
``T_world_cam``. Depth is uint16 millimetres (``depth_scale = 1000``, Kinect-like).

Rendering
    ``o3d.t.geometry.RaycastingScene`` (Embree, headless, built once per world and cached).
    Color = per-part base color x procedural texture (wood planks, fabric, noise) x Lambert
    shading. Depth noise (``depth_noise=True``) follows the Kinect axial model
    sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m, with holes: random dropouts, pixels at grazing
    angles (|cos| < 0.15) and most pixels at depth discontinuities; depth outside
    [0.25, 8.0] m is 0. Instance images are exact (int32, 0 = none).

Ground truth
    ``ground_truth_surface(spacing_m)`` samples the meshes uniformly (one point per
    ``spacing_m``^2 of area, area-weighted random positions) and by default keeps only points
    that can be seen from inside the room (hidden faces such as box bottoms on the floor or
    the floor under the bed are dropped, so completeness is measured against what a camera
    could observe).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import look_at
from openfusion.sources.base import IndexedFrameSource

logger = logging.getLogger(__name__)

DEPTH_SCALE = 1000.0
DEPTH_MIN_M = 0.25
DEPTH_MAX_M = 8.0
GRAZING_COS = 0.15

# texture kinds (index into per-geometry texture weights)
_TEXTURES = ("plain", "wood", "fabric", "noise", "planks", "paint")


@dataclass
class Part:
    """One rigid piece of an object: a triangle mesh with a base color and texture kind."""

    vertices: np.ndarray  # (V, 3) float64 world metres
    triangles: np.ndarray  # (T, 3) int32
    rgb: tuple[float, float, float]
    texture: str = "plain"


@dataclass
class WorldObject:
    """An instance: id, raw category name and its parts."""

    instance_id: int
    category: str
    parts: list[Part] = field(default_factory=list)
    footprint: tuple[float, float, float, float] | None = None  # (x0, y0, x1, y1) on the floor
    height_m: float = 0.0


@dataclass
class GroundTruthSurface:
    """Labelled points on the world's surfaces."""

    points: np.ndarray  # (N, 3) float32 world metres
    instance_ids: np.ndarray  # (N,) int32, never 0
    categories: dict[int, str]  # instance id -> raw category


@dataclass
class RenderedView:
    """Noise-free render: depth in metres (0 = miss), instance ids, color, |cos| of the view angle."""

    color: np.ndarray  # (h, w, 3) uint8
    depth_m: np.ndarray  # (h, w) float32, 0 where nothing was hit
    instance: np.ndarray  # (h, w) int32
    view_cos: np.ndarray  # (h, w) float32


# ----------------------------------------------------------------------------------- meshes


def _mesh_arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(mesh.vertices, dtype=np.float64).copy(), np.asarray(mesh.triangles, dtype=np.int32).copy()


def _box(x: float, y: float, z0: float, sx: float, sy: float, sz: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box centred at (x, y) in the plane, bottom at z0, local coordinates."""
    v, t = _mesh_arrays(o3d.geometry.TriangleMesh.create_box(sx, sy, sz))
    return v + np.array([x - sx / 2, y - sy / 2, z0]), t


def _cylinder(x: float, y: float, z0: float, radius: float, height: float, resolution: int = 16):
    v, t = _mesh_arrays(o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution, 1))
    return v + np.array([x, y, z0 + height / 2]), t


def _sphere(x: float, y: float, z: float, radius: float, resolution: int = 8):
    v, t = _mesh_arrays(o3d.geometry.TriangleMesh.create_sphere(radius, resolution))
    return v + np.array([x, y, z]), t


def _quad(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles over 4 corners given counter-clockwise seen from the visible side."""
    return np.asarray(corners, dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


def _jitter(rng: np.random.Generator, rgb: tuple[float, float, float], amount: float = 0.08):
    c = np.clip(np.asarray(rgb) + rng.uniform(-amount, amount, 3), 0.03, 0.97)
    return (float(c[0]), float(c[1]), float(c[2]))


class _Builder:
    """Collects parts in an object's local frame (front = +y, floor z = 0), then places them."""

    def __init__(self) -> None:
        self.parts: list[tuple[np.ndarray, np.ndarray, tuple[float, float, float], str]] = []

    def add(self, geom: tuple[np.ndarray, np.ndarray], rgb, texture: str = "plain") -> None:
        self.parts.append((geom[0], geom[1], rgb, texture))

    def place(self, x: float, y: float, yaw: float, z: float = 0.0) -> list[Part]:
        c, s = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out = []
        for v, t, rgb, tex in self.parts:
            out.append(Part(v @ R.T + np.array([x, y, z]), t, rgb, tex))
        return out

    def local_bounds(self) -> np.ndarray:
        allv = np.concatenate([p[0] for p in self.parts])
        return np.stack([allv.min(0), allv.max(0)])


# Base colors per category (RGB 0..1); instances jitter around them.
_PALETTE: dict[str, tuple[float, float, float]] = {
    "wall": (0.86, 0.84, 0.78),
    "floor": (0.62, 0.45, 0.30),
    "ceiling": (0.93, 0.93, 0.92),
    "door": (0.55, 0.38, 0.22),
    "window": (0.70, 0.85, 0.95),
    "picture": (0.25, 0.20, 0.15),
    "bed": (0.45, 0.30, 0.20),
    "pillow": (0.90, 0.90, 0.95),
    "sofa": (0.25, 0.35, 0.55),
    "bookshelf": (0.50, 0.35, 0.20),
    "cabinet": (0.80, 0.78, 0.70),
    "desk": (0.70, 0.55, 0.35),
    "monitor": (0.08, 0.08, 0.10),
    "office chair": (0.15, 0.15, 0.18),
    "table": (0.60, 0.42, 0.25),
    "chair": (0.75, 0.20, 0.15),
    "lamp": (0.95, 0.85, 0.55),
    "plant": (0.20, 0.55, 0.20),
    "trash can": (0.35, 0.40, 0.45),
}

CATEGORIES: tuple[str, ...] = tuple(_PALETTE)
"""Every raw category the synthetic world can contain (walls/floor/ceiling included)."""


def _build_table(rng, w, d, h):
    b = _Builder()
    col = _jitter(rng, _PALETTE["table"])
    b.add(_box(0, 0, h - 0.04, w, d, 0.04), col, "wood")
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.add(_box(sx * (w / 2 - 0.06), sy * (d / 2 - 0.06), 0, 0.05, 0.05, h - 0.04), col, "wood")
    return b


def _build_chair(rng, col):
    b = _Builder()
    w, d, hs = 0.44, 0.44, 0.45
    b.add(_box(0, 0, hs - 0.04, w, d, 0.04), col, "fabric")
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.add(_box(sx * (w / 2 - 0.03), sy * (d / 2 - 0.03), 0, 0.035, 0.035, hs - 0.04), (0.2, 0.2, 0.2))
    b.add(_box(0, -d / 2 + 0.02, hs, w, 0.04, 0.45), col, "fabric")
    return b


def _build_office_chair(rng):
    b = _Builder()
    col = _jitter(rng, _PALETTE["office chair"], 0.05)
    metal = (0.55, 0.55, 0.58)
    for k in range(5):
        a = 2 * math.pi * k / 5
        v, t = _box(0.16, 0, 0.03, 0.32, 0.04, 0.03)
        c, s = math.cos(a), math.sin(a)
        v = v @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
        b.add((v, t), metal)
    b.add(_cylinder(0, 0, 0.06, 0.03, 0.36, 10), metal)
    b.add(_box(0, 0, 0.42, 0.5, 0.5, 0.08), col, "fabric")
    b.add(_box(0, -0.23, 0.55, 0.46, 0.06, 0.55), col, "fabric")
    return b


def _build_desk(rng, w, d, h):
    b = _Builder()
    col = _jitter(rng, _PALETTE["desk"])
    b.add(_box(0, 0, h - 0.03, w, d, 0.03), col, "wood")
    for sx in (-1, 1):
        b.add(_box(sx * (w / 2 - 0.015), 0, 0, 0.03, d, h - 0.03), col, "wood")
    b.add(_box(0, -d / 2 + 0.01, 0.25, w - 0.06, 0.02, h - 0.28), col, "wood")
    return b


def _build_monitor(rng):
    b = _Builder()
    col = _jitter(rng, _PALETTE["monitor"], 0.03)
    b.add(_box(0, 0, 0, 0.22, 0.16, 0.02), col)
    b.add(_box(0, -0.02, 0.02, 0.05, 0.03, 0.14), col)
    b.add(_box(0, 0.0, 0.12, 0.56, 0.03, 0.34), col, "noise")
    return b


def _build_sofa(rng, w, d):
    b = _Builder()
    col = _jitter(rng, _PALETTE["sofa"])
    b.add(_box(0, 0, 0.05, w, d, 0.38), col, "fabric")
    b.add(_box(0, -d / 2 + 0.11, 0.43, w, 0.22, 0.42), col, "fabric")
    for sx in (-1, 1):
        b.add(_box(sx * (w / 2 - 0.09), 0.11, 0.43, 0.18, d - 0.22, 0.2), col, "fabric")
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.add(_box(sx * (w / 2 - 0.05), sy * (d / 2 - 0.05), 0, 0.05, 0.05, 0.05), (0.15, 0.1, 0.05))
    return b


def _build_bed(rng, w, length):
    b = _Builder()
    col = _jitter(rng, _PALETTE["bed"])
    sheet = _jitter(rng, (0.85, 0.85, 0.80), 0.1)
    b.add(_box(0, 0, 0, w, length, 0.3), col, "wood")
    b.add(_box(0, 0.02, 0.3, w - 0.06, length - 0.1, 0.22), sheet, "fabric")
    b.add(_box(0, -length / 2 + 0.03, 0, w, 0.06, 1.0), col, "wood")
    return b


def _build_pillow(rng):
    b = _Builder()
    b.add(_box(0, 0, 0, 0.55, 0.35, 0.12), _jitter(rng, _PALETTE["pillow"], 0.06), "fabric")
    return b


def _build_bookshelf(rng, w, d, h):
    b = _Builder()
    col = _jitter(rng, _PALETTE["bookshelf"])
    t = 0.02
    for sx in (-1, 1):
        b.add(_box(sx * (w / 2 - t / 2), 0, 0, t, d, h), col, "wood")
    b.add(_box(0, -d / 2 + t / 2, 0, w - 2 * t, t, h), col, "wood")
    n_shelves = int(rng.integers(4, 6))
    levels = np.linspace(0.0, h - t, n_shelves + 1)
    for z in levels:
        b.add(_box(0, 0, z, w - 2 * t, d, t), col, "wood")
    # books on every shelf but the top board
    for z0, z1 in zip(levels[:-1], levels[1:], strict=True):
        x = -w / 2 + t + 0.01
        gap = z1 - z0 - t
        while x < w / 2 - t - 0.05:
            bw = float(rng.uniform(0.02, 0.05))
            if rng.random() < 0.12:  # leave an empty slot
                x += bw + 0.04
                continue
            bh = float(rng.uniform(0.55, 0.9)) * gap
            bd = float(rng.uniform(0.6, 0.85)) * (d - t)
            bc = tuple(float(c) for c in rng.uniform(0.1, 0.9, 3))
            b.add(_box(x + bw / 2, -d / 2 + t + bd / 2, z0 + t, bw, bd, bh), bc, "paint")
            x += bw + 0.003
    return b


def _build_cabinet(rng, w, d, h):
    b = _Builder()
    col = _jitter(rng, _PALETTE["cabinet"])
    b.add(_box(0, 0, 0, w, d, h), col, "paint")
    n_doors = 2 if w > 0.7 else 1
    for k in range(n_doors):
        x = -w / 2 + (k + 0.5) * w / n_doors + (0.1 if k == 0 and n_doors == 2 else -0.1 if n_doors == 2 else 0.2)
        b.add(_box(x, d / 2 + 0.01, h * 0.55, 0.02, 0.02, 0.12), (0.7, 0.7, 0.72))
    return b


def _build_lamp(rng):
    b = _Builder()
    metal = (0.3, 0.3, 0.32)
    b.add(_cylinder(0, 0, 0, 0.15, 0.03, 16), metal)
    b.add(_cylinder(0, 0, 0.03, 0.015, 1.4, 8), metal)
    b.add(_cylinder(0, 0, 1.35, 0.2, 0.28, 16), _jitter(rng, _PALETTE["lamp"], 0.05), "fabric")
    return b


def _build_plant(rng):
    b = _Builder()
    r = float(rng.uniform(0.14, 0.2))
    hp = float(rng.uniform(0.28, 0.4))
    b.add(_cylinder(0, 0, 0, r, hp, 16), _jitter(rng, (0.65, 0.35, 0.2), 0.08), "plain")
    leaf = _jitter(rng, _PALETTE["plant"], 0.08)
    for _ in range(int(rng.integers(3, 6))):
        rr = float(rng.uniform(0.12, 0.22))
        b.add(
            _sphere(float(rng.uniform(-0.1, 0.1)), float(rng.uniform(-0.1, 0.1)), hp + rr * 0.8 + float(rng.uniform(0, 0.35)), rr),
            leaf,
            "noise",
        )
    return b


def _build_trash_can(rng):
    b = _Builder()
    b.add(_cylinder(0, 0, 0, 0.15, 0.36, 16), _jitter(rng, _PALETTE["trash can"], 0.1), "plain")
    return b


def _build_door(rng, w, h):
    b = _Builder()
    col = _jitter(rng, _PALETTE["door"])
    b.add(_box(0, 0.02, 0, w, 0.04, h), col, "planks")
    b.add(_box(w / 2 - 0.1, 0.06, 1.0, 0.12, 0.04, 0.03), (0.75, 0.75, 0.7))
    return b


def _build_window(rng, w, h):
    b = _Builder()
    frame = (0.92, 0.92, 0.9)
    f = 0.06
    b.add(_box(0, 0.03, 0, w, 0.06, f), frame)
    b.add(_box(0, 0.03, h - f, w, 0.06, f), frame)
    for sx in (-1, 1):
        b.add(_box(sx * (w / 2 - f / 2), 0.03, f, f, 0.06, h - 2 * f), frame)
    b.add(_box(0, 0.03, h / 2 - 0.02, w - 2 * f, 0.05, 0.04), frame)
    b.add(_box(0, 0.01, f, w - 2 * f, 0.02, h - 2 * f), _jitter(rng, _PALETTE["window"], 0.05), "noise")
    return b


def _build_picture(rng, w, h):
    b = _Builder()
    b.add(_box(0, 0.015, 0, w, 0.03, h), _jitter(rng, _PALETTE["picture"], 0.05), "wood")
    canvas = tuple(float(c) for c in rng.uniform(0.2, 0.9, 3))
    b.add(_box(0, 0.035, 0.04, w - 0.08, 0.01, h - 0.08), canvas, "noise")
    return b


# ------------------------------------------------------------------------------------ world


class SyntheticWorld:
    """A furnished room, deterministic by ``seed``.

    ``room_size_m=(W, D, H)`` fixes the room size; by default it is drawn from the seed
    (W 5.5..7, D 4.5..6, H 2.6..3.0 m). ``.categories`` maps instance id -> raw category.
    """

    def __init__(self, seed: int = 0, *, room_size_m: tuple[float, float, float] | None = None) -> None:
        self.seed = int(seed)
        rng = np.random.default_rng([self.seed, 7])
        if room_size_m is None:
            room_size_m = (
                round(float(rng.uniform(5.5, 7.0)), 2),
                round(float(rng.uniform(4.5, 6.0)), 2),
                round(float(rng.uniform(2.6, 3.0)), 2),
            )
        W, D, H = (float(v) for v in room_size_m)
        if min(W, D) < 3.0 or H < 2.2:
            raise ValueError(f"room_size_m must be at least 3 x 3 x 2.2 m, got {room_size_m}")
        self.room_size_m = (W, D, H)
        self.objects: list[WorldObject] = []
        self._floor_rects: list[tuple[float, float, float, float]] = []
        self._wall_rects: dict[int, list[tuple[float, float, float, float]]] = {k: [] for k in range(4)}
        self._build_room()
        self._furnish(rng)
        self.categories: dict[int, str] = {o.instance_id: o.category for o in self.objects}
        self._lut_built = False
        self._gt_cache: dict[tuple[float, bool], GroundTruthSurface] = {}

    # ---------------------------------------------------------------- construction helpers

    def _new_object(self, category: str, parts: list[Part], **kw) -> WorldObject:
        obj = WorldObject(len(self.objects) + 1, category, parts, **kw)
        self.objects.append(obj)
        return obj

    def _build_room(self) -> None:
        W, D, H = self.room_size_m
        e = 0.01  # overlap at the corners so rays never slip through a crack
        wall_rgb = _PALETTE["wall"]
        # walls: 0 (y=0, faces +y), 1 (x=W, faces -x), 2 (y=D, faces -y), 3 (x=0, faces +x)
        quads = [
            [[-e, 0, -e], [W + e, 0, -e], [W + e, 0, H + e], [-e, 0, H + e]],
            [[W, -e, -e], [W, D + e, -e], [W, D + e, H + e], [W, -e, H + e]],
            [[W + e, D, -e], [-e, D, -e], [-e, D, H + e], [W + e, D, H + e]],
            [[0, D + e, -e], [0, -e, -e], [0, -e, H + e], [0, D + e, H + e]],
        ]
        for k, q in enumerate(quads):
            # orient so the normal points into the room: (p1-p0) x (p3-p0)
            q = np.array(q, dtype=np.float64)
            n = np.cross(q[1] - q[0], q[3] - q[0])
            inward = np.array([[0, 1, 0], [-1, 0, 0], [0, -1, 0], [1, 0, 0]][k], dtype=np.float64)
            if np.dot(n, inward) < 0:
                q = q[::-1]
            self._new_object("wall", [Part(*_quad(q), wall_rgb, "paint")])
        floor = np.array([[-e, -e, 0], [W + e, -e, 0], [W + e, D + e, 0], [-e, D + e, 0]], dtype=np.float64)
        self._new_object("floor", [Part(*_quad(floor), _PALETTE["floor"], "planks")])
        ceiling = np.array([[-e, -e, H], [-e, D + e, H], [W + e, D + e, H], [W + e, -e, H]], dtype=np.float64)
        self._new_object("ceiling", [Part(*_quad(ceiling), _PALETTE["ceiling"], "paint")])

    def _wall_frame(self, wall: int) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(origin, along-wall unit vector, yaw so local +y faces into the room, wall length)."""
        W, D, _ = self.room_size_m
        if wall == 0:
            return np.array([0.0, 0.0]), np.array([1.0, 0.0]), 0.0, W
        if wall == 1:
            return np.array([W, 0.0]), np.array([0.0, 1.0]), math.pi / 2, D
        if wall == 2:
            return np.array([W, D]), np.array([-1.0, 0.0]), math.pi, W
        return np.array([0.0, D]), np.array([0.0, -1.0]), -math.pi / 2, D

    @staticmethod
    def _overlap(a, b, margin: float = 0.0) -> bool:
        return a[0] < b[2] + margin and b[0] < a[2] + margin and a[1] < b[3] + margin and b[1] < a[3] + margin

    def _floor_free(self, rect, margin: float = 0.05) -> bool:
        W, D, _ = self.room_size_m
        if rect[0] < -1e-6 or rect[1] < -1e-6 or rect[2] > W + 1e-6 or rect[3] > D + 1e-6:
            return False
        return not any(self._overlap(rect, r, margin) for r in self._floor_rects)

    def _place_on_wall(
        self,
        rng: np.random.Generator,
        builder: _Builder,
        category: str,
        *,
        z0: float = 0.0,
        on_floor: bool = True,
        keepout_depth_m: float = 0.0,
        attempts: int = 40,
        walls: list[int] | None = None,
    ) -> WorldObject | None:
        """Put an object with its back against a wall; returns None when it does not fit."""
        lo, hi = builder.local_bounds()
        width = hi[0] - lo[0]
        depth = hi[1] - lo[1]
        height = hi[2] - lo[2]
        for _ in range(attempts):
            wall = int(rng.choice(walls)) if walls else int(rng.integers(0, 4))
            origin, along, yaw, length = self._wall_frame(wall)
            if length < width + 0.3:
                continue
            s = float(rng.uniform(0.15 + width / 2, length - 0.15 - width / 2))
            wall_rect = (s - width / 2, z0, s + width / 2, z0 + height)
            if any(self._overlap(wall_rect, r, 0.05) for r in self._wall_rects[wall]):
                continue
            inward = np.array([-along[1], along[0]])
            centre = origin + along * s + inward * (-lo[1])
            a = origin + along * (s - width / 2)
            b = origin + along * (s + width / 2)
            reach = inward * (depth + keepout_depth_m)
            pts = np.array([a, b, a + reach, b + reach])
            rect = (pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max())
            if on_floor and not self._floor_free(rect):
                continue
            self._wall_rects[wall].append(wall_rect)
            if on_floor:
                self._floor_rects.append(rect)
            parts = builder.place(float(centre[0]), float(centre[1]), yaw, z0)
            return self._new_object(category, parts, footprint=rect if on_floor else None, height_m=z0 + height)
        return None

    def _place_free(
        self, rng, builder: _Builder, category: str, x: float, y: float, yaw: float, *, check_floor: bool = True
    ) -> WorldObject | None:
        lo, hi = builder.local_bounds()
        corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        c, s = math.cos(yaw), math.sin(yaw)
        pts = corners @ np.array([[c, -s], [s, c]]).T + np.array([x, y])
        rect = (pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max())
        if check_floor:
            if not self._floor_free(rect):
                return None
            self._floor_rects.append(rect)
        return self._new_object(category, builder.place(x, y, yaw), footprint=rect, height_m=float(hi[2]))

    def _furnish(self, rng: np.random.Generator) -> None:
        W, D, H = self.room_size_m
        self._place_on_wall(rng, _build_door(rng, 0.9, 2.05), "door", keepout_depth_m=0.9)
        for _ in range(int(rng.integers(1, 3))):
            w = float(rng.uniform(1.0, 1.6))
            self._place_on_wall(rng, _build_window(rng, w, 1.2), "window", z0=0.95, on_floor=False)
        if rng.random() < 0.7:
            bed_w = float(rng.uniform(1.4, 1.8))
            bed = self._place_on_wall(rng, _build_bed(rng, bed_w, 2.0), "bed")
            if bed is not None:
                self._add_pillows(rng, bed, bed_w)
        if rng.random() < 0.8:
            self._place_on_wall(rng, _build_sofa(rng, float(rng.uniform(1.7, 2.2)), 0.9), "sofa")
        for _ in range(int(rng.integers(1, 3))):
            self._place_on_wall(
                rng, _build_bookshelf(rng, float(rng.uniform(0.8, 1.2)), 0.35, float(rng.uniform(1.7, 2.0))), "bookshelf"
            )
        for _ in range(int(rng.integers(1, 3))):
            self._place_on_wall(
                rng,
                _build_cabinet(rng, float(rng.uniform(0.6, 1.2)), 0.45, float(rng.uniform(0.8, 1.1))),
                "cabinet",
            )
        desk_w = float(rng.uniform(1.2, 1.6))
        desk = self._place_on_wall(rng, _build_desk(rng, desk_w, 0.7, 0.75), "desk", keepout_depth_m=0.9)
        if desk is not None:
            self._add_desk_set(rng, desk)
        for _ in range(int(rng.integers(1, 4))):
            w = float(rng.uniform(0.4, 0.9))
            self._place_on_wall(rng, _build_picture(rng, w, w * float(rng.uniform(0.6, 1.2))), "picture", z0=1.35, on_floor=False)
        self._add_dining_set(rng)
        for builder, category in ((_build_lamp(rng), "lamp"), (_build_plant(rng), "plant"), (_build_plant(rng), "plant")):
            self._place_in_corner(rng, builder, category)
        self._place_on_wall(rng, _build_trash_can(rng), "trash can")

    def _add_pillows(self, rng, bed: WorldObject, bed_w: float) -> None:
        # the bed's headboard is at its local -y end; recover the placement from its parts
        head = bed.parts[2].vertices.mean(0)
        centre = bed.parts[0].vertices.mean(0)
        direction = centre[:2] - head[:2]
        direction /= np.linalg.norm(direction)
        yaw = math.atan2(direction[1], direction[0]) - math.pi / 2
        side = np.array([direction[1], -direction[0]])
        n = 2 if bed_w > 1.3 else 1
        for k in range(n):
            offset = (k - (n - 1) / 2) * (bed_w / 2)
            p = head[:2] + direction * 0.3 + side * offset
            self._new_object("pillow", _build_pillow(rng).place(float(p[0]), float(p[1]), yaw, 0.52))

    def _add_desk_set(self, rng, desk: WorldObject) -> None:
        top = desk.parts[0].vertices
        centre = top.mean(0)
        back = desk.parts[3].vertices.mean(0)
        direction = centre[:2] - back[:2]
        direction /= np.linalg.norm(direction)
        yaw = math.atan2(direction[1], direction[0]) - math.pi / 2
        p = back[:2] + direction * 0.18
        self._new_object("monitor", _build_monitor(rng).place(float(p[0]), float(p[1]), yaw, float(top[:, 2].max())))
        q = centre[:2] + direction * float(rng.uniform(0.65, 0.8))
        chair_yaw = yaw + math.pi + float(rng.uniform(-0.4, 0.4))
        # the desk reserved the floor in front of it (keep-out), so no floor check here
        self._place_free(rng, _build_office_chair(rng), "office chair", float(q[0]), float(q[1]), chair_yaw, check_floor=False)

    def _add_dining_set(self, rng) -> None:
        W, D, _ = self.room_size_m
        for _ in range(30):
            tw, td = float(rng.uniform(1.0, 1.6)), float(rng.uniform(0.7, 0.9))
            x = float(rng.uniform(1.4, W - 1.4))
            y = float(rng.uniform(1.4, D - 1.4))
            yaw = float(rng.choice([0.0, math.pi / 2]))
            ex, ey = (tw / 2 + 0.75, td / 2 + 0.75) if yaw == 0.0 else (td / 2 + 0.75, tw / 2 + 0.75)
            margin_rect = (x - ex, y - ey, x + ex, y + ey)
            if not self._floor_free(margin_rect, 0.0):
                continue
            self._place_free(rng, _build_table(rng, tw, td, 0.75), "table", x, y, yaw, check_floor=False)
            self._floor_rects.append(margin_rect)
            chair_rgb = _jitter(rng, _PALETTE["chair"], 0.1)
            c, s = math.cos(yaw), math.sin(yaw)
            seats = [(0.0, -td / 2 - 0.3, 0.0), (0.0, td / 2 + 0.3, math.pi)]
            if tw > 1.2:
                seats = [(-tw / 4, -td / 2 - 0.3, 0.0), (tw / 4, -td / 2 - 0.3, 0.0), (0.0, td / 2 + 0.3, math.pi)]
            for lx, ly, lyaw in seats:
                if rng.random() < 0.15:
                    continue
                gx, gy = x + c * lx - s * ly, y + s * lx + c * ly
                jitter_yaw = float(rng.uniform(-0.25, 0.25))
                self._place_free(
                    rng, _build_chair(rng, chair_rgb), "chair", gx, gy, yaw + lyaw + jitter_yaw, check_floor=False
                )
            return

    def _place_in_corner(self, rng, builder: _Builder, category: str) -> None:
        W, D, _ = self.room_size_m
        lo, hi = builder.local_bounds()
        r = max(hi[0] - lo[0], hi[1] - lo[1]) / 2 + 0.05
        corners = [(r, r), (W - r, r), (W - r, D - r), (r, D - r)]
        order = rng.permutation(4)
        for k in order:
            x, y = corners[int(k)]
            x += float(rng.uniform(0, 0.3)) * (1 if x < W / 2 else -1)
            y += float(rng.uniform(0, 0.3)) * (1 if y < D / 2 else -1)
            if self._place_free(rng, builder, category, x, y, float(rng.uniform(0, 2 * math.pi))) is not None:
                return
        for _ in range(20):  # no free corner: anywhere along a wall
            wall_obj = self._place_on_wall(rng, builder, category, attempts=1)
            if wall_obj is not None:
                return

    # ----------------------------------------------------------------------- ray casting

    def _build_luts(self) -> None:
        """One Embree geometry with every triangle; per-triangle look-up tables for shading."""
        verts, tris, inst, part_ids, tex, part_rgb = [], [], [], [], [], []
        offset = 0
        for obj in self.objects:
            for part in obj.parts:
                verts.append(part.vertices)
                tris.append(part.triangles + offset)
                offset += len(part.vertices)
                n = len(part.triangles)
                inst.append(np.full(n, obj.instance_id, dtype=np.int32))
                part_ids.append(np.full(n, len(part_rgb), dtype=np.int32))
                part_rgb.append(part.rgb)
                tex.append(np.full(n, _TEXTURES.index(part.texture), dtype=np.int32))
        V = np.concatenate(verts)
        F = np.concatenate(tris)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
        tri = V[F]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        light = np.array([0.35, -0.25, 0.90])
        light /= np.linalg.norm(light)
        # the last entry of every table stands for "miss" (primitive id INVALID_ID clipped to it)
        self._lut_instance = np.concatenate(inst + [np.zeros(1, np.int32)])
        # color = table[part, intensity level]: one uint8 gather per pixel instead of float math;
        # levels are intensity in steps of 1/128 (intensity runs from 0 to about 1.6)
        self._lut_part = np.concatenate(part_ids + [np.full(1, len(part_rgb), np.int32)]) * np.int32(_LEVELS)
        base = np.array(part_rgb + [(0.0, 0.0, 0.0)], dtype=np.float64) * 255.0
        levels = np.arange(_LEVELS, dtype=np.float64) / _LEVEL_SCALE
        table = np.clip(base[:, None, :] * levels[None, :, None] + 0.5, 0, 255).astype(np.uint8)
        self._color_table = table.reshape(-1, 3)
        self._lut_tex = np.concatenate(tex + [np.zeros(1, np.int32)]) * np.int32(_TEX_SIZE * _TEX_SIZE)
        self._lut_axis = np.append(np.argmax(np.abs(normals), axis=1), 2).astype(np.int8)
        self._lut_lambert = np.append(0.55 + 0.30 * np.maximum(normals @ light, 0.0), 0.0).astype(np.float32)
        self._atlas = _texture_atlas().ravel()
        self._scene = scene
        self._lut_built = True

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """The cached ``RaycastingScene`` (all triangles in one geometry; built on first use)."""
        if not self._lut_built:
            self._build_luts()
        return self._scene

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (float32 (..., 3) origins and directions); returns ``t_hit`` (in units of
        the direction length, inf on a miss), ``instance`` (0 on a miss) and ``normal``."""
        rays = np.concatenate([np.broadcast_to(origins, directions.shape), directions], axis=-1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
        tri = np.minimum(ans["primitive_ids"].numpy(), len(self._lut_instance) - 1)
        return {"t_hit": ans["t_hit"].numpy(), "instance": self._lut_instance[tri], "normal": ans["primitive_normals"].numpy()}

    # ---------------------------------------------------------------------------- camera

    def camera_path(self, num_frames: int, *, frames_per_lap: int | None = None) -> np.ndarray:
        """(num_frames, 4, 4) smooth camera-to-world poses: an elliptic walk around the room's
        middle at about 1.45 m, always looking across the room at the furniture.

        Position and look-at target are sums of sinusoids in the frame index, so both the
        path and the orientation are smooth; ``frames_per_lap`` (default max(num_frames, 360),
        about 0.8 m/s at 30 fps)
        is the number of frames of one lap.
        """
        W, D, _ = self.room_size_m
        lap = frames_per_lap if frames_per_lap is not None else max(num_frames, 360)
        if lap < 2:
            raise ValueError(f"frames_per_lap must be >= 2, got {lap}")
        phase0 = (self.seed % 97) / 97.0 * 2 * math.pi
        ax, ay = max(W / 2 - 1.2, 0.4), max(D / 2 - 1.2, 0.4)
        poses = np.empty((num_frames, 4, 4))
        for i in range(num_frames):
            th = phase0 + 2 * math.pi * i / lap
            pos = np.array([W / 2 + ax * math.cos(th), D / 2 + ay * math.sin(th), 1.45 + 0.08 * math.sin(3 * th)])
            sweep = th + math.pi + 0.5 * math.sin(2 * th)
            target = np.array(
                [W / 2 + 0.9 * ax * math.cos(sweep), D / 2 + 0.9 * ay * math.sin(sweep), 0.75 + 0.2 * math.sin(2 * th + 1.0)]
            )
            poses[i] = look_at(pos, target)
        return poses

    # --------------------------------------------------------------------------- render

    def render(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RenderedView:
        """Noise-free render from ``T_world_cam`` (OpenCV camera axes)."""
        scene = self.scene
        ux, uy, inv_len = _pixel_rays(intrinsics)
        T = np.asarray(T_world_cam, dtype=np.float64)
        R = T[:3, :3].astype(np.float32)
        origin = T[:3, 3].astype(np.float32)
        h, w = intrinsics.height_px, intrinsics.width_px
        rays = np.empty((h, w, 6), dtype=np.float32)
        rays[..., :3] = origin
        for k in range(3):
            plane = ux * R[k, 0]
            plane += uy * R[k, 1]
            plane += R[k, 2]
            rays[..., 3 + k] = plane
        ans = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        tri = np.minimum(ans["primitive_ids"].numpy(), np.uint32(len(self._lut_instance) - 1))
        t_hit = ans["t_hit"].numpy()
        depth = np.where(t_hit < np.float32(1e6), t_hit, np.float32(0.0))
        normals = ans["primitive_normals"].numpy()
        dx, dy, dz = rays[..., 3], rays[..., 4], rays[..., 5]
        view_cos = np.abs(normals[..., 0] * dx + normals[..., 1] * dy + normals[..., 2] * dz) * inv_len
        # texture: triplanar look-up in a 1 cm texel atlas along the two axes of the plane
        scale = np.float32(1.0 / _TEXEL_M)
        ix = ((origin[0] + dx * depth) * scale).astype(np.int32)
        iy = ((origin[1] + dy * depth) * scale).astype(np.int32)
        iz = ((origin[2] + dz * depth) * scale).astype(np.int32)
        axis = self._lut_axis[tri]
        u = np.where(axis == 0, iy, ix)
        v = np.where(axis == 2, iy, iz)
        u &= _TEX_SIZE - 1
        v &= _TEX_SIZE - 1
        u *= _TEX_SIZE
        u += v
        u += self._lut_tex[tri]
        intensity = self._atlas[u] * (self._lut_lambert[tri] + np.float32(0.15) * view_cos)
        intensity *= np.float32(_LEVEL_SCALE)
        np.minimum(intensity, np.float32(_LEVELS - 1), out=intensity)
        index = intensity.astype(np.int32)
        index += self._lut_part[tri]
        color = self._color_table[index]
        return RenderedView(color=color, depth_m=depth, instance=self._lut_instance[tri], view_cos=view_cos)

    # ----------------------------------------------------------------------- ground truth

    def to_mesh(self) -> o3d.geometry.TriangleMesh:
        """All parts as one legacy Open3D mesh with vertex colors (for viewing)."""
        mesh = o3d.geometry.TriangleMesh()
        for obj in self.objects:
            for part in obj.parts:
                m = o3d.geometry.TriangleMesh(
                    o3d.utility.Vector3dVector(part.vertices), o3d.utility.Vector3iVector(part.triangles)
                )
                m.paint_uniform_color(part.rgb)
                mesh += m
        mesh.compute_triangle_normals()
        return mesh

    def ground_truth_surface(self, spacing_m: float = 0.02, *, visible_only: bool = True) -> GroundTruthSurface:
        """Points sampled uniformly on all surfaces (about one per ``spacing_m``^2), labelled.

        ``visible_only`` keeps a point only when a ray from it (along its outward normal side)
        reaches one of a grid of viewpoints inside the room without hitting anything else.
        """
        if not (spacing_m > 0 and math.isfinite(spacing_m)):
            raise ValueError(f"spacing_m must be positive, got {spacing_m}")
        key = (float(spacing_m), bool(visible_only))
        cached = self._gt_cache.get(key)
        if cached is None:
            cached = self._sample_surface(float(spacing_m), visible_only)
            self._gt_cache[key] = cached
        return GroundTruthSurface(cached.points.copy(), cached.instance_ids.copy(), dict(cached.categories))

    def _sample_surface(self, spacing_m: float, visible_only: bool) -> GroundTruthSurface:
        if spacing_m < 0.002:
            raise ValueError(f"spacing_m {spacing_m} would sample more than 10^7 points per 40 m^2; use >= 0.002")
        rng = np.random.default_rng([self.seed, 11])
        pts, ids, nrm = [], [], []
        for obj in self.objects:
            for part in obj.parts:
                tri = part.vertices[part.triangles]
                cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
                area2 = np.linalg.norm(cross, axis=1)
                total = float(area2.sum()) / 2.0
                n = int(round(total / spacing_m**2))
                if n == 0:
                    continue
                choice = rng.choice(len(tri), size=n, p=area2 / area2.sum())
                r1 = np.sqrt(rng.random(n))
                r2 = rng.random(n)
                a, b, c = tri[choice, 0], tri[choice, 1], tri[choice, 2]
                p = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
                pts.append(p)
                ids.append(np.full(n, obj.instance_id, dtype=np.int32))
                nrm.append(cross[choice] / np.maximum(area2[choice], 1e-12)[:, None])
        points = np.concatenate(pts)
        instance_ids = np.concatenate(ids)
        normals = np.concatenate(nrm)
        if visible_only:
            keep = self._visible(points, normals)
            points, instance_ids = points[keep], instance_ids[keep]
        present = {int(i) for i in np.unique(instance_ids)}
        cats = {i: c for i, c in self.categories.items() if i in present}
        return GroundTruthSurface(points.astype(np.float32), instance_ids.astype(np.int32), cats)

    def _viewpoints(self) -> np.ndarray:
        """Viewpoints on a ~1.1 m grid at four heights, outside every object, centre first."""
        W, D, H = self.room_size_m
        xs = np.linspace(0.4, W - 0.4, max(3, int(round(W / 1.1))))
        ys = np.linspace(0.4, D - 0.4, max(3, int(round(D / 1.1))))
        zs = [1.5, 0.4, 1.0, min(2.3, H - 0.3)]
        out = []
        for z in zs:
            for x in xs:
                for y in ys:
                    inside = any(
                        o.footprint is not None
                        and o.footprint[0] - 0.1 < x < o.footprint[2] + 0.1
                        and o.footprint[1] - 0.1 < y < o.footprint[3] + 0.1
                        and z < o.height_m + 0.1
                        for o in self.objects
                    )
                    if not inside:
                        out.append((x, y, z))
        vp = np.array(out, dtype=np.float32)
        centre = np.array([W / 2, D / 2, 1.5], dtype=np.float32)
        return vp[np.argsort(np.linalg.norm(vp - centre, axis=1), kind="stable")]

    def _visible(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        nrm = normals.astype(np.float32)
        origin = (points + 0.004 * normals).astype(np.float32)
        # a surface within 1.5 cm in front of the point hides it (faces resting on other faces)
        free = self.cast(origin, nrm)["t_hit"] > 0.015
        todo = np.flatnonzero(free)
        visible = np.zeros(len(points), dtype=bool)
        for v in self._viewpoints():
            if todo.size == 0:
                break
            d = v - origin[todo]
            facing = np.einsum("nc,nc->n", d, nrm[todo]) > 0
            sub, d = todo[facing], d[facing]
            if sub.size == 0:
                continue
            length = np.linalg.norm(d, axis=1)
            # t_hit is in units of |d|: a hit before reaching the viewpoint blocks the view
            seen = self.cast(origin[sub], d)["t_hit"] * length >= length - 0.01
            visible[sub[seen]] = True
            todo = todo[~visible[todo]]
        return visible


_TEX_SIZE = 256
_TEXEL_M = 0.01
_LEVELS = 256
_LEVEL_SCALE = 128.0


def _smooth_noise(rng: np.random.Generator, cells: int) -> np.ndarray:
    """Tileable value noise on the atlas grid with ``cells`` x ``cells`` random values."""
    coarse = rng.random((cells, cells))
    idx = np.arange(_TEX_SIZE) * cells / _TEX_SIZE
    i0 = np.floor(idx).astype(int)
    f = idx - i0
    f = f * f * (3 - 2 * f)
    i1 = (i0 + 1) % cells
    rows = coarse[i0] * (1 - f)[:, None] + coarse[i1] * f[:, None]
    return rows[:, i0] * (1 - f)[None, :] + rows[:, i1] * f[None, :]


def _texture_atlas() -> np.ndarray:
    """(n_textures, 256, 256) float32 brightness multipliers around 1, one per texture kind.

    Axis order is (u, v): u runs along x (or y on walls facing x), v along y or z.
    """
    rng = np.random.default_rng(20240611)
    white = rng.random((_TEX_SIZE, _TEX_SIZE)) - 0.5
    blocks = np.kron(rng.random((_TEX_SIZE // 2, _TEX_SIZE // 2)) - 0.5, np.ones((2, 2)))
    low = _smooth_noise(rng, 8) - 0.5
    v = np.arange(_TEX_SIZE)[None, :]
    u = np.arange(_TEX_SIZE)[:, None]
    grain = np.sin(2 * np.pi * v / 3.2 + 6.0 * low)
    plank_id = u // 18
    plank_tone = (rng.random(_TEX_SIZE) - 0.5)[plank_id]
    seams = np.where(u % 18 == 0, -0.25, 0.0)
    out = {
        "plain": 1 + 0.03 * white,
        "wood": 1 + 0.05 * grain + 0.04 * white + 0.06 * low,
        "fabric": 1 + 0.10 * white + 0.05 * low,
        "noise": 1 + 0.30 * blocks + 0.1 * low,
        "planks": 1 + 0.16 * plank_tone + 0.05 * grain + 0.03 * white + seams,
        "paint": 1 + 0.02 * white + 0.05 * low,
    }
    return np.stack([np.broadcast_to(out[name], (_TEX_SIZE, _TEX_SIZE)) for name in _TEXTURES]).astype(np.float32)


_RAY_CACHE: dict[CameraIntrinsics, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def _pixel_rays(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame ray directions ``(ux, uy, 1)`` per pixel (z = 1, so t_hit is the z depth):
    contiguous (h, w) float32 ``ux``, ``uy`` and the inverse ray lengths (rotation keeps
    lengths, so they hold in the world too)."""
    cached = _RAY_CACHE.get(intrinsics)
    if cached is None:
        u = (np.arange(intrinsics.width_px, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
        v = (np.arange(intrinsics.height_px, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
        uu, vv = np.meshgrid(u, v)
        inv_len = 1.0 / np.sqrt(uu * uu + vv * vv + 1.0)
        cached = (uu.astype(np.float32), vv.astype(np.float32), inv_len.astype(np.float32))
        if len(_RAY_CACHE) > 8:
            _RAY_CACHE.clear()
        _RAY_CACHE[intrinsics] = cached
    return cached


def default_intrinsics(width_px: int = 640, height_px: int = 480) -> CameraIntrinsics:
    """A ScanNet/Kinect-like depth camera (fx = fy = 577.5 px at 640 wide), principal point centred."""
    f = 577.5 * width_px / 640.0
    return CameraIntrinsics(width_px, height_px, f, f, (width_px - 1) / 2.0, (height_px - 1) / 2.0)


def apply_depth_noise(
    depth_m: np.ndarray, view_cos: np.ndarray, rng: np.random.Generator, *, dropout: float = 0.002
) -> np.ndarray:
    """Kinect-like noisy depth (float32 m, 0 = hole) from a clean depth image.

    Axial noise sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m; holes at grazing angles
    (|cos| < 0.15), at 60 % of pixels next to a depth jump larger than 4 cm + 3 % of z,
    ``dropout`` random pixels, and outside [0.25, 8.0] m.
    """
    z = depth_m
    valid = (z >= DEPTH_MIN_M) & (z <= DEPTH_MAX_M) & (view_cos >= GRAZING_COS)
    sigma = 0.0012 + 0.0019 * np.square(z - 0.4)
    noisy = z + sigma * rng.standard_normal(z.shape, dtype=np.float32)
    # depth discontinuities: compare with the 4 neighbours
    zp = np.where(z > 0, z, np.float32(100.0))
    jump = np.zeros(z.shape, dtype=bool)
    thr = 0.04 + 0.03 * zp
    dx = np.abs(np.diff(zp, axis=1)) > thr[:, 1:]
    dy = np.abs(np.diff(zp, axis=0)) > thr[1:, :]
    jump[:, 1:] |= dx
    jump[:, :-1] |= dx
    jump[1:, :] |= dy
    jump[:-1, :] |= dy
    r = rng.random(z.shape, dtype=np.float32)
    holes = (jump & (r < 0.6)) | (r > 1.0 - dropout)
    return np.where(valid & ~holes, noisy, np.float32(0.0)).astype(np.float32)


class SyntheticSource(IndexedFrameSource):
    """Frames rendered from a ``SyntheticWorld`` along its ``camera_path`` (streams directly).

    Frame i: ``frame_id = i``, ``stamp_ns = round(i * 1e9 / fps)``, depth uint16 mm, exact
    instance image and the categories of the instances it shows. Frames are a pure function
    of (world seed, i, options): iterating twice gives identical frames.
    """

    def __init__(
        self,
        world: SyntheticWorld,
        num_frames: int = 300,
        width_px: int = 640,
        height_px: int = 480,
        *,
        fps: float = 30.0,
        depth_noise: bool = True,
        frames_per_lap: int | None = None,
        intrinsics: CameraIntrinsics | None = None,
        stride: int = 1,
        max_frames: int | None = None,
    ) -> None:
        if num_frames < 0:
            raise ValueError(f"num_frames must be >= 0, got {num_frames}")
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        super().__init__(f"synthetic:seed={world.seed}", stride=stride, max_frames=max_frames)
        self.world = world
        self.num_frames = int(num_frames)
        if intrinsics is not None and (intrinsics.width_px, intrinsics.height_px) != (width_px, height_px):
            raise ValueError(
                f"intrinsics are for {intrinsics.width_px}x{intrinsics.height_px}, frames asked for {width_px}x{height_px}"
            )
        self.intrinsics = intrinsics if intrinsics is not None else default_intrinsics(width_px, height_px)
        self.fps = float(fps)
        self.depth_noise = depth_noise
        self.poses = world.camera_path(self.num_frames, frames_per_lap=frames_per_lap)

    def _num_items(self) -> int:
        return self.num_frames

    def _load(self, index: int) -> Frame:
        T = self.poses[index]
        view = self.world.render(T, self.intrinsics)
        if self.depth_noise:
            rng = np.random.default_rng([self.world.seed, 1000 + index])
            depth_m = apply_depth_noise(view.depth_m, view.view_cos, rng)
        else:
            depth_m = np.where((view.depth_m >= DEPTH_MIN_M) & (view.depth_m <= DEPTH_MAX_M), view.depth_m, 0.0)
        depth = np.round(depth_m * DEPTH_SCALE).astype(np.uint16)
        present = np.flatnonzero(np.bincount(view.instance.ravel()))
        cats = {int(i): self.world.categories[int(i)] for i in present if i != 0}
        return Frame(
            frame_id=index,
            stamp_ns=int(round(index * 1e9 / self.fps)),
            color=view.color,
            depth=depth,
            depth_scale=DEPTH_SCALE,
            intrinsics=self.intrinsics,
            T_world_cam=T.copy(),
            instance=view.instance,
            instance_categories=cats,
            source=self.name,
        )


_SPEC_KEYS = {
    "seed": ("seed", int),
    "frames": ("num_frames", int),
    "width": ("width_px", int),
    "height": ("height_px", int),
    "fps": ("fps", float),
    "lap": ("frames_per_lap", int),
    "noise": ("depth_noise", None),
}


def open_synthetic(spec_options: dict[str, str] | None = None, **kwargs) -> SyntheticSource:
    """A ``SyntheticSource`` from ``synthetic:seed=N,frames=N,width=W,height=H,fps=F,noise=0|1,lap=N``
    options (strings) plus keyword arguments of ``SyntheticSource`` (and ``seed``)."""
    merged = dict(kwargs)
    for key, text in (spec_options or {}).items():
        if key not in _SPEC_KEYS:
            raise ValueError(f"unknown synthetic option {key!r}; known: {', '.join(sorted(_SPEC_KEYS))}")
        name, conv = _SPEC_KEYS[key]
        if name in merged:
            raise ValueError(f"synthetic option {key!r} is given both in the spec and as the keyword {name!r}")
        if conv is None:
            if text.lower() not in ("0", "1", "true", "false"):
                raise ValueError(f"synthetic option noise must be 0/1/true/false, got {text!r}")
            merged[name] = text.lower() in ("1", "true")
            continue
        try:
            merged[name] = conv(text)
        except ValueError:
            raise ValueError(f"synthetic option {key}={text!r} is not a valid {conv.__name__}") from None
    seed = int(merged.pop("seed", 0))
    return SyntheticSource(SyntheticWorld(seed), **merged)


def __getattr__(name: str):
    # write_scannet_layout lives in its own module (it writes any source); exported here too.
    if name == "write_scannet_layout":
        from openfusion.sources.scannet_writer import write_scannet_layout

        return write_scannet_layout
    raise AttributeError(name)
