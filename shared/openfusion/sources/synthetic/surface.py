"""Ground truth of the synthetic world: labelled points on its surfaces, hidden ones dropped.

``sample_surface`` samples every part's triangles uniformly (one point per ``spacing_m``^2,
area-weighted random positions, its own seeded stream) and by default keeps only points that
can be seen from inside the room: a point is visible when nothing lies within 1.5 cm in front of
it and a ray from it reaches one of a grid of viewpoints (``room_viewpoints``; in a building, those
of the room or corridor the object is in) unobstructed. Hidden faces such as box bottoms on the
floor are thus dropped, so completeness is measured against what a camera could observe.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from openfusion.sources.synthetic.furniture import WorldObject

CastFn = Callable[[np.ndarray, np.ndarray], dict[str, np.ndarray]]
"""``SyntheticWorld.cast``: (origins, directions) -> ``t_hit``, ``instance``, ``normal``."""


@dataclass
class GroundTruthSurface:
    """Labelled points on the world's surfaces."""

    points: np.ndarray  # (N, 3) float32 world metres
    instance_ids: np.ndarray  # (N,) int32, never 0
    categories: dict[int, str]  # instance id -> raw category


def sample_surface(
    objects: list[WorldObject],
    categories: dict[int, str],
    *,
    seed: int,
    room_size_m: tuple[float, float, float] | None = None,
    cast: CastFn,
    spacing_m: float,
    visible_only: bool,
    viewpoints: np.ndarray | None = None,
    stream: tuple[int, ...] = (),
) -> GroundTruthSurface:
    """Points sampled uniformly (area-weighted) on every part of ``objects``, labelled by instance;
    with ``visible_only``, only those ``_visible`` from inside the room (``cast`` casts the rays).

    The room is ``[0, W] x [0, D] x [0, H]`` (``room_size_m``) and its viewpoints a grid in it
    (:func:`room_viewpoints`), unless ``viewpoints`` ((V, 3) float32, tried in order) are given: a
    building samples each room and its corridor with that part's own viewpoints. ``stream``
    extends the seed of the sampling's random stream (a building: one stream per part)."""
    if spacing_m < 0.002:
        raise ValueError(f"spacing_m {spacing_m} would sample more than 10^7 points per 40 m^2; use >= 0.002")
    if viewpoints is None and visible_only:
        if room_size_m is None:
            raise ValueError("sample_surface needs room_size_m or viewpoints")
        W, D, H = room_size_m
        viewpoints = room_viewpoints(objects, (0.0, 0.0, W, D), H)
    rng = np.random.default_rng([seed, 11, *stream])
    pts, ids, nrm = [], [], []
    for obj in objects:
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
    if not pts:
        return GroundTruthSurface(np.zeros((0, 3), np.float32), np.zeros(0, np.int32), {})
    points = np.concatenate(pts)
    instance_ids = np.concatenate(ids)
    normals = np.concatenate(nrm)
    if visible_only:
        keep = _visible(points, normals, viewpoints, cast)
        points, instance_ids = points[keep], instance_ids[keep]
    present = {int(i) for i in np.unique(instance_ids)}
    cats = {i: c for i, c in categories.items() if i in present}
    return GroundTruthSurface(points.astype(np.float32), instance_ids.astype(np.int32), cats)


def room_viewpoints(
    objects: list[WorldObject], rect_m: tuple[float, float, float, float], height_m: float
) -> np.ndarray:
    """Viewpoints on a ~1.1 m grid at four heights over the floor rectangle ``rect_m`` =
    (x0, y0, x1, y1) of a room ``height_m`` high, outside every object, centre first."""
    x0, y0, x1, y1 = rect_m
    W, D, H = x1 - x0, y1 - y0, height_m
    xs = np.linspace(x0 + 0.4, x1 - 0.4, max(3, int(round(W / 1.1))))
    ys = np.linspace(y0 + 0.4, y1 - 0.4, max(3, int(round(D / 1.1))))
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
                    for o in objects
                )
                if not inside:
                    out.append((x, y, z))
    vp = np.array(out, dtype=np.float32)
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 1.5], dtype=np.float32)
    return vp[np.argsort(np.linalg.norm(vp - centre, axis=1), kind="stable")]


def _visible(points: np.ndarray, normals: np.ndarray, viewpoints: np.ndarray, cast: CastFn) -> np.ndarray:
    nrm = normals.astype(np.float32)
    origin = (points + 0.004 * normals).astype(np.float32)
    # a surface within 1.5 cm in front of the point hides it (faces resting on other faces)
    free = cast(origin, nrm)["t_hit"] > 0.015
    todo = np.flatnonzero(free)
    visible = np.zeros(len(points), dtype=bool)
    for v in viewpoints:
        if todo.size == 0:
            break
        d = v - origin[todo]
        facing = np.einsum("nc,nc->n", d, nrm[todo]) > 0
        sub, d = todo[facing], d[facing]
        if sub.size == 0:
            continue
        length = np.linalg.norm(d, axis=1)
        # t_hit is in units of |d|: a hit before reaching the viewpoint blocks the view
        seen = cast(origin[sub], d)["t_hit"] * length >= length - 0.01
        visible[sub[seen]] = True
        todo = todo[~visible[todo]]
    return visible
