"""``SyntheticSource`` and ``BuildingSource``: frames of the room or the building, and ``open_synthetic``.

Frame i is rendered at pose i of the world's camera path, with Kinect-like depth noise drawn
from a stream seeded by (world seed, 1000 + i), so frames are a pure function of the seed, the
index and the options. The path is a closed lap (``lap=N`` frames, default
:data:`~openfusion.sources.synthetic.camera.LAP_FRAMES`); a source with more frames than a lap walks
the lap again with the same poses, while frame ids and stamps keep increasing. With ``stop=N`` the
camera stands still for N frames at the start and at each quarter of the lap (a robot waiting at a
door): the same pose, a fresh draw of depth noise each frame. ``open_synthetic``
parses the ``synthetic:key=value,...`` spec options
(:mod:`openfusion.sources.synthetic_spec`). ``BuildingSource`` renders the frames of a walk through
a :class:`~openfusion.sources.synthetic.building.SyntheticBuilding` the same way
(:func:`render_frame`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.sources.base import IndexedFrameSource
from openfusion.sources.synthetic.building import SyntheticBuilding
from openfusion.sources.synthetic.camera import LAP_FRAMES, default_intrinsics
from openfusion.sources.synthetic.depth import DEPTH_MAX_M, DEPTH_MIN_M, DEPTH_SCALE, apply_depth_noise
from openfusion.sources.synthetic.walk import visit_order
from openfusion.sources.synthetic.world import SyntheticWorld
from openfusion.sources.synthetic_spec import (
    BUILDING_SPEC_KEYS,
    DEFAULT_ROOMS,
    SPEC_KEYS,
    WORLDS,
    default_revisit,
    synthetic_options,
)


class SyntheticSource(IndexedFrameSource):
    """Frames rendered from a ``SyntheticWorld`` along its ``camera_path`` (streams directly).

    Frame i: ``frame_id = i``, ``stamp_ns = round(i * 1e9 / fps)``, depth uint16 mm, exact
    instance image and the categories of the instances it shows. Frames are a pure function
    of (world seed, i, options): iterating twice gives identical frames. ``frames_per_lap``
    (default :data:`~openfusion.sources.synthetic.camera.LAP_FRAMES`): frames of one lap of the
    room; frame ``i`` is taken at the pose of frame ``i mod frames_per_lap`` (``self.lap``).
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
        stop_frames: int = 0,
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
        self.lap = int(frames_per_lap) if frames_per_lap is not None else LAP_FRAMES
        # One lap's poses (or fewer): later laps take the same poses.
        self.poses = world.camera_path(min(self.num_frames, self.lap), frames_per_lap=self.lap)
        if stop_frames < 0:
            raise ValueError(f"stop_frames must be >= 0, got {stop_frames}")
        self.stop_frames = int(stop_frames)
        #: the pose index of each frame of one lap, stops included
        self.walk = lap_with_stops(self.lap, self.stop_frames)

    def _num_items(self) -> int:
        return self.num_frames

    def _load(self, index: int) -> Frame:
        return render_frame(self.world, self.poses[self.walk[index % len(self.walk)]], self.intrinsics, index=index,
                            fps=self.fps, depth_noise=self.depth_noise, source=self.name)


def lap_with_stops(lap: int, stop_frames: int) -> list[int]:
    """The pose index of each frame of a lap of ``lap`` poses where the camera stands still for
    ``stop_frames`` more frames at pose 0 and at each quarter of the lap."""
    quarter = max(1, lap // 4)
    walk: list[int] = []
    for pose in range(lap):
        if stop_frames and pose % quarter == 0 and pose // quarter < 4:
            walk.extend([pose] * stop_frames)
        walk.append(pose)
    return walk


def render_frame(
    world: SyntheticWorld | SyntheticBuilding,
    T_world_cam: np.ndarray,
    intrinsics: CameraIntrinsics,
    *,
    index: int,
    fps: float,
    depth_noise: bool,
    source: str,
) -> Frame:
    """Frame ``index`` of a synthetic source: ``world`` rendered at ``T_world_cam``, depth noise drawn
    from the stream (world seed, 1000 + index), stamp ``index / fps``, instances and their categories."""
    view = world.render(T_world_cam, intrinsics)
    if depth_noise:
        rng = np.random.default_rng([world.seed, 1000 + index])
        depth_m = apply_depth_noise(view.depth_m, view.view_cos, rng)
    else:
        depth_m = np.where((view.depth_m >= DEPTH_MIN_M) & (view.depth_m <= DEPTH_MAX_M), view.depth_m, 0.0)
    depth = np.round(depth_m * DEPTH_SCALE).astype(np.uint16)
    present = np.flatnonzero(np.bincount(view.instance.ravel()))
    cats = {int(i): world.categories[int(i)] for i in present if i != 0}
    return Frame(
        frame_id=index,
        stamp_ns=int(round(index * 1e9 / fps)),
        color=view.color,
        depth=depth,
        depth_scale=DEPTH_SCALE,
        intrinsics=intrinsics,
        T_world_cam=np.array(T_world_cam, dtype=np.float64),
        instance=view.instance,
        instance_categories=cats,
        source=source,
    )


class BuildingSource(IndexedFrameSource):
    """Frames of a walk through a ``SyntheticBuilding`` (``synthetic:building,...``; streams directly).

    The walk visits the rooms of ``route`` (default: all, in order) and then the route's first
    ``revisit`` rooms again (default :data:`~openfusion.sources.synthetic_spec.DEFAULT_REVISIT`);
    ``num_frames=None`` samples it at its own density (a frame every 0.3 m or 20 degrees), a number
    spreads that many frames over it. Frames are a pure function of (seed, rooms, route, revisit,
    i, options), as the room's. ``metadata``: the world, the floor area (m^2) of the building and of
    the route, the route and the rooms in visiting order.
    """

    def __init__(
        self,
        building: SyntheticBuilding,
        num_frames: int | None = None,
        width_px: int = 640,
        height_px: int = 480,
        *,
        route: Sequence[int] | None = None,
        revisit: int | None = None,
        fps: float = 30.0,
        depth_noise: bool = True,
        intrinsics: CameraIntrinsics | None = None,
        stride: int = 1,
        max_frames: int | None = None,
    ) -> None:
        if num_frames is not None and num_frames < 1:
            raise ValueError(f"num_frames must be >= 1, got {num_frames}")
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.route = building.check_route(range(building.num_rooms) if route is None else route)
        self.revisit = default_revisit(len(self.route)) if revisit is None else int(revisit)
        self.visits = visit_order(self.route, self.revisit)
        name = f"synthetic:building,seed={building.seed},rooms={building.num_rooms},route={_route_text(self.route)}"
        super().__init__(f"{name},revisit={self.revisit}", stride=stride, max_frames=max_frames)
        self.world = building
        if intrinsics is not None and (intrinsics.width_px, intrinsics.height_px) != (width_px, height_px):
            raise ValueError(
                f"intrinsics are for {intrinsics.width_px}x{intrinsics.height_px}, frames asked for {width_px}x{height_px}"
            )
        self.intrinsics = intrinsics if intrinsics is not None else default_intrinsics(width_px, height_px)
        self.fps = float(fps)
        self.depth_noise = depth_noise
        self.poses = building.camera_path(self.route, revisit=self.revisit, frames=num_frames)
        self.num_frames = len(self.poses)

    @property
    def metadata(self) -> dict[str, object]:
        """What benches report a map against: ``floor_area_m2`` (the building),
        ``route_floor_area_m2`` (the route's rooms and the corridor), ``route``, ``visits``."""
        return {
            "world": "building",
            "seed": self.world.seed,
            "rooms": self.world.num_rooms,
            "floor_area_m2": round(self.world.floor_area_m2, 3),
            "route_floor_area_m2": round(self.world.route_floor_area_m2(self.route), 3),
            "route": list(self.route),
            "revisit": self.revisit,
            "visits": list(self.visits),
        }

    def _num_items(self) -> int:
        return self.num_frames

    def _load(self, index: int) -> Frame:
        return render_frame(self.world, self.poses[index], self.intrinsics, index=index, fps=self.fps,
                            depth_noise=self.depth_noise, source=self.name)


def _route_text(route: Sequence[int]) -> str:
    """(0, 1, 2, 3, 6) -> '0-3+6' (ascending runs as ranges; what parse_route reads back)."""
    parts, start = [], 0
    for i in range(1, len(route) + 1):
        if i == len(route) or route[i] != route[i - 1] + 1:
            a, b = route[start], route[i - 1]
            parts.append(f"{a}-{b}" if b > a else f"{a}")
            start = i
    return "+".join(parts)


def open_synthetic(spec_options: dict[str, str] | None = None, *, world: str = "room", **kwargs) -> IndexedFrameSource:
    """A ``SyntheticSource`` from ``synthetic:seed=N,frames=N,width=W,height=H,fps=F,noise=0|1,lap=N,stop=N``
    options (strings, :data:`~openfusion.sources.synthetic_spec.SPEC_KEYS`), or with
    ``world="building"`` a ``BuildingSource`` from ``synthetic:building,seed=N,rooms=N,route=A-B,
    revisit=N,frames=N,...`` options (:data:`~openfusion.sources.synthetic_spec.BUILDING_SPEC_KEYS`),
    plus keyword arguments of the source (and ``seed``; ``rooms`` for the building)."""
    if world not in WORLDS:
        raise ValueError(f"unknown synthetic world {world!r}; known: {', '.join(WORLDS)}")
    keys = BUILDING_SPEC_KEYS if world == "building" else SPEC_KEYS
    merged = dict(kwargs)
    for name, value in synthetic_options(spec_options or {}, world=world).items():
        if name in merged:
            key = next(k for k, (n, _conv) in keys.items() if n == name)
            raise ValueError(f"synthetic option {key!r} is given both in the spec and as the keyword {name!r}")
        merged[name] = value
    seed = int(merged.pop("seed", 0))
    if world == "building":
        building = SyntheticBuilding(seed, rooms=int(merged.pop("rooms", DEFAULT_ROOMS)))
        return BuildingSource(building, **merged)
    return SyntheticSource(SyntheticWorld(seed), **merged)
