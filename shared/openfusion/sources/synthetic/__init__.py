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

Modules (each owns one part; this package re-exports the public names)
    ``furniture``  mesh primitives, ``Part``/``WorldObject``, palette and ``CATEGORIES``, object builders
    ``layout``     the room and where the furniture goes (the seeded draws that make a room)
    ``textures``   the procedural texture atlas
    ``camera``     ``default_intrinsics``, per-pixel rays, the camera path (a closed lap of ``LAP_FRAMES``)
    ``render``     the ray-cast scene, shading tables, ``RenderedView``
    ``surface``    ``GroundTruthSurface`` and the visible-surface sampling
    ``depth``      depth units/range (``DEPTH_*``, ``GRAZING_COS``) and ``apply_depth_noise``
    ``world``      ``SyntheticWorld``, tying the above together
    ``floorplan``  the building: a corridor with furnished rooms (``layout``'s) on both sides, doorways
    ``walk``       a route of rooms turned into a collision-free camera walk (grid, shortest paths)
    ``building``   ``SyntheticBuilding``: the building's world (same interface as ``SyntheticWorld``)
    ``source``     ``SyntheticSource``, ``BuildingSource`` and ``open_synthetic``

The building (``synthetic:building,rooms=10,route=0-3,revisit=2``) is documented in
``floorplan`` (the plan), ``walk`` (routes and the trajectory) and ``building`` (rendering and
ground truth); docs/BUILDING.md has the commands.
"""

from __future__ import annotations

from openfusion.sources.synthetic.building import SyntheticBuilding
from openfusion.sources.synthetic.camera import LAP_FRAMES, default_intrinsics
from openfusion.sources.synthetic.camera import _pixel_rays as _pixel_rays
from openfusion.sources.synthetic.depth import (
    DEPTH_MAX_M,
    DEPTH_MIN_M,
    DEPTH_SCALE,
    GRAZING_COS,
    apply_depth_noise,
)
from openfusion.sources.synthetic.furniture import CATEGORIES, Part, WorldObject
from openfusion.sources.synthetic.render import RenderedView
from openfusion.sources.synthetic.source import BuildingSource, SyntheticSource, open_synthetic
from openfusion.sources.synthetic.surface import GroundTruthSurface
from openfusion.sources.synthetic.world import SyntheticWorld

__all__ = [
    "CATEGORIES",
    "BuildingSource",
    "DEPTH_MAX_M",
    "DEPTH_MIN_M",
    "DEPTH_SCALE",
    "GRAZING_COS",
    "LAP_FRAMES",
    "GroundTruthSurface",
    "Part",
    "RenderedView",
    "SyntheticBuilding",
    "SyntheticSource",
    "SyntheticWorld",
    "WorldObject",
    "apply_depth_noise",
    "default_intrinsics",
    "open_synthetic",
    "write_scannet_layout",
]


def __getattr__(name: str):
    # write_scannet_layout lives in its own module (it writes any source); exported here too.
    if name == "write_scannet_layout":
        from openfusion.sources.scannet_writer import write_scannet_layout

        return write_scannet_layout
    raise AttributeError(name)
