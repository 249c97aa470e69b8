"""The synthetic building's floor plan: a corridor with furnished rooms on both sides, a doorway into each.

Plan (world metres, z up, floor at z = 0, one ceiling height for the whole building)::

      y
      ^   | room 0 | room 2 | room 4 |  ...        north rooms: even indices, doorway in their south wall
      |   +---  ---+---  ---+---  ---+
      |     corridor  (interior x in [0, L], y in [0, Cw])
      |   +---  ---+---  ---+---  ---+
      |   | room 1 | room 3 | room 5 |  ...        south rooms: odd indices, doorway in their north wall
      +----------------------------------> x

Room ``k`` is in bay ``k // 2`` along the corridor (bay 0 after a lobby of :data:`LOBBY_M` at
x = 0), so rooms 0-3 are the first two bays and rooms 4-7 the next two: routes through
neighbouring rooms share the corridor's start. The two rooms of a bay have the same width
(5.5..7 m, along x) and their own depth (4.5..6 m); walls are :data:`WALL_THICKNESS_M` thick
(every wall is a room's or the corridor's own, inward-facing surface; the reveal of each doorway
closes the wall's cavity). A doorway is :data:`DOORWAY_WIDTH_M` x :data:`DOORWAY_HEIGHT_M`; its
door stands open at 90 degrees beside it, inside the room, and the floor in front of it is kept
free of furniture (:data:`DOOR_ENTRY_DEPTH_M`), so a robot can always get in.

Rooms are furnished by the built-in room's own layout (:class:`~.layout.RoomLayout`, in the room's
frame, then moved into place), without the fake door on a wall. The corridor is split into one
wall / floor / ceiling instance per bay on each side (as an annotator would label a long
corridor), with pictures on its walls and plants in its lobby corners.

Determinism: every part draws from its own stream (building: ``[seed, 33]``, bay ``j``:
``[seed, 33, 1, j]``, room ``k``: ``[seed, 33, 2, k]``, corridor: ``[seed, 33, 3]``), so a room is
the same in every building of the same seed that has it, whatever the number of rooms.
Instance ids run from 1 over the whole building: the corridor first, then room 0, room 1, ...
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from openfusion.sources.synthetic.furniture import (
    _PALETTE,
    Part,
    WorldObject,
    _build_door,
    _build_picture,
    _build_plant,
    _quad,
)
from openfusion.sources.synthetic.layout import RoomLayout, facing_quad

WALL_THICKNESS_M = 0.15
DOORWAY_WIDTH_M = 1.0
DOORWAY_HEIGHT_M = 2.1
#: Corridor beyond the first and the last bay (m).
LOBBY_M = 1.6
#: Depth of the floor kept free inside a room in front of its doorway (m).
DOOR_ENTRY_DEPTH_M = 1.6
#: Room widths (along the corridor), depths and the building's height are drawn from these (m).
ROOM_WIDTH_RANGE_M = (5.5, 7.0)
ROOM_DEPTH_RANGE_M = (4.5, 6.0)
HEIGHT_RANGE_M = (2.7, 3.0)
CORRIDOR_WIDTH_RANGE_M = (2.0, 2.4)
_E = RoomLayout.CORNER_OVERLAP_M


@dataclass(frozen=True)
class BuildingRoom:
    """One room of the building, in world coordinates."""

    index: int
    side: str  # "north" (y > corridor) or "south" (y < 0)
    rect_m: tuple[float, float, float, float]  # interior floor (x0, y0, x1, y1)
    door_x_m: float  # the doorway's centre along the corridor
    instance_ids: tuple[int, ...]
    portal_y_m: float  # the plane of the corridor's wall the doorway opens in (the room's cell starts there)

    @property
    def doorway_x_m(self) -> tuple[float, float]:
        """The doorway's opening along the corridor (m)."""
        return (self.door_x_m - DOORWAY_WIDTH_M / 2, self.door_x_m + DOORWAY_WIDTH_M / 2)

    def portal_quad(self) -> np.ndarray:
        """(4, 3) the doorway's opening in the corridor's wall, floor (less the walls' overlap) to lintel."""
        a, b = self.doorway_x_m
        y = self.portal_y_m
        return np.array([[a, y, -_E], [b, y, -_E], [b, y, DOORWAY_HEIGHT_M], [a, y, DOORWAY_HEIGHT_M]])

    def contains(self, xy: np.ndarray) -> bool:
        """``xy`` lies in the room or in its doorway (the wall's thickness, between the jambs)."""
        x, y = float(xy[0]), float(xy[1])
        x0, y0, x1, y1 = self.rect_m
        if x0 <= x <= x1 and y0 <= y <= y1:
            return True
        a, b = self.doorway_x_m
        lo, hi = (self.portal_y_m, y0) if self.side == "north" else (y1, self.portal_y_m)
        return a <= x <= b and lo < y < hi

    @property
    def inward_y(self) -> float:
        """+1 when the room lies north of the corridor (entering is +y), -1 south."""
        return 1.0 if self.side == "north" else -1.0

    @property
    def floor_area_m2(self) -> float:
        x0, y0, x1, y1 = self.rect_m
        return (x1 - x0) * (y1 - y0)

    @property
    def centre_m(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.rect_m
        return ((x0 + x1) / 2, (y0 + y1) / 2)


@dataclass
class Floorplan:
    """The building's objects (ids 1..N) and where its rooms and corridor are."""

    height_m: float
    corridor_width_m: float
    corridor_length_m: float
    rooms: tuple[BuildingRoom, ...]
    corridor_instance_ids: tuple[int, ...]
    objects: list[WorldObject] = field(default_factory=list)

    @property
    def corridor_rect_m(self) -> tuple[float, float, float, float]:
        return (0.0, 0.0, self.corridor_length_m, self.corridor_width_m)

    @property
    def floor_area_m2(self) -> float:
        """Interior floor of the rooms and the corridor (doorway thresholds not counted)."""
        return self.corridor_length_m * self.corridor_width_m + sum(r.floor_area_m2 for r in self.rooms)


def wall_with_openings(
    start_xy: tuple[float, float],
    along_xy: tuple[float, float],
    s_range: tuple[float, float],
    height_m: float,
    normal_xy: tuple[float, float],
    openings: list[tuple[float, float, float]],
) -> list[np.ndarray]:
    """Quads of a vertical wall through ``start_xy`` along the unit vector ``along_xy``, from
    ``s_range[0]`` to ``s_range[1]`` (m along it) and from just under the floor to just over
    ``height_m``, facing ``normal_xy``, minus the ``openings`` ``(s0, s1, top_z)`` (floor to top)."""
    o = np.array([start_xy[0], start_xy[1], 0.0])
    u = np.array([along_xy[0], along_xy[1], 0.0])
    n = (normal_xy[0], normal_xy[1], 0.0)
    z_lo, z_hi = -_E, height_m + _E

    def quad(s0: float, s1: float, z0: float, z1: float) -> np.ndarray:
        a, b = o + u * s0, o + u * s1
        return facing_quad([a + [0, 0, z0], b + [0, 0, z0], b + [0, 0, z1], a + [0, 0, z1]], n)

    quads = []
    cur = s_range[0]
    for s0, s1, top in sorted(openings):
        if s0 > cur:
            quads.append(quad(cur, s0, z_lo, z_hi))
        quads.append(quad(s0, s1, top, z_hi))
        cur = s1
    if s_range[1] > cur:
        quads.append(quad(cur, s_range[1], z_lo, z_hi))
    return quads


class DoorwayRoomLayout(RoomLayout):
    """A room of the building in its own frame ``[0, W] x [0, D]``: wall 0 (y = 0, towards the
    corridor) has a doorway centred at ``x = door_s_m`` with its reveal through the wall's
    thickness, the floor runs through the doorway, the door stands open beside it, and the floor
    in front of it is kept free."""

    def __init__(self, room_size_m: tuple[float, float, float], *, door_s_m: float, hinge_left: bool) -> None:
        super().__init__(room_size_m)
        self.door_s_m = door_s_m
        self.hinge_left = hinge_left

    @property
    def doorway_m(self) -> tuple[float, float]:
        return (self.door_s_m - DOORWAY_WIDTH_M / 2, self.door_s_m + DOORWAY_WIDTH_M / 2)

    def build_room(self) -> None:
        W, _, H = self.room_size_m
        a, b = self.doorway_m
        t, dh = WALL_THICKNESS_M, DOORWAY_HEIGHT_M
        wall0 = wall_with_openings((0.0, 0.0), (1.0, 0.0), (-_E, W + _E), H, (0.0, 1.0), [(a, b, dh)])
        # the reveal: both jambs and the lintel through the wall, from the corridor's face (the
        # doorway's portal, where the room's cell ends) to a little past the room's
        y0, y1 = -t, _E
        wall0 += [
            facing_quad([[a, y0, -_E], [a, y1, -_E], [a, y1, dh], [a, y0, dh]], (1, 0, 0)),
            facing_quad([[b, y0, -_E], [b, y1, -_E], [b, y1, dh], [b, y0, dh]], (-1, 0, 0)),
            facing_quad([[a, y0, dh], [b, y0, dh], [b, y1, dh], [a, y1, dh]], (0, 0, -1)),
        ]
        self._build_room([wall0, *self.wall_quads()[1:]])
        floor = next(o for o in self.objects if o.category == "floor")
        # the threshold: the room's floor through the doorway, up to the corridor's (which ends there)
        threshold = facing_quad([[a, -t, 0.0], [b, -t, 0.0], [b, 0.0, 0.0], [a, 0.0, 0.0]], (0, 0, 1))
        floor.parts.append(Part(*_quad(threshold), _PALETTE["floor"], "planks"))

    def add_door(self, rng: np.random.Generator) -> WorldObject:
        """The door, open at 90 degrees beside the doorway (hinge side drawn by the caller), and
        the wall and floor around the doorway reserved so no furniture blocks it."""
        a, b = self.doorway_m
        leaf_w = DOORWAY_WIDTH_M - 0.1
        builder = _build_door(rng, leaf_w, 2.05)
        # yaw pi/2: the leaf's width runs along +y, its 8 cm (leaf + handle) along -x from x
        x = a - 0.02 if self.hinge_left else b + 0.10
        y = leaf_w / 2 + 0.03
        parts = builder.place(x, y, math.pi / 2)
        footprint = (x - 0.10, 0.0, x + 0.01, leaf_w + 0.05)
        self._wall_rects[0].append((a - 0.2, 0.0, b + 0.2, DOORWAY_HEIGHT_M + 0.15))
        self._floor_rects.append(footprint)
        self._floor_rects.append((a - 0.45, 0.0, b + 0.45, DOOR_ENTRY_DEPTH_M))
        return self._new_object("door", parts, footprint=footprint, height_m=2.05)


def _moved(obj: WorldObject, instance_id: int, R2: np.ndarray, t2: np.ndarray) -> WorldObject:
    """``obj`` with a new id, rotated by the 2x2 ``R2`` about z and moved by ``t2``."""
    R = np.eye(3)
    R[:2, :2] = R2
    t = np.array([t2[0], t2[1], 0.0])
    parts = [Part(p.vertices @ R.T + t, p.triangles, p.rgb, p.texture) for p in obj.parts]
    footprint = None
    if obj.footprint is not None:
        x0, y0, x1, y1 = obj.footprint
        c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) @ R2.T + t2
        footprint = (float(c[:, 0].min()), float(c[:, 1].min()), float(c[:, 0].max()), float(c[:, 1].max()))
    return WorldObject(instance_id, obj.category, parts, footprint=footprint, height_m=obj.height_m)


def build_floorplan(seed: int, rooms: int) -> Floorplan:
    """The building of ``seed`` with ``rooms`` rooms (>= 1), furnished, ids 1..N."""
    if rooms < 1:
        raise ValueError(f"a building needs at least 1 room, got {rooms}")
    rng = np.random.default_rng([seed, 33])
    H = round(float(rng.uniform(*HEIGHT_RANGE_M)), 2)
    Cw = round(float(rng.uniform(*CORRIDOR_WIDTH_RANGE_M)), 2)
    t = WALL_THICKNESS_M
    n_bays = (rooms + 1) // 2
    widths = [round(float(np.random.default_rng([seed, 33, 1, j]).uniform(*ROOM_WIDTH_RANGE_M)), 2) for j in range(n_bays)]
    bay_x0 = [LOBBY_M + sum(widths[:j]) + j * t for j in range(n_bays)]
    L = bay_x0[-1] + widths[-1] + LOBBY_M

    # ---- rooms, each in its own frame first
    room_layouts: list[tuple[int, DoorwayRoomLayout]] = []
    for k in range(rooms):
        r = np.random.default_rng([seed, 33, 2, k])
        W = widths[k // 2]
        D = round(float(r.uniform(*ROOM_DEPTH_RANGE_M)), 2)
        door_s = round(float(r.uniform(1.2, W - 1.2)), 2)
        layout = DoorwayRoomLayout((W, D, H), door_s_m=door_s, hinge_left=bool(r.random() < 0.5))
        layout.build_room()
        layout.add_door(r)
        layout.furnish(r, door=False)
        room_layouts.append((k, layout))

    def door_x(k: int, layout: DoorwayRoomLayout) -> float:
        x0 = bay_x0[k // 2]
        return x0 + layout.door_s_m if k % 2 == 0 else x0 + layout.room_size_m[0] - layout.door_s_m

    doors = {k: door_x(k, lay) for k, lay in room_layouts}

    # ---- the corridor (ids first)
    objects: list[WorldObject] = []

    def new(category: str, parts: list[Part], **kw) -> WorldObject:
        obj = WorldObject(len(objects) + 1, category, parts, **kw)
        objects.append(obj)
        return obj

    wall_rgb = _PALETTE["wall"]
    cuts = [0.0] + [(bay_x0[j - 1] + widths[j - 1] + bay_x0[j]) / 2 for j in range(1, n_bays)] + [L]
    half = DOORWAY_WIDTH_M / 2
    new("wall", [Part(*_quad(q), wall_rgb, "paint") for q in wall_with_openings((0.0, 0.0), (0.0, 1.0), (-_E, Cw + _E), H, (1.0, 0.0), [])])
    for j in range(n_bays):
        s_lo = -_E if j == 0 else cuts[j]
        s_hi = L + _E if j == n_bays - 1 else cuts[j + 1]
        for k, y, normal in ((2 * j, Cw, -1.0), (2 * j + 1, 0.0, 1.0)):
            openings = [(doors[k] - half, doors[k] + half, DOORWAY_HEIGHT_M)] if k in doors else []
            quads = wall_with_openings((0.0, y), (1.0, 0.0), (s_lo, s_hi), H, (0.0, normal), openings)
            new("wall", [Part(*_quad(q), wall_rgb, "paint") for q in quads])
        for category, z, nz, texture in (("floor", 0.0, 1.0, "planks"), ("ceiling", H, -1.0, "paint")):
            # exactly between the walls (which reach past floor and ceiling): nothing of the corridor
            # lies beyond a doorway's portal
            q = facing_quad([[s_lo, 0.0, z], [s_hi, 0.0, z], [s_hi, Cw, z], [s_lo, Cw, z]], (0, 0, nz))
            new(category, [Part(*_quad(q), _PALETTE[category], texture)])
    new("wall", [Part(*_quad(q), wall_rgb, "paint") for q in wall_with_openings((L, 0.0), (0.0, 1.0), (-_E, Cw + _E), H, (-1.0, 0.0), [])])
    _decorate_corridor(np.random.default_rng([seed, 33, 3]), new, L, Cw, cuts, doors, n_bays)
    corridor_ids = tuple(o.instance_id for o in objects)

    # ---- rooms moved into place, ids after the corridor's
    placed: list[BuildingRoom] = []
    for k, layout in room_layouts:
        W, D, _ = layout.room_size_m
        x0 = bay_x0[k // 2]
        if k % 2 == 0:  # north: the room's frame is only shifted
            R2, t2, rect = np.eye(2), np.array([x0, Cw + t]), (x0, Cw + t, x0 + W, Cw + t + D)
        else:  # south: turned half round, wall 0 facing the corridor from below
            R2, t2, rect = -np.eye(2), np.array([x0 + W, -t]), (x0, -t - D, x0 + W, -t)
        ids = []
        for obj in layout.objects:
            moved = _moved(obj, len(objects) + 1, R2, t2)
            objects.append(moved)
            ids.append(moved.instance_id)
        placed.append(BuildingRoom(k, "north" if k % 2 == 0 else "south", tuple(float(v) for v in rect), float(doors[k]),
                                   tuple(ids), Cw if k % 2 == 0 else 0.0))
    return Floorplan(H, Cw, L, tuple(placed), corridor_ids, objects)


def _decorate_corridor(rng, new, L: float, Cw: float, cuts: list[float], doors: dict[int, float], n_bays: int) -> None:  # noqa: ANN001
    """Pictures on the corridor's walls (away from doorways, above the robot's reach) and plants
    in the lobby corners (outside the walking line at y = Cw / 2)."""
    for j in range(n_bays):
        for k, y, yaw in ((2 * j, Cw, math.pi), (2 * j + 1, 0.0, 0.0)):
            if rng.random() > 0.8:
                continue
            w = float(rng.uniform(0.5, 0.9))
            builder = _build_picture(rng, w, w * float(rng.uniform(0.6, 1.0)))
            for _ in range(10):
                s = float(rng.uniform(cuts[j] + 0.4 + w / 2, cuts[j + 1] - 0.4 - w / 2))
                if k in doors and abs(s - doors[k]) < DOORWAY_WIDTH_M / 2 + 0.3 + w / 2:
                    continue
                new("picture", builder.place(s, y, yaw, 1.35))
                break
    for x, y in ((0.35, 0.35), (0.35, Cw - 0.35), (L - 0.35, 0.35), (L - 0.35, Cw - 0.35)):
        if rng.random() < 0.6:
            builder = _build_plant(rng)
            lo, hi = builder.local_bounds()
            footprint = (x + lo[0], y + lo[1], x + hi[0], y + hi[1])
            new("plant", builder.place(x, y, 0.0), footprint=footprint, height_m=float(hi[2]))
