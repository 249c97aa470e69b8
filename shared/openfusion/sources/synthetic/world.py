"""``SyntheticWorld``: one furnished room, deterministic by seed, and what can be asked of it.

The world draws its room size from the seed, has ``layout.py`` build and furnish the room,
and then answers: ``render``/``cast``/``scene`` (``render.py``, the ray-cast scene built on
first use and cached), ``camera_path`` (``camera.py``), ``ground_truth_surface``
(``surface.py``, cached per spacing) and ``to_mesh`` for viewing.
"""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d

from openfusion.frame import CameraIntrinsics
from openfusion.sources.synthetic.camera import camera_path
from openfusion.sources.synthetic.furniture import WorldObject
from openfusion.sources.synthetic.layout import furnished_room
from openfusion.sources.synthetic.render import RenderedView, SceneRenderer, objects_mesh
from openfusion.sources.synthetic.surface import GroundTruthSurface, sample_surface


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
        self.objects: list[WorldObject] = furnished_room(self.room_size_m, rng)
        self.categories: dict[int, str] = {o.instance_id: o.category for o in self.objects}
        self._renderer: SceneRenderer | None = None
        self._gt_cache: dict[tuple[float, bool], GroundTruthSurface] = {}

    # ----------------------------------------------------------------------- ray casting

    def _scene_renderer(self) -> SceneRenderer:
        if self._renderer is None:
            self._renderer = SceneRenderer(self.objects)
        return self._renderer

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """The cached ``RaycastingScene`` (all triangles in one geometry; built on first use)."""
        return self._scene_renderer().scene

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays (float32 (..., 3) origins and directions); returns ``t_hit`` (in units of
        the direction length, inf on a miss), ``instance`` (0 on a miss) and ``normal``."""
        return self._scene_renderer().cast(origins, directions)

    def render(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RenderedView:
        """Noise-free render from ``T_world_cam`` (OpenCV camera axes)."""
        return self._scene_renderer().render(T_world_cam, intrinsics)

    # ---------------------------------------------------------------------------- camera

    def camera_path(self, num_frames: int, *, frames_per_lap: int | None = None) -> np.ndarray:
        """(num_frames, 4, 4) smooth camera-to-world poses: an elliptic walk around the room's
        middle at about 1.45 m, always looking across the room at the furniture.

        Position and look-at target are sums of sinusoids in the frame index, so both the
        path and the orientation are smooth; ``frames_per_lap`` (default
        :data:`~openfusion.sources.synthetic.camera.LAP_FRAMES` = 360, about 0.8 m/s at 30 fps) is
        the number of frames of one lap; a longer path walks the same lap again.
        """
        return camera_path(self.room_size_m, self.seed, num_frames, frames_per_lap=frames_per_lap)

    # ----------------------------------------------------------------------- ground truth

    def to_mesh(self) -> o3d.geometry.TriangleMesh:
        """All parts as one legacy Open3D mesh with vertex colors (for viewing)."""
        return objects_mesh(self.objects)

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
            cached = sample_surface(
                self.objects,
                self.categories,
                seed=self.seed,
                room_size_m=self.room_size_m,
                cast=self.cast,
                spacing_m=float(spacing_m),
                visible_only=visible_only,
            )
            self._gt_cache[key] = cached
        return GroundTruthSurface(cached.points.copy(), cached.instance_ids.copy(), dict(cached.categories))
