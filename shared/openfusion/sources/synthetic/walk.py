"""A walk through the synthetic building: a list of rooms to visit turned into camera poses.

Route as data
    The walk is made from the list of rooms it visits (:func:`visit_order`: the route, then its
    first ``revisit`` rooms again), so two robots can be given different routes through the same
    building (rooms 0-3 and 4-7 share the corridor's first stretch) and one robot both. Each
    room visit is the same whatever route it is part of (at the default frame density, its frames
    are identical too); only the corridor legs between visits depend on the route.

One room visit (:func:`room_visit`)
    From the corridor's centre line in front of the doorway: turn to face the doorway, walk
    :data:`ENTRY_M` into the room, look around: a loop through up to four viewpoints (one per
    quarter of the room, at the free spot nearest the quarter's centre that keeps the most
    clearance), looking across the room at its furniture with a slow sweep (so each wall's
    furniture is seen from several places and directions), back to the entry point, turn round
    and walk out. The loop is planned on a 5 cm occupancy grid of the room (every footprint of
    furniture, the walls), keeping :data:`ROBOT_CLEARANCE_M` from both (a robot's radius and a
    margin), with Dijkstra's shortest paths (scipy) pulled straight where the line stays clear.
    A viewpoint the entry cannot reach is left out; a room with none is looked at from the
    entry point, panning.

Corridor legs
    On the corridor's centre line: turn in place to face along it, walk, turn to face the next
    doorway. The walk starts at :data:`START_X_M` facing along the corridor.

Frames
    Keyposes are (x, y, yaw, pitch); the camera is :data:`CAMERA_HEIGHT_M` above the floor and
    pitched down (more inside rooms, to see the furniture). Frames are spread evenly over the
    walk's cost, counted in steps: the larger of metres walked / :data:`STEP_M` (0.3 m) and
    radians turned / :data:`STEP_RAD` (20 degrees), so turning in place gets frames as walking
    does. By default each piece (a room visit, a corridor leg) gets ``ceil(cost)`` frames of its
    own (so no frame moves more than a step from the last, and a room visit's frames do not
    depend on the route); ``frames=N`` spreads exactly N frames over the whole walk instead.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from openfusion.poses import look_at
from openfusion.sources.synthetic.floorplan import BuildingRoom, Floorplan

GRID_M = 0.05
#: The camera's centre keeps this far from walls and furniture footprints (a robot's radius + margin).
ROBOT_CLEARANCE_M = 0.40
CAMERA_HEIGHT_M = 1.45
#: How far into a room the walk goes through the doorway before looking around (m).
ENTRY_M = 1.0
#: Where the walk starts on the corridor's centre line (m from its west end).
START_X_M = 1.2
#: By default a frame every this many metres walked ...
STEP_M = 0.3
#: ... or this many radians turned (yaw + pitch), whichever comes first.
STEP_RAD = math.radians(20.0)
PITCH_CORRIDOR_RAD = math.radians(-8.0)
PITCH_ROOM_RAD = math.radians(-16.0)
#: Look-around inside a room: the view sweeps this far (rad) either side of the room's centre ...
SWEEP_RAD = 0.4
#: ... once per this many metres walked.
SWEEP_PERIOD_M = 4.0
#: Up to four viewpoints per room, at these fractions of its width and depth.
_QUARTERS = ((0.28, 0.30), (0.72, 0.30), (0.72, 0.70), (0.28, 0.70))


def visit_order(route: Sequence[int], revisit: int) -> list[int]:
    """The rooms in the order visited: ``route``, then its first ``revisit`` rooms again."""
    if revisit < 0 or revisit > len(route):
        raise ValueError(f"revisit must be between 0 and the route's {len(route)} rooms, got {revisit}")
    return [*route, *route[:revisit]]


def _wrap(a: float | np.ndarray) -> float | np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# --------------------------------------------------------------------------------- room grid


class RoomGrid:
    """Occupancy of one room's floor on a :data:`GRID_M` grid: which cell centres keep
    :data:`ROBOT_CLEARANCE_M` from the walls and from every footprint in the room."""

    def __init__(self, room: BuildingRoom, footprints: Sequence[tuple[float, float, float, float]]) -> None:
        x0, y0, x1, y1 = room.rect_m
        self.origin = np.array([x0, y0])
        self.shape = (int(math.ceil((x1 - x0) / GRID_M)), int(math.ceil((y1 - y0) / GRID_M)))
        xs = x0 + (np.arange(self.shape[0]) + 0.5) * GRID_M
        ys = y0 + (np.arange(self.shape[1]) + 0.5) * GRID_M
        free = np.ones(self.shape, dtype=bool)
        half = GRID_M / 2
        for fx0, fy0, fx1, fy1 in footprints:  # every cell a footprint touches, however thin
            ix = (xs + half >= fx0) & (xs - half <= fx1)
            iy = (ys + half >= fy0) & (ys - half <= fy1)
            free[np.ix_(ix, iy)] = False
        padded = np.zeros((self.shape[0] + 2, self.shape[1] + 2), dtype=bool)  # walls all round
        padded[1:-1, 1:-1] = free
        # distance between cell centres, less a cell: never more than the true clearance
        self.clearance_m = ndimage.distance_transform_edt(padded)[1:-1, 1:-1] * GRID_M - GRID_M
        self.walkable = self.clearance_m >= ROBOT_CLEARANCE_M
        self._csr = None  # the walkable cells' graph, built on the first shortest path

    def cell(self, p: np.ndarray) -> tuple[int, int]:
        i, j = np.floor((np.asarray(p, dtype=np.float64) - self.origin) / GRID_M).astype(int)
        return int(np.clip(i, 0, self.shape[0] - 1)), int(np.clip(j, 0, self.shape[1] - 1))

    def centre(self, cell: tuple[int, int]) -> np.ndarray:
        return self.origin + (np.asarray(cell, dtype=np.float64) + 0.5) * GRID_M

    def clear_line(self, a: np.ndarray, b: np.ndarray) -> bool:
        """Every point of the segment a-b (sampled every half cell) is on a walkable cell."""
        n = max(2, int(np.linalg.norm(b - a) / (GRID_M / 2)) + 2)
        pts = a[None, :] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None, :]
        idx = np.floor((pts - self.origin) / GRID_M).astype(int)
        inside = (idx >= 0).all(1) & (idx[:, 0] < self.shape[0]) & (idx[:, 1] < self.shape[1])
        return bool(inside.all() and self.walkable[idx[:, 0], idx[:, 1]].all())

    def _graph(self):  # noqa: ANN202 - a scipy sparse matrix
        nx, ny = self.shape
        ids = np.arange(nx * ny).reshape(nx, ny)
        rows, cols, weights = [], [], []
        for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):  # each neighbour pair once (undirected)
            i1, j0, j1 = nx - di, max(0, -dj), ny - max(0, dj)
            both = self.walkable[:i1, j0:j1] & self.walkable[di : i1 + di, j0 + dj : j1 + dj]
            rows.append(ids[:i1, j0:j1][both])
            cols.append(ids[di : i1 + di, j0 + dj : j1 + dj][both])
            weights.append(np.full(int(both.sum()), GRID_M * math.hypot(di, dj)))
        r, c, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
        return coo_matrix((w, (r, c)), shape=(nx * ny, nx * ny)).tocsr()

    def shortest_path(self, a: np.ndarray, b: np.ndarray) -> list[np.ndarray] | None:
        """Points from ``a`` to ``b`` (both walkable) along walkable cells, pulled straight where
        the line stays clear; None when ``b`` cannot be reached."""
        if self._csr is None:
            self._csr = self._graph()
        graph = self._csr
        ca, cb = self.cell(a), self.cell(b)
        ia, ib = ca[0] * self.shape[1] + ca[1], cb[0] * self.shape[1] + cb[1]
        dist, pred = dijkstra(graph, directed=False, indices=ia, return_predecessors=True)
        if not np.isfinite(dist[ib]):
            return None
        chain = [ib]
        while chain[-1] != ia:
            chain.append(int(pred[chain[-1]]))
        cells = [np.array(divmod(c, self.shape[1])) for c in reversed(chain)]
        pts = [np.asarray(a, dtype=np.float64)] + [self.centre(c) for c in cells[1:-1]] + [np.asarray(b, dtype=np.float64)]
        out = [pts[0]]
        i = 0
        while i < len(pts) - 1:  # string pulling: the farthest point still in clear sight
            j = len(pts) - 1
            while j > i + 1 and not self.clear_line(pts[i], pts[j]):
                j -= 1
            out.append(pts[j])
            i = j
        return out

    def best_spot(self, target: np.ndarray, reachable: np.ndarray, *, radius_m: float = 1.2) -> np.ndarray | None:
        """The reachable cell near ``target`` that balances clearance (up to 0.8 m counts) and
        distance to it; None when none lies within ``radius_m``."""
        centres_x = self.origin[0] + (np.arange(self.shape[0]) + 0.5) * GRID_M
        centres_y = self.origin[1] + (np.arange(self.shape[1]) + 0.5) * GRID_M
        d = np.hypot(centres_x[:, None] - target[0], centres_y[None, :] - target[1])
        ok = reachable & (d <= radius_m)
        if not ok.any():
            return None
        score = np.where(ok, np.minimum(self.clearance_m, 0.8) - 0.5 * d, -np.inf)
        i, j = np.unravel_index(int(np.argmax(score)), score.shape)
        return self.centre((int(i), int(j)))


# --------------------------------------------------------------------------------- pieces


def _densify(points: Sequence[np.ndarray], spacing_m: float = GRID_M) -> np.ndarray:
    out = [np.asarray(points[0], dtype=np.float64)]
    for a, b in zip(points[:-1], points[1:], strict=True):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / spacing_m)))
        for k in range(1, n + 1):
            out.append(a + (b - a) * (k / n))
    return np.array(out)


def room_visit(plan: Floorplan, room: BuildingRoom, footprints: Sequence[tuple[float, float, float, float]]) -> np.ndarray:
    """(K, 4) keyposes (x, y, yaw, pitch) of one visit of ``room``, from the corridor's centre
    line in front of its doorway back to it."""
    yc = plan.corridor_width_m / 2
    inward = room.inward_y
    wall_y = room.rect_m[1] if inward > 0 else room.rect_m[3]
    outside = np.array([room.door_x_m, yc])
    entry = np.array([room.door_x_m, wall_y + inward * ENTRY_M])
    yaw_in = math.atan2(inward, 0.0)
    yaw_out = float(_wrap(yaw_in + math.pi))
    grid = RoomGrid(room, footprints)
    keys: list[tuple[float, float, float, float]] = [
        (*outside, yaw_in, PITCH_CORRIDOR_RAD),
        (*entry, yaw_in, PITCH_CORRIDOR_RAD),
    ]
    x0, y0, x1, y1 = room.rect_m
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    labels, _ = ndimage.label(grid.walkable)
    home = labels[grid.cell(entry)]
    spots = []
    if home:
        reachable = labels == home
        for fx, fy in _QUARTERS:
            spot = grid.best_spot(np.array([x0 + fx * (x1 - x0), y0 + fy * (y1 - y0)]), reachable)
            if spot is not None:
                spots.append(spot)
    if spots:
        # a loop round the room's centre, starting with the viewpoint nearest the entry
        ang = [math.atan2(s[1] - centre[1], s[0] - centre[0]) for s in spots]
        order = sorted(range(len(spots)), key=lambda k: ang[k])
        first = min(order, key=lambda k: np.linalg.norm(spots[k] - entry))
        order = order[order.index(first) :] + order[: order.index(first)]
        stops = [entry] + [spots[k] for k in order] + [entry]
        path: list[np.ndarray] = [entry]
        for stop in stops[1:]:
            leg = grid.shortest_path(path[-1], stop)
            if leg is not None:  # always, for spots in the entry's component; never a jump
                path.extend(leg[1:])
        dense = _densify(path)
        walked = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
        yaw = yaw_in
        for p, s in zip(dense, walked, strict=True):
            to_centre = centre - p
            if np.linalg.norm(to_centre) > 0.6:  # near the centre: keep the last direction
                yaw = math.atan2(to_centre[1], to_centre[0]) + SWEEP_RAD * math.sin(2 * math.pi * s / SWEEP_PERIOD_M)
            keys.append((float(p[0]), float(p[1]), float(yaw), PITCH_ROOM_RAD))
    else:  # nowhere to go: pan from the entry
        look = math.atan2(*(centre - entry)[::-1])
        for a in (0.0, 1.2, -1.2, 0.0):
            keys.append((float(entry[0]), float(entry[1]), look + a, PITCH_ROOM_RAD))
    keys.append((*entry, yaw_out, PITCH_CORRIDOR_RAD))
    keys.append((*outside, yaw_out, PITCH_CORRIDOR_RAD))
    return np.array(keys, dtype=np.float64)


def corridor_leg(plan: Floorplan, x_from: float, yaw_from: float, x_to: float, yaw_to: float) -> np.ndarray:
    """(K, 4) keyposes along the corridor's centre line: turn to face along it, walk, turn to ``yaw_to``."""
    yc = plan.corridor_width_m / 2
    p = PITCH_CORRIDOR_RAD
    if abs(x_to - x_from) < 1e-9:
        return np.array([(x_from, yc, yaw_from, p), (x_to, yc, yaw_to, p)])
    heading = 0.0 if x_to > x_from else math.pi
    return np.array([(x_from, yc, yaw_from, p), (x_from, yc, heading, p), (x_to, yc, heading, p), (x_to, yc, yaw_to, p)])


# --------------------------------------------------------------------------------- sampling


def _costs(keys: np.ndarray) -> np.ndarray:
    """Cumulative walk cost at each keypose (0 at the first), in default steps: a segment costs the
    larger of its metres walked / :data:`STEP_M` and its radians turned / :data:`STEP_RAD`."""
    if len(keys) < 2:
        return np.zeros(len(keys))
    d = np.diff(keys, axis=0)
    step = np.maximum(np.hypot(d[:, 0], d[:, 1]) / STEP_M, (np.abs(_wrap(d[:, 2])) + np.abs(d[:, 3])) / STEP_RAD)
    return np.concatenate([[0.0], np.cumsum(step)])


def _sample(keys: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Keyposes interpolated at the walk costs ``at`` (position and pitch linearly, yaw the short way)."""
    cost = _costs(keys)
    seg = np.clip(np.searchsorted(cost, at, side="right") - 1, 0, len(keys) - 2)
    span = cost[seg + 1] - cost[seg]
    f = np.where(span > 0, (at - cost[seg]) / np.where(span > 0, span, 1.0), 0.0)
    a, b = keys[seg], keys[seg + 1]
    out = a + (b - a) * f[:, None]
    out[:, 2] = _wrap(a[:, 2] + _wrap(b[:, 2] - a[:, 2]) * f)
    return out


def sample_walk(pieces: Sequence[np.ndarray], frames: int | None = None) -> np.ndarray:
    """(N, 4) samples of the walk made of ``pieces`` (consecutive pieces share their end keypose).

    ``frames=None``: each piece gets ``ceil(cost)`` samples from its start (its end is the next
    piece's start; so no frame walks more than :data:`STEP_M` or turns more than :data:`STEP_RAD`
    from the last), plus the walk's last keypose. ``frames=N``: N samples spread evenly over the
    whole walk's cost, first and last keypose included."""
    if frames is not None:
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        walk = np.concatenate([pieces[0]] + [p[1:] for p in pieces[1:]])
        total = _costs(walk)[-1]
        return _sample(walk, np.linspace(0.0, total, frames) if frames > 1 else np.zeros(1))
    out = []
    for piece in pieces:
        total = _costs(piece)[-1]
        n = max(1, int(math.ceil(total - 1e-9)))
        out.append(_sample(piece, total * np.arange(n) / n))
    out.append(pieces[-1][-1:].copy())
    return np.concatenate(out)


def poses_from_samples(samples: np.ndarray, *, height_m: float = CAMERA_HEIGHT_M) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses (OpenCV axes) from (x, y, yaw, pitch) samples."""
    poses = np.empty((len(samples), 4, 4))
    for i, (x, y, yaw, pitch) in enumerate(samples):
        pos = np.array([x, y, height_m])
        forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
        poses[i] = look_at(pos, pos + forward)
    return poses
