"""Ray-cast rendering of the synthetic world (Open3D ``RaycastingScene``, Embree, headless).

``SceneRenderer`` puts every triangle of the world's objects into one Embree geometry and
builds per-triangle look-up tables (instance id, part color, texture, dominant axis, Lambert
term), so a render is one ``cast_rays`` plus a few gathers: color = part base color x
procedural texture (triplanar, 1 cm texels) x Lambert shading, quantised through a uint8
color table. ``render`` returns a noise-free ``RenderedView``; ``cast`` casts arbitrary rays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from openfusion.frame import CameraIntrinsics
from openfusion.sources.synthetic.camera import _pixel_rays
from openfusion.sources.synthetic.furniture import WorldObject
from openfusion.sources.synthetic.textures import _TEX_SIZE, _TEXEL_M, _TEXTURES, _texture_atlas

_LEVELS = 256
_LEVEL_SCALE = 128.0


@dataclass
class RenderedView:
    """Noise-free render: depth in metres (0 = miss), instance ids, color, |cos| of the view angle."""

    color: np.ndarray  # (h, w, 3) uint8
    depth_m: np.ndarray  # (h, w) float32, 0 where nothing was hit
    instance: np.ndarray  # (h, w) int32
    view_cos: np.ndarray  # (h, w) float32


def objects_mesh(objects: list[WorldObject]) -> o3d.geometry.TriangleMesh:
    """All parts of ``objects`` as one legacy Open3D mesh with vertex colors (for viewing)."""
    verts, tris, colors = [], [], []
    offset = 0
    for obj in objects:
        for part in obj.parts:
            verts.append(part.vertices)
            tris.append(part.triangles + offset)
            colors.append(np.broadcast_to(np.asarray(part.rgb, dtype=np.float64), part.vertices.shape))
            offset += len(part.vertices)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.concatenate(verts)), o3d.utility.Vector3iVector(np.concatenate(tris))
    )
    mesh.vertex_colors = o3d.utility.Vector3dVector(np.concatenate(colors))
    mesh.compute_triangle_normals()
    return mesh


class SceneRenderer:
    """The world's triangles in one ``RaycastingScene`` with the shading tables of each triangle."""

    def __init__(self, objects: list[WorldObject]) -> None:
        """One Embree geometry with every triangle; per-triangle look-up tables for shading."""
        verts, tris, inst, part_ids, tex, part_rgb = [], [], [], [], [], []
        offset = 0
        for obj in objects:
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
        self._V32, self._F32 = V.astype(np.float32), F.astype(np.uint32)
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
        self._scene: o3d.t.geometry.RaycastingScene | None = None

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """The ``RaycastingScene`` (all triangles in one geometry; built on first use)."""
        if self._scene is None:
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(o3d.core.Tensor(self._V32), o3d.core.Tensor(self._F32))
        return self._scene

    @property
    def miss_index(self) -> int:
        """The triangle index that stands for "no hit" in the shading tables (one past the last)."""
        return len(self._lut_instance) - 1

    def _view_hits(self, rays: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(triangle index (``miss_index`` on a miss), t_hit (inf on a miss), normal) of each of the
        (h, w, 6) ``rays`` of a view from ``origin``: one cast into the whole scene."""
        ans = self.scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        tri = np.minimum(ans["primitive_ids"].numpy(), np.uint32(self.miss_index))
        return tri, ans["t_hit"].numpy(), ans["primitive_normals"].numpy()

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (float32 (..., 3) origins and directions); returns ``t_hit`` (in units of
        the direction length, inf on a miss), ``instance`` (0 on a miss) and ``normal``."""
        rays = np.concatenate([np.broadcast_to(origins, directions.shape), directions], axis=-1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
        tri = np.minimum(ans["primitive_ids"].numpy(), len(self._lut_instance) - 1)
        return {"t_hit": ans["t_hit"].numpy(), "instance": self._lut_instance[tri], "normal": ans["primitive_normals"].numpy()}

    def render(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RenderedView:
        """Noise-free render from ``T_world_cam`` (OpenCV camera axes)."""
        rays, origin, inv_len = self._view_rays(T_world_cam, intrinsics)
        return self._shade(rays, origin, inv_len, *self._view_hits(rays, origin))

    def render_whole(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RenderedView:
        """:meth:`render` cast into the whole scene at once (what a subclass's own casting agrees with)."""
        rays, origin, inv_len = self._view_rays(T_world_cam, intrinsics)
        return self._shade(rays, origin, inv_len, *SceneRenderer._view_hits(self, rays, origin))

    @staticmethod
    def _view_rays(T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The (h, w, 6) world rays of a view (direction (ux, uy, 1) rotated, so t_hit is the z
        depth), the camera's position and the rays' inverse lengths."""
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
        return rays, origin, inv_len

    def _shade(
        self, rays: np.ndarray, origin: np.ndarray, inv_len: np.ndarray, tri: np.ndarray, t_hit: np.ndarray, normals: np.ndarray
    ) -> RenderedView:
        """Depth, color, instances and view angle of a view from its rays' hits."""
        depth = np.where(t_hit < np.float32(1e6), t_hit, np.float32(0.0))
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
