"""Headless pictures of a map: CPU ray casting of its mesh with Lambert shading, captions with Pillow.

No GPU, no display: Open3D's ``RaycastingScene`` (Embree) casts one ray per pixel through a
pinhole camera (pixel centres at integer coordinates, OpenCV axes), every hit takes the
barycentric blend of its triangle's vertex colours, shaded by

    intensity = ambient + (1 - ambient) * max(0, n . l)

with ``n`` the interpolated vertex normal (turned towards the camera) and ``l`` a fixed light
above-left of the camera.

Visibility ("doll's house" view of a room scan seen from outside)
    TSDF normals point to free space, so a face is a *front face* when the camera is on its normal
    side. A ray passes back faces (the ceiling and near walls seen from behind vanish). It also
    passes a front face met less than ``peel_gap_m`` after the last back face: depth noise leaves
    small free-space pockets inside the truncation band behind a wall, whose far sides are front
    faces; without this rule they show as speckle where the near walls were. The pocket is never
    thicker than the band, so ``1.25 x truncation distance`` (what ``openfusion render`` uses)
    removes them while anything a real gap of free space away is kept.

``supersample`` renders at ``s`` times the size and averages ``s x s`` blocks (anti-aliasing);
the per-pixel triangle index and depth then come from the centre sample of each block.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d
from PIL import Image, ImageDraw, ImageFont

from openfusion.frame import CameraIntrinsics
from openfusion.viz.camera import VirtualCamera, check_image_size
from openfusion.viz.errors import VizError

logger = logging.getLogger(__name__)

BACKGROUND_RGB = (250, 250, 250)
OUTLINE_RGB = (25, 25, 25)
MAX_SUPERSAMPLE = 4


@dataclass
class RenderedImage:
    """A shaded view plus what each pixel shows."""

    rgb: np.ndarray  # (h, w, 3) uint8
    depth_m: np.ndarray  # (h, w) float32 z-depth in the camera frame, 0 = background
    triangle_index: np.ndarray  # (h, w) int64 index into the mesh's triangles, -1 = background
    camera: VirtualCamera

    @property
    def coverage(self) -> float:
        """Fraction of pixels showing the mesh."""
        return float((self.triangle_index >= 0).mean())

    def mask_of_triangles(self, triangle_mask: np.ndarray) -> np.ndarray:
        """(h, w) bool: pixels whose visible triangle is selected by ``triangle_mask`` (T,) bool."""
        triangle_mask = np.asarray(triangle_mask, bool)
        out = np.zeros(self.triangle_index.shape, bool)
        hit = self.triangle_index >= 0
        out[hit] = triangle_mask[self.triangle_index[hit]]
        return out


def _face_normals(
    vertices: np.ndarray, triangles: np.ndarray, vertex_normals: np.ndarray | None, which: np.ndarray
) -> np.ndarray:
    """Unit normals of triangles ``which``, oriented like the vertex normals (the TSDF's free-space side) where known."""
    triangles = triangles[which]
    v0, v1, v2 = (vertices[triangles[:, i]] for i in range(3))
    n = np.cross(v1 - v0, v2 - v0)
    if vertex_normals is not None:
        vn = vertex_normals[triangles].sum(axis=1)
        flip = (n * vn).sum(axis=1) < 0
        n[flip] *= -1.0
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(norm, 1e-12)


def _pixel_rays(intr: CameraIntrinsics) -> np.ndarray:
    u = (np.arange(intr.width_px, dtype=np.float64) - intr.cx) / intr.fx
    v = (np.arange(intr.height_px, dtype=np.float64) - intr.cy) / intr.fy
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv, np.ones_like(uu)], axis=-1)  # z = 1: t_hit is the z depth


def _first_visible_hits(
    vertices: np.ndarray,
    triangles: np.ndarray,
    normals: np.ndarray | None,
    origin: np.ndarray,
    dirs: np.ndarray,
    *,
    cull: bool,
    peel_gap_m: float,
    max_layers: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(triangle, depth, barycentric uv, pixel) of every pixel's first visible surface.

    Without culling this is the first hit. With culling, a ray passes back faces and, when
    ``peel_gap_m`` > 0, front faces less than ``peel_gap_m`` (along the ray) behind the last back
    face it passed; it stops at the first other front face.
    """
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    n_px = len(dirs)
    ray_len = np.linalg.norm(dirs, axis=1)
    t_start = np.zeros(n_px)  # where each active ray starts, in units of its direction
    t_back = np.full(n_px, -np.inf)  # last back face passed
    active = np.arange(n_px)
    out_tri, out_t, out_uv, out_px = [], [], [], []
    eps = 1e-4
    for _layer in range(max_layers if cull else 1):
        if len(active) == 0:
            break
        o = origin[None, :] + dirs[active] * t_start[active, None]
        rays = np.concatenate([o, dirs[active]], axis=1).astype(np.float32)
        ans = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
        t_hit = ans["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t_hit)
        active, t_hit = active[hit], t_hit[hit]
        tri = ans["primitive_ids"].numpy()[hit].astype(np.int64)
        uv = ans["primitive_uvs"].numpy()[hit]
        t_abs = t_start[active] + t_hit
        if not cull:
            accept = np.ones(len(active), bool)
        else:
            face_n = _face_normals(vertices, triangles, normals, tri)
            front = (face_n * dirs[active]).sum(axis=1) < 0.0
            gap_m = (t_abs - t_back[active]) * ray_len[active]
            accept = front & (gap_m >= peel_gap_m)
            back = ~front
            t_back[active[back]] = t_abs[back]
        out_tri.append(tri[accept])
        out_t.append(t_abs[accept])
        out_uv.append(uv[accept])
        out_px.append(active[accept])
        t_start[active] = t_abs + eps
        active = active[~accept]
    if not out_px:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2), np.float32), np.zeros(0, np.int64)
    return np.concatenate(out_tri), np.concatenate(out_t), np.concatenate(out_uv), np.concatenate(out_px)


def render_mesh(
    vertices: np.ndarray,
    triangles: np.ndarray,
    vertex_colors: np.ndarray,
    camera: VirtualCamera,
    *,
    vertex_normals: np.ndarray | None = None,
    cull_back_faces: bool = True,
    ambient: float = 0.4,
    background_rgb: tuple[int, int, int] = BACKGROUND_RGB,
    supersample: int = 1,
    peel_gap_m: float = 0.0,
    max_layers: int = 8,
) -> RenderedImage:
    """Ray-cast and shade a vertex-coloured triangle mesh from ``camera`` (module docstring).

    ``vertex_normals`` (V, 3) orient faces for culling and smooth the shading; without them faces
    are two-sided and flat-shaded. ``peel_gap_m`` > 0 also skips a front face met within that
    distance after a back face (see the module docstring); ``max_layers`` bounds the surfaces one
    ray may pass.
    """
    vertices = np.asarray(vertices, np.float64)
    triangles = np.asarray(triangles, np.int64)
    colors = np.asarray(vertex_colors)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise VizError(f"vertices must be (V, 3), got {vertices.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise VizError(f"triangles must be (T, 3), got {triangles.shape}")
    if colors.shape != vertices.shape or colors.dtype != np.uint8:
        raise VizError(f"vertex colours must be (V, 3) uint8 like the vertices, got {colors.dtype} {colors.shape}")
    if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(vertices)):
        raise VizError("triangles refer to vertices that do not exist")
    if not (isinstance(supersample, int) and 1 <= supersample <= MAX_SUPERSAMPLE):
        raise VizError(f"supersample must be an integer from 1 to {MAX_SUPERSAMPLE}, got {supersample!r}")
    if not 0.0 <= ambient <= 1.0:
        raise VizError(f"ambient must be within [0, 1], got {ambient}")
    intr = camera.intrinsics
    check_image_size(intr.width_px, intr.height_px)
    s = supersample
    intr_s = intr if s == 1 else intr.scaled(intr.width_px * s, intr.height_px * s)
    h, w = intr_s.height_px, intr_s.width_px
    T = np.asarray(camera.T_world_cam, np.float64)
    R, origin = T[:3, :3], T[:3, 3]

    normals = None
    if vertex_normals is not None:
        normals = np.asarray(vertex_normals, np.float64)
        if normals.shape != vertices.shape:
            raise VizError(f"vertex normals must be (V, 3) like the vertices, got {normals.shape}")
        if not (np.linalg.norm(normals, axis=1) > 1e-6).any():
            normals = None
    cull = cull_back_faces and normals is not None

    rays_cam = _pixel_rays(intr_s).reshape(-1, 3)
    dirs = rays_cam @ R.T
    n_px = h * w
    rgb = np.empty((n_px, 3), np.float32)
    rgb[:] = np.asarray(background_rgb, np.float32)
    depth = np.zeros(n_px, np.float32)
    tri_index = np.full(n_px, -1, np.int64)
    if len(triangles):
        tri, t_hit, uv, px = _first_visible_hits(
            vertices, triangles, normals, origin, dirs, cull=cull, peel_gap_m=peel_gap_m, max_layers=max_layers
        )
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        corners = triangles[tri]
        col = (colors[corners].astype(np.float32) * bary[:, :, None]).sum(axis=1)
        if normals is not None:
            n = (normals[corners] * bary[:, :, None]).sum(axis=1)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        else:
            n = _face_normals(vertices, triangles, None, tri)
        ray_dir = dirs[px]
        facing = (n * ray_dir).sum(axis=1) > 0
        n[facing] *= -1.0  # shade the side the camera sees
        light = -R[:, 2] + 0.6 * (-R[:, 1]) - 0.3 * R[:, 0]
        light /= np.linalg.norm(light)
        lambert = np.clip(n @ light, 0.0, 1.0)
        intensity = ambient + (1.0 - ambient) * lambert
        rgb[px] = col * intensity[:, None].astype(np.float32)
        depth[px] = t_hit
        tri_index[px] = tri
    rgb = rgb.reshape(h, w, 3)
    depth = depth.reshape(h, w)
    tri_index = tri_index.reshape(h, w)
    if s > 1:
        h0, w0 = intr.height_px, intr.width_px
        rgb = rgb.reshape(h0, s, w0, s, 3).mean(axis=(1, 3))
        c = s // 2
        depth = depth[c::s, c::s]
        tri_index = tri_index[c::s, c::s]
    out = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    return RenderedImage(out, np.ascontiguousarray(depth), np.ascontiguousarray(tri_index), camera)


def outline(rgb: np.ndarray, mask: np.ndarray, *, color: tuple[int, int, int] = OUTLINE_RGB, width_px: int = 2) -> np.ndarray:
    """Copy of ``rgb`` with a ``width_px`` line drawn just outside the boundary of ``mask``."""
    grown = mask.copy()
    for _ in range(width_px):
        g = grown.copy()
        g[1:] |= grown[:-1]
        g[:-1] |= grown[1:]
        g[:, 1:] |= grown[:, :-1]
        g[:, :-1] |= grown[:, 1:]
        grown = g
    ring = grown & ~mask
    out = rgb.copy()
    out[ring] = color
    return out


@dataclass(frozen=True)
class CaptionLine:
    """One caption line; ``swatch_rgb`` draws a colour square before the text."""

    text: str
    swatch_rgb: tuple[int, int, int] | None = None


def _font(size_px: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    return ImageFont.load_default(size=size_px)


def draw_caption(image: Image.Image, lines: Sequence[CaptionLine], *, font_px: int | None = None) -> Image.Image:
    """Draw ``lines`` in a translucent box at the top-left corner of ``image`` (returns a new image)."""
    if not lines:
        return image.copy()
    size = font_px if font_px is not None else max(12, image.height // 36)
    font = _font(size)
    base = image.convert("RGBA")
    layer = Image.new("RGBA", base.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(layer)
    pad, gap = size // 2, size // 4
    swatch = size
    widths = []
    for line in lines:
        box = draw.textbbox((0, 0), line.text, font=font)
        widths.append(box[2] - box[0] + (swatch + gap if line.swatch_rgb is not None else 0))
    line_h = size + gap
    box_w = min(max(widths) + 2 * pad, base.width)
    box_h = min(len(lines) * line_h + 2 * pad - gap, base.height)
    draw.rectangle([0, 0, box_w, box_h], fill=(255, 255, 255, 215))
    y = pad
    for line in lines:
        x = pad
        if line.swatch_rgb is not None:
            draw.rectangle([x, y + 1, x + swatch - 2, y + swatch - 1], fill=(*line.swatch_rgb, 255), outline=(0, 0, 0, 255))
            x += swatch + gap
        draw.text((x, y), line.text, fill=(20, 20, 20, 255), font=font)
        y += line_h
    return Image.alpha_composite(base, layer).convert("RGB")


def save_png(image: Image.Image, path: str | os.PathLike[str]) -> Path:
    """Write ``image`` as PNG atomically (temporary file + rename); VizError for a bad target."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise VizError(f"{path}: pictures are written as .png, got {path.suffix or '(no suffix)'!r}")
    if not path.parent.is_dir():
        raise VizError(f"cannot write {path}: folder {path.parent} does not exist")
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        image.save(tmp, format="PNG")
        tmp.replace(path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise VizError(f"cannot write {path}: {exc}") from exc
    return path
