"""``SyntheticBuilding``: a floor of furnished rooms along a corridor, deterministic by seed.

It answers what :class:`~openfusion.sources.synthetic.world.SyntheticWorld` answers (``objects``,
``categories``, ``render``/``cast``/``scene``, ``to_mesh``, ``ground_truth_surface``), so the
ground-truth encoder, the evaluation and the ScanNet writer take either, plus what a floor has:
``rooms`` (where each room and its doorway are, and its instance ids), ``floor_area_m2`` and
``route_floor_area_m2``, and ``camera_path(route, revisit=..., frames=...)``, a walk through the
rooms of a route (:mod:`~openfusion.sources.synthetic.walk`). The plan is
:mod:`~openfusion.sources.synthetic.floorplan`'s.

Rendering
    Only what the camera can see: each room and the corridor is a cell with its own Embree scene,
    and a view is cast into the camera's cell and on through the doorways it sees
    (:mod:`~openfusion.sources.synthetic.portals`), so a frame costs about what a frame of the
    built-in room costs whatever the number of rooms (``bench/bench_building_render.py``: per
    number of rooms, against the room in the same run). ``render_whole`` casts into the whole
    building at once (the reference the tests compare with); ``cast`` (ground truth) always does.

Ground truth
    As the room's: labelled points sampled on every surface, kept when seen from a viewpoint, where
    each room and the corridor are sampled with their own viewpoint grid (a point of room 3 must
    be seen from inside room 3; the corridor's from the corridor), so what no camera inside the
    building could see is not ground truth.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import open3d as o3d

from openfusion.frame import CameraIntrinsics
from openfusion.sources.synthetic.floorplan import build_floorplan
from openfusion.sources.synthetic.furniture import WorldObject
from openfusion.sources.synthetic.portals import PORTAL_MARGIN_M, Portal, PortalRenderer
from openfusion.sources.synthetic.render import RenderedView, objects_mesh
from openfusion.sources.synthetic.surface import GroundTruthSurface, room_viewpoints, sample_surface
from openfusion.sources.synthetic.walk import (
    START_X_M,
    corridor_leg,
    poses_from_samples,
    room_visit,
    sample_walk,
    visit_order,
)
from openfusion.sources.synthetic_spec import DEFAULT_ROOMS, MAX_ROOMS, default_revisit


class SyntheticBuilding:
    """A corridor with ``rooms`` furnished rooms on both sides (room k: north side for even k,
    south for odd k, in bay k // 2), deterministic by ``seed``. ``.categories`` maps instance id
    -> raw category; ids are unique over the whole building."""

    def __init__(self, seed: int = 0, *, rooms: int = DEFAULT_ROOMS) -> None:
        if not 1 <= rooms <= MAX_ROOMS:
            raise ValueError(f"rooms must be between 1 and {MAX_ROOMS}, got {rooms}")
        self.seed = int(seed)
        self.plan = build_floorplan(self.seed, int(rooms))
        self.objects: list[WorldObject] = self.plan.objects
        self.categories: dict[int, str] = {o.instance_id: o.category for o in self.objects}
        self.rooms = self.plan.rooms
        self.height_m = self.plan.height_m
        self._renderer: PortalRenderer | None = None
        self._gt_cache: dict[tuple[float, bool], GroundTruthSurface] = {}
        self._visits: dict[int, np.ndarray] = {}

    @property
    def num_rooms(self) -> int:
        return len(self.rooms)

    @property
    def floor_area_m2(self) -> float:
        """Interior floor of every room and the corridor (m^2)."""
        return self.plan.floor_area_m2

    def route_floor_area_m2(self, route: Sequence[int]) -> float:
        """Floor of the rooms on ``route`` plus the whole corridor (m^2): the area a walk of that
        route maps (it sees along the corridor)."""
        corridor = self.plan.corridor_length_m * self.plan.corridor_width_m
        return corridor + sum(self.rooms[k].floor_area_m2 for k in set(route))

    def room_of_instance(self) -> dict[int, int]:
        """Instance id -> room index (-1: the corridor)."""
        out = {i: -1 for i in self.plan.corridor_instance_ids}
        for room in self.rooms:
            out.update({i: room.index for i in room.instance_ids})
        return out

    # ----------------------------------------------------------------------- ray casting

    def _scene_renderer(self) -> PortalRenderer:
        if self._renderer is None:
            cells = [self.plan.corridor_instance_ids] + [room.instance_ids for room in self.rooms]
            portals = [Portal(room.portal_quad(), (0, 1 + room.index)) for room in self.rooms]
            self._renderer = PortalRenderer(self.objects, cells, portals, self.cell_of)
        return self._renderer

    def cell_of(self, xyz: np.ndarray) -> int | None:
        """The cell a camera at ``xyz`` is in: 0 the corridor, 1 + k room k (or its doorway); None
        within :data:`~.portals.PORTAL_MARGIN_M` of a doorway's portal or outside every cell."""
        x, y = float(xyz[0]), float(xyz[1])
        for room in self.rooms:
            a, b = room.doorway_x_m
            if a - PORTAL_MARGIN_M <= x <= b + PORTAL_MARGIN_M and abs(y - room.portal_y_m) <= PORTAL_MARGIN_M:
                return None
            if room.contains((x, y)):
                return 1 + room.index
        x0, y0, x1, y1 = self.plan.corridor_rect_m
        return 0 if x0 <= x <= x1 and y0 <= y <= y1 else None

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """The whole building's ``RaycastingScene`` (all triangles in one geometry; built on first use)."""
        return self._scene_renderer().scene

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays into the whole building; see :meth:`SyntheticWorld.cast`."""
        return self._scene_renderer().cast(origins, directions)

    def render(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RenderedView:
        """Noise-free render from ``T_world_cam`` (OpenCV camera axes), cast into the camera's room
        or corridor and on through doorways (:mod:`~openfusion.sources.synthetic.portals`)."""
        return self._scene_renderer().render(T_world_cam, intrinsics)

    def render_whole(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics) -> RenderedView:
        """The same view cast into the whole building at once (the reference :meth:`render` agrees with)."""
        return self._scene_renderer().render_whole(T_world_cam, intrinsics)

    # ---------------------------------------------------------------------------- camera

    def check_route(self, route: Sequence[int]) -> list[int]:
        """``route`` as a list; ValueError for an empty route, a room twice or a room the building lacks."""
        route = [int(k) for k in route]
        if not route:
            raise ValueError("a route needs at least one room")
        for k in route:
            if not 0 <= k < self.num_rooms:
                raise ValueError(f"route room {k} does not exist: the building has rooms 0-{self.num_rooms - 1}")
        twice = sorted({k for k in route if route.count(k) > 1})
        if twice:
            raise ValueError(f"room(s) {twice} are twice in the route (revisit=N walks rooms again)")
        return route

    def room_visit(self, k: int) -> np.ndarray:
        """(K, 4) keyposes (x, y, yaw, pitch) of a visit of room ``k`` (cached; the same in every route)."""
        keys = self._visits.get(k)
        if keys is None:
            room = self.rooms[k]
            footprints = [self.objects[i - 1].footprint for i in room.instance_ids if self.objects[i - 1].footprint]
            keys = self._visits[k] = room_visit(self.plan, room, footprints)
        return keys

    def walk_pieces(self, route: Sequence[int] | None = None, *, revisit: int | None = None) -> list[np.ndarray]:
        """The walk as pieces of keyposes: corridor leg, room visit, corridor leg, ... over the
        rooms of ``route`` (default: every room in order) and then its first ``revisit`` again
        (default :data:`~openfusion.sources.synthetic_spec.DEFAULT_REVISIT`, at most the route)."""
        route = self.check_route(range(self.num_rooms) if route is None else route)
        revisit = default_revisit(len(route)) if revisit is None else revisit
        pieces = []
        x, yaw = START_X_M, 0.0
        for k in visit_order(route, revisit):
            visit = self.room_visit(k)
            pieces.append(corridor_leg(self.plan, x, yaw, float(visit[0, 0]), float(visit[0, 2])))
            pieces.append(visit)
            x, yaw = float(visit[-1, 0]), float(visit[-1, 2])
        return pieces

    def camera_path(
        self, route: Sequence[int] | None = None, *, revisit: int | None = None, frames: int | None = None
    ) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses of the walk of ``route`` (:meth:`walk_pieces`): by default
        a frame every 0.3 m walked or 20 degrees turned; ``frames=N`` spreads N frames over it."""
        return poses_from_samples(sample_walk(self.walk_pieces(route, revisit=revisit), frames))

    # ----------------------------------------------------------------------- ground truth

    def to_mesh(self) -> o3d.geometry.TriangleMesh:
        """All parts as one legacy Open3D mesh with vertex colors (for viewing)."""
        return objects_mesh(self.objects)

    def ground_truth_surface(self, spacing_m: float = 0.02, *, visible_only: bool = True) -> GroundTruthSurface:
        """Points sampled uniformly on all surfaces (about one per ``spacing_m``^2), labelled;
        ``visible_only`` keeps those seen from inside the room (or corridor) they belong to."""
        if not (spacing_m > 0 and math.isfinite(spacing_m)):
            raise ValueError(f"spacing_m must be positive, got {spacing_m}")
        key = (float(spacing_m), bool(visible_only))
        cached = self._gt_cache.get(key)
        if cached is None:
            H = self.plan.height_m
            parts = [(self.plan.corridor_instance_ids, self.plan.corridor_rect_m)]
            parts += [(room.instance_ids, room.rect_m) for room in self.rooms]
            pts, ids = [], []
            for n, (instance_ids, rect) in enumerate(parts):
                objects = [self.objects[i - 1] for i in instance_ids]
                surface = sample_surface(
                    objects,
                    self.categories,
                    seed=self.seed,
                    cast=self.cast,
                    spacing_m=float(spacing_m),
                    visible_only=visible_only,
                    viewpoints=room_viewpoints(objects, rect, H) if visible_only else None,
                    stream=(33, n),
                )
                pts.append(surface.points)
                ids.append(surface.instance_ids)
            instance_ids = np.concatenate(ids)
            present = {int(i) for i in np.unique(instance_ids)}
            cats = {i: c for i, c in self.categories.items() if i in present}
            cached = self._gt_cache[key] = GroundTruthSurface(np.concatenate(pts), instance_ids, cats)
        return GroundTruthSurface(cached.points.copy(), cached.instance_ids.copy(), dict(cached.categories))
