"""Rendering a building only where a camera can see: cells joined by portals (its doorways).

A building's objects are split into cells (the corridor, each room) that are closed except for
their portals: a doorway's opening in the corridor's wall, shared by the corridor and the room
behind it. A view is cast into a small Embree scene around the camera: its own cell, joined
(when the camera is in the corridor) with the room whose doorway it faces; the rays that hit a
portal of that scene go on from there into the cell behind it (at most corridor -> room or
room -> corridor -> room), in scenes of that cell alone. This is the portal visibility of indoor
renderers (Luebke & Georges, "Portals and Mirrors", 1995).

Why: a view cast into the whole building costs about 1.3x a view of the built-in room (Embree's
traversal grows with the scene: 47,000 triangles for 10 rooms against 4,000), one cast into a
room-sized scene about 1.0x, and most rays of a view stay in the camera's room or go through the
one doorway it faces (``bench/bench_building_render.py`` measures the three).

Exact: the cells' geometry meets exactly at the portals (nothing of a cell lies on the other side
of its portals' planes; :mod:`~openfusion.sources.synthetic.floorplan`), a ray that came in
through a portal goes on from just before its plane in a scene without that portal (a straight ray
never goes back out the way it came in), so every ray finds the first surface the whole building
would give it (tested: the same instance and depth on every pixel of a walk). Where a camera is not
clearly in one cell (within :data:`PORTAL_MARGIN_M` of a portal's plane, or outside every cell) the
view is cast into the whole building.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from openfusion.sources.synthetic.furniture import WorldObject
from openfusion.sources.synthetic.render import SceneRenderer

#: A ray that went through a portal goes on in the next cell from this far before it (in units of
#: its direction's length, at least 1 for a view's rays: 0.1 mm; nothing of the next cell lies on
#: this side of the portal's plane, and the scene it goes on in lacks that portal).
PORTAL_STEP = 1e-4
#: A view from within this distance of a portal's plane (in its doorway) is cast into the whole building.
PORTAL_MARGIN_M = 2e-3
#: Corridor -> room is the longest way a view's ray goes through portals (room -> corridor ->
#: room from a room); more hops than this end the ray as a miss.
MAX_HOPS = 4

#: A view's first cast joins the cell behind the portal that takes more than this share of its rays
#: (estimated on every 16th pixel): one cast into a bigger scene then costs less than casting
#: those rays again (a room joined with the corridor costs about 1.15x the room alone).
JOIN_FRACTION = 0.12
#: ``locate(position)``: the camera's cell, or None when it is not clearly in one.
Locate = Callable[[np.ndarray], "int | None"]


@dataclass(frozen=True)
class Portal:
    """An opening between two cells: a planar quad (4, 3; a parallelogram, corners in order) and
    the two cells' indices."""

    quad: np.ndarray
    cells: tuple[int, int]

    def other(self, cell: int) -> int:
        return self.cells[1] if cell == self.cells[0] else self.cells[0]


def portal_shares(quads: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """(P,) the share of ``rays`` (N, 6) that cross each portal quad ((P, 4, 3), parallelograms)
    ahead of their origin; occlusion is not counted (an estimate for choosing scenes, never for
    what a ray hits)."""
    q0, e1, e3 = quads[:, 0], quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0]
    n = np.cross(e1, e3)  # (P, 3)
    o, d = rays[:, :3].astype(np.float64), rays[:, 3:].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.einsum("pc,pc->p", q0, n)[None, :] - o @ n.T) / (d @ n.T)  # (N, P)
        inside = t > 0
        for e in (e1, e3):  # the hit's coordinate along each edge, in [0, 1]
            coord = ((o @ e.T) + t * (d @ e.T) - np.einsum("pc,pc->p", q0, e)[None, :]) / np.einsum("pc,pc->p", e, e)
            inside &= (coord >= 0) & (coord <= 1)
    return inside.mean(axis=0) if len(rays) else np.zeros(len(quads))



class _Scene:
    """An Embree scene of some cells' surfaces, then some portals (two triangles each).

    ``tri_of`` maps a primitive id (clipped to its last entry, which stands for a miss) to a global
    triangle index (a portal's and a miss: ``miss``); ``far`` maps a portal primitive (less
    ``surface_tris``) to (portal index, the cell behind it)."""

    def __init__(self, surfaces: list[tuple[np.ndarray, np.ndarray, np.ndarray]], portals: list[tuple[int, np.ndarray, int]],
                 miss: int) -> None:
        verts, tris, global_tri = [], [], []
        offset = 0
        for V, F, g in surfaces:
            verts.append(V)
            tris.append(F + np.uint32(offset))
            global_tri.append(g)
            offset += len(V)
        for k, (_p, quad, _far) in enumerate(portals):
            verts.append(quad.astype(np.float32))
            tris.append(np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32) + np.uint32(offset + 4 * k))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.concatenate(verts)), o3d.core.Tensor(np.concatenate(tris)))
        self.surface_tris = sum(len(F) for _V, F, _g in surfaces)
        self.miss = np.uint32(miss)
        # a portal's primitives map past the miss index (miss + 1 + slot), so one gather and one
        # comparison find the rays that left; a miss maps to the miss index
        slots = np.arange(2 * len(portals), dtype=np.int64) + miss + 1
        self.tri_of = np.concatenate(global_tri + [slots, [miss]]).astype(np.uint32)
        self.portal = np.repeat(np.array([p for p, _q, _f in portals], dtype=np.int64), 2)
        self.far = np.repeat(np.array([f for _p, _q, f in portals], dtype=np.int64), 2)

    def cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(global triangle, t_hit, normal, portal, cell behind it) of ``rays`` (..., 6): a ray that
        left through a portal has its index (else -1), the miss triangle and its t_hit at the
        portal; ``portal`` and ``cell`` are None when no ray left."""
        ans = self.scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
        tri = self.tri_of[np.minimum(ans["primitive_ids"].numpy(), np.uint32(len(self.tri_of) - 1))]
        through = tri > self.miss
        if not through.any():
            return tri, ans["t_hit"].numpy(), ans["primitive_normals"].numpy(), None, None
        slot = tri[through].astype(np.int64) - (int(self.miss) + 1)
        portal = np.full(tri.shape, -1, dtype=np.int64)
        far = portal.copy()
        portal[through] = self.portal[slot]
        far[through] = self.far[slot]
        tri[through] = self.miss
        return tri, ans["t_hit"].numpy(), ans["primitive_normals"].numpy(), portal, far


class PortalRenderer(SceneRenderer):
    """A ``SceneRenderer`` whose views are cast cell by cell through portals.

    ``cells``: the instance ids of each cell (every object in exactly one); ``portals``: the
    openings between them; ``locate``: see :data:`Locate`. ``cast`` and ``scene`` stay the whole
    building's. Scenes are built on first use: a cell's (with its portals), a cell joined with a
    neighbour (the portal between them left out), a cell entered through one of its portals (that
    portal left out)."""

    def __init__(self, objects: list[WorldObject], cells: Sequence[Sequence[int]], portals: Sequence[Portal], locate: Locate) -> None:
        super().__init__(objects)
        first: dict[int, tuple[int, int]] = {}  # instance id -> (first global triangle, count)
        offset = 0
        for obj in objects:
            n = sum(len(p.triangles) for p in obj.parts)
            first[obj.instance_id] = (offset, n)
            offset += n
        by_id = {obj.instance_id: obj for obj in objects}
        self._surfaces = []
        for ids in cells:
            verts, tris, global_tri = [], [], []
            v_off = 0
            for iid in ids:
                start, n = first[iid]
                global_tri.append(np.arange(start, start + n))
                for part in by_id[iid].parts:
                    verts.append(part.vertices)
                    tris.append(part.triangles + v_off)
                    v_off += len(part.vertices)
            self._surfaces.append((np.concatenate(verts).astype(np.float32), np.concatenate(tris).astype(np.uint32),
                                   np.concatenate(global_tri)))
        self._portals = list(portals)
        self._portals_of = [[k for k, p in enumerate(self._portals) if c in p.cells] for c in range(len(cells))]
        self._quads = np.array([p.quad for p in self._portals], dtype=np.float64).reshape(-1, 4, 3)
        self._locate = locate
        self._scenes: dict[tuple[tuple[int, ...], int | None], _Scene] = {}

    def _scene_of(self, cells: tuple[int, ...], without: int | None) -> _Scene:
        """The scene of ``cells`` with every portal of theirs that leads out of them, but ``without``."""
        key = (cells, without)
        scene = self._scenes.get(key)
        if scene is None:
            portals = [(k, p.quad, next(c for c in p.cells if c not in cells)) for k, p in enumerate(self._portals)
                       if k != without and set(p.cells) & set(cells) and not set(p.cells) <= set(cells)]
            scene = self._scenes[key] = _Scene([self._surfaces[c] for c in cells], portals, self.miss_index)
        return scene

    def _view_hits(self, rays: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        h, w = rays.shape[:2]
        cell = self._locate(origin)
        if cell is None:
            return super()._view_hits(rays, origin)
        join = None
        mine = self._portals_of[cell]
        if mine:
            shares = portal_shares(self._quads[mine], rays[::16, ::16].reshape(-1, 6))
            if shares.max() > JOIN_FRACTION:
                join = mine[int(np.argmax(shares))]
        start = (cell,) if join is None else tuple(sorted((cell, self._portals[join].other(cell))))
        # the camera's cell (and the room it faces), every ray at once, as the whole scene would be ...
        tri, t_hit, normals, portal, far = self._scene_of(start, join).cast(rays)
        if portal is None:
            return tri, t_hit, normals
        left = portal >= 0
        # ... then only the rays that left it, each through its portal into the cell behind (and on)
        tri, t_hit, normals = tri.reshape(-1), t_hit.reshape(-1), normals.reshape(-1, 3)
        at = np.flatnonzero(left.reshape(-1))
        flat = rays.reshape(-1, 6)
        work = [(at, flat[at], np.zeros(len(at), dtype=np.float32), t_hit[at], portal.reshape(-1)[at], far.reshape(-1)[at])]
        for _ in range(MAX_HOPS):
            ahead = []
            for ids, r, t0, t_portal, via, into in work:
                step = t_portal - np.float32(PORTAL_STEP)  # go on from just before the portal's plane
                r[:, :3] += r[:, 3:] * step[:, None]
                base = t0 + step
                present = np.flatnonzero(np.bincount(via))
                for p in present:
                    sel = slice(None) if len(present) == 1 else via == p
                    n_tri, n_th, n_nrm, n_portal, n_far = self._scene_of((int(into[sel][0]),), int(p)).cast(r[sel])
                    sub = ids[sel]
                    tri[sub] = n_tri
                    t_hit[sub] = base[sel] + n_th
                    normals[sub] = n_nrm
                    if n_portal is None:
                        continue
                    on = n_portal >= 0
                    if on.any():
                        ahead.append((sub[on], r[sel][on], base[sel][on], n_th[on], n_portal[on], n_far[on]))
            work = ahead
            if not work:
                break
        for ids, *_rest in work:  # still going after MAX_HOPS (not in a building): no hit
            tri[ids], t_hit[ids] = self.miss_index, np.inf
        return tri.reshape(h, w), t_hit.reshape(h, w), normals.reshape(h, w, 3)
