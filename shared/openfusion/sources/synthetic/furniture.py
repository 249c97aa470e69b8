"""The synthetic world's furniture: mesh primitives and the builders of every object kind.

Owns ``Part`` / ``WorldObject`` (an instance made of triangle-mesh parts), the Open3D mesh
primitives (``_box``, ``_cylinder``, ``_sphere``, ``_quad``), the per-category base colors
(``_PALETTE``, hence ``CATEGORIES``), ``_Builder`` (parts collected in an object's local frame,
front = +y, floor z = 0, then placed) and one ``_build_*`` function per object kind (door,
window, picture, bed, pillow, sofa, bookshelf with books, cabinet, desk, monitor, office chair,
table, chair, lamp, plant, trash can). Builders draw their sizes and colors from the ``rng`` they
are given, so the caller's call order fixes the room bit for bit. Where objects go is
``layout.py``'s business.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from openfusion.sources.synthetic_categories import CATEGORIES  # noqa: F401 (re-exported)
from openfusion.sources.synthetic_categories import PALETTE as _PALETTE


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


# Base colors per category and CATEGORIES live in openfusion.sources.synthetic_categories (no Open3D).


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

