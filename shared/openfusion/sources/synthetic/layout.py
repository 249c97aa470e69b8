"""Room layout of the synthetic world: the closed room and where each piece of furniture goes.

``RoomLayout`` builds the four walls, floor and ceiling as quads facing into the room, then
furnishes it: objects with their back against a wall (door, windows, bed + pillows, sofa,
bookshelves, cabinets, desk + monitor + office chair, pictures, trash can), a dining set in the
middle and lamp/plants in corners. It keeps the occupied floor and wall rectangles so nothing
overlaps. Every draw comes from the one ``rng`` passed to ``furnish``, in a fixed order, so the
same seed gives the same room. Instance ids are assigned in creation order starting at 1.
"""

from __future__ import annotations

import math

import numpy as np

from openfusion.sources.synthetic.furniture import (
    _PALETTE,
    Part,
    WorldObject,
    _build_bed,
    _build_bookshelf,
    _build_cabinet,
    _build_chair,
    _build_desk,
    _build_door,
    _build_lamp,
    _build_monitor,
    _build_office_chair,
    _build_picture,
    _build_pillow,
    _build_plant,
    _build_sofa,
    _build_table,
    _build_trash_can,
    _build_window,
    _Builder,
    _jitter,
    _quad,
)


def facing_quad(corners, normal) -> np.ndarray:
    """``corners`` (4 x 3, in order around the quad) reversed when needed so that the quad's
    normal (p1-p0) x (p3-p0) points along ``normal``."""
    q = np.array(corners, dtype=np.float64)
    n = np.cross(q[1] - q[0], q[3] - q[0])
    if np.dot(n, np.asarray(normal, dtype=np.float64)) < 0:
        q = q[::-1]
    return q


def furnished_room(room_size_m: tuple[float, float, float], rng: np.random.Generator) -> list[WorldObject]:
    """The room's objects (walls, floor, ceiling, then the furniture), ids 1, 2, ... in order."""
    layout = RoomLayout(room_size_m)
    layout.build_room()
    layout.furnish(rng)
    return layout.objects


class RoomLayout:
    """Objects of one room of size ``room_size_m`` = (W, D, H), placed without overlaps."""

    def __init__(self, room_size_m: tuple[float, float, float]) -> None:
        self.room_size_m = room_size_m
        self.objects: list[WorldObject] = []
        self._floor_rects: list[tuple[float, float, float, float]] = []
        self._wall_rects: dict[int, list[tuple[float, float, float, float]]] = {k: [] for k in range(4)}

    def _new_object(self, category: str, parts: list[Part], **kw) -> WorldObject:
        obj = WorldObject(len(self.objects) + 1, category, parts, **kw)
        self.objects.append(obj)
        return obj

    #: Corner overlap of the room's quads (m), so rays never slip through a crack.
    CORNER_OVERLAP_M = 0.01
    #: Unit normal of each wall, pointing into the room: 0 (y=0), 1 (x=W), 2 (y=D), 3 (x=0).
    WALL_INWARD = ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (1.0, 0.0, 0.0))

    def wall_quads(self) -> list[np.ndarray]:
        """The four walls as (4, 3) quads, each ordered so its normal points into the room."""
        W, D, H = self.room_size_m
        e = self.CORNER_OVERLAP_M
        quads = [
            [[-e, 0, -e], [W + e, 0, -e], [W + e, 0, H + e], [-e, 0, H + e]],
            [[W, -e, -e], [W, D + e, -e], [W, D + e, H + e], [W, -e, H + e]],
            [[W + e, D, -e], [-e, D, -e], [-e, D, H + e], [W + e, D, H + e]],
            [[0, D + e, -e], [0, -e, -e], [0, -e, H + e], [0, D + e, H + e]],
        ]
        return [facing_quad(q, self.WALL_INWARD[k]) for k, q in enumerate(quads)]

    def build_room(self) -> None:
        self._build_room(self.wall_quads())

    def _build_room(self, wall_parts: list[np.ndarray | list[np.ndarray]]) -> None:
        """Walls 0..3 (one object each, made of the quads given), then the floor and the ceiling."""
        W, D, H = self.room_size_m
        e = self.CORNER_OVERLAP_M
        wall_rgb = _PALETTE["wall"]
        for quads in wall_parts:
            quads = [quads] if isinstance(quads, np.ndarray) else quads
            self._new_object("wall", [Part(*_quad(q), wall_rgb, "paint") for q in quads])
        floor = np.array([[-e, -e, 0], [W + e, -e, 0], [W + e, D + e, 0], [-e, D + e, 0]], dtype=np.float64)
        self._new_object("floor", [Part(*_quad(floor), _PALETTE["floor"], "planks")])
        ceiling = np.array([[-e, -e, H], [-e, D + e, H], [W + e, D + e, H], [W + e, -e, H]], dtype=np.float64)
        self._new_object("ceiling", [Part(*_quad(ceiling), _PALETTE["ceiling"], "paint")])

    def _wall_frame(self, wall: int) -> tuple[np.ndarray, np.ndarray, float, float]:
        """(origin, along-wall unit vector, yaw so local +y faces into the room, wall length)."""
        W, D, _ = self.room_size_m
        if wall == 0:
            return np.array([0.0, 0.0]), np.array([1.0, 0.0]), 0.0, W
        if wall == 1:
            return np.array([W, 0.0]), np.array([0.0, 1.0]), math.pi / 2, D
        if wall == 2:
            return np.array([W, D]), np.array([-1.0, 0.0]), math.pi, W
        return np.array([0.0, D]), np.array([0.0, -1.0]), -math.pi / 2, D

    @staticmethod
    def _overlap(a, b, margin: float = 0.0) -> bool:
        return a[0] < b[2] + margin and b[0] < a[2] + margin and a[1] < b[3] + margin and b[1] < a[3] + margin

    def _floor_free(self, rect, margin: float = 0.05) -> bool:
        W, D, _ = self.room_size_m
        if rect[0] < -1e-6 or rect[1] < -1e-6 or rect[2] > W + 1e-6 or rect[3] > D + 1e-6:
            return False
        return not any(self._overlap(rect, r, margin) for r in self._floor_rects)

    def _place_on_wall(
        self,
        rng: np.random.Generator,
        builder: _Builder,
        category: str,
        *,
        z0: float = 0.0,
        on_floor: bool = True,
        keepout_depth_m: float = 0.0,
        attempts: int = 40,
        walls: list[int] | None = None,
    ) -> WorldObject | None:
        """Put an object with its back against a wall; returns None when it does not fit."""
        lo, hi = builder.local_bounds()
        width = hi[0] - lo[0]
        depth = hi[1] - lo[1]
        height = hi[2] - lo[2]
        for _ in range(attempts):
            wall = int(rng.choice(walls)) if walls else int(rng.integers(0, 4))
            origin, along, yaw, length = self._wall_frame(wall)
            if length < width + 0.3:
                continue
            s = float(rng.uniform(0.15 + width / 2, length - 0.15 - width / 2))
            wall_rect = (s - width / 2, z0, s + width / 2, z0 + height)
            if any(self._overlap(wall_rect, r, 0.05) for r in self._wall_rects[wall]):
                continue
            inward = np.array([-along[1], along[0]])
            centre = origin + along * s + inward * (-lo[1])
            a = origin + along * (s - width / 2)
            b = origin + along * (s + width / 2)
            reach = inward * (depth + keepout_depth_m)
            pts = np.array([a, b, a + reach, b + reach])
            rect = (pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max())
            if on_floor and not self._floor_free(rect):
                continue
            self._wall_rects[wall].append(wall_rect)
            if on_floor:
                self._floor_rects.append(rect)
            parts = builder.place(float(centre[0]), float(centre[1]), yaw, z0)
            return self._new_object(category, parts, footprint=rect if on_floor else None, height_m=z0 + height)
        return None

    def _place_free(
        self, rng, builder: _Builder, category: str, x: float, y: float, yaw: float, *, check_floor: bool = True
    ) -> WorldObject | None:
        lo, hi = builder.local_bounds()
        corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        c, s = math.cos(yaw), math.sin(yaw)
        pts = corners @ np.array([[c, -s], [s, c]]).T + np.array([x, y])
        rect = (pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max())
        if check_floor:
            if not self._floor_free(rect):
                return None
            self._floor_rects.append(rect)
        return self._new_object(category, builder.place(x, y, yaw), footprint=rect, height_m=float(hi[2]))

    def furnish(self, rng: np.random.Generator, *, door: bool = True) -> None:
        """Furniture drawn from ``rng``; ``door=False`` leaves out the door on a wall (a room whose
        door is a real doorway, placed by the caller)."""
        W, D, H = self.room_size_m
        if door:
            self._place_on_wall(rng, _build_door(rng, 0.9, 2.05), "door", keepout_depth_m=0.9)
        for _ in range(int(rng.integers(1, 3))):
            w = float(rng.uniform(1.0, 1.6))
            self._place_on_wall(rng, _build_window(rng, w, 1.2), "window", z0=0.95, on_floor=False)
        if rng.random() < 0.7:
            bed_w = float(rng.uniform(1.4, 1.8))
            bed = self._place_on_wall(rng, _build_bed(rng, bed_w, 2.0), "bed")
            if bed is not None:
                self._add_pillows(rng, bed, bed_w)
        if rng.random() < 0.8:
            self._place_on_wall(rng, _build_sofa(rng, float(rng.uniform(1.7, 2.2)), 0.9), "sofa")
        for _ in range(int(rng.integers(1, 3))):
            self._place_on_wall(
                rng, _build_bookshelf(rng, float(rng.uniform(0.8, 1.2)), 0.35, float(rng.uniform(1.7, 2.0))), "bookshelf"
            )
        for _ in range(int(rng.integers(1, 3))):
            self._place_on_wall(
                rng,
                _build_cabinet(rng, float(rng.uniform(0.6, 1.2)), 0.45, float(rng.uniform(0.8, 1.1))),
                "cabinet",
            )
        desk_w = float(rng.uniform(1.2, 1.6))
        desk = self._place_on_wall(rng, _build_desk(rng, desk_w, 0.7, 0.75), "desk", keepout_depth_m=0.9)
        if desk is not None:
            self._add_desk_set(rng, desk)
        for _ in range(int(rng.integers(1, 4))):
            w = float(rng.uniform(0.4, 0.9))
            self._place_on_wall(rng, _build_picture(rng, w, w * float(rng.uniform(0.6, 1.2))), "picture", z0=1.35, on_floor=False)
        self._add_dining_set(rng)
        for builder, category in ((_build_lamp(rng), "lamp"), (_build_plant(rng), "plant"), (_build_plant(rng), "plant")):
            self._place_in_corner(rng, builder, category)
        self._place_on_wall(rng, _build_trash_can(rng), "trash can")

    def _add_pillows(self, rng, bed: WorldObject, bed_w: float) -> None:
        # the bed's headboard is at its local -y end; recover the placement from its parts
        head = bed.parts[2].vertices.mean(0)
        centre = bed.parts[0].vertices.mean(0)
        direction = centre[:2] - head[:2]
        direction /= np.linalg.norm(direction)
        yaw = math.atan2(direction[1], direction[0]) - math.pi / 2
        side = np.array([direction[1], -direction[0]])
        n = 2 if bed_w > 1.3 else 1
        for k in range(n):
            offset = (k - (n - 1) / 2) * (bed_w / 2)
            p = head[:2] + direction * 0.3 + side * offset
            self._new_object("pillow", _build_pillow(rng).place(float(p[0]), float(p[1]), yaw, 0.52))

    def _add_desk_set(self, rng, desk: WorldObject) -> None:
        top = desk.parts[0].vertices
        centre = top.mean(0)
        back = desk.parts[3].vertices.mean(0)
        direction = centre[:2] - back[:2]
        direction /= np.linalg.norm(direction)
        yaw = math.atan2(direction[1], direction[0]) - math.pi / 2
        p = back[:2] + direction * 0.18
        self._new_object("monitor", _build_monitor(rng).place(float(p[0]), float(p[1]), yaw, float(top[:, 2].max())))
        q = centre[:2] + direction * float(rng.uniform(0.65, 0.8))
        chair_yaw = yaw + math.pi + float(rng.uniform(-0.4, 0.4))
        # the desk reserved the floor in front of it (keep-out), so no floor check here
        self._place_free(rng, _build_office_chair(rng), "office chair", float(q[0]), float(q[1]), chair_yaw, check_floor=False)

    def _add_dining_set(self, rng) -> None:
        W, D, _ = self.room_size_m
        for _ in range(30):
            tw, td = float(rng.uniform(1.0, 1.6)), float(rng.uniform(0.7, 0.9))
            x = float(rng.uniform(1.4, W - 1.4))
            y = float(rng.uniform(1.4, D - 1.4))
            yaw = float(rng.choice([0.0, math.pi / 2]))
            ex, ey = (tw / 2 + 0.75, td / 2 + 0.75) if yaw == 0.0 else (td / 2 + 0.75, tw / 2 + 0.75)
            margin_rect = (x - ex, y - ey, x + ex, y + ey)
            if not self._floor_free(margin_rect, 0.0):
                continue
            self._place_free(rng, _build_table(rng, tw, td, 0.75), "table", x, y, yaw, check_floor=False)
            self._floor_rects.append(margin_rect)
            chair_rgb = _jitter(rng, _PALETTE["chair"], 0.1)
            c, s = math.cos(yaw), math.sin(yaw)
            seats = [(0.0, -td / 2 - 0.3, 0.0), (0.0, td / 2 + 0.3, math.pi)]
            if tw > 1.2:
                seats = [(-tw / 4, -td / 2 - 0.3, 0.0), (tw / 4, -td / 2 - 0.3, 0.0), (0.0, td / 2 + 0.3, math.pi)]
            for lx, ly, lyaw in seats:
                if rng.random() < 0.15:
                    continue
                gx, gy = x + c * lx - s * ly, y + s * lx + c * ly
                jitter_yaw = float(rng.uniform(-0.25, 0.25))
                self._place_free(
                    rng, _build_chair(rng, chair_rgb), "chair", gx, gy, yaw + lyaw + jitter_yaw, check_floor=False
                )
            return

    def _place_in_corner(self, rng, builder: _Builder, category: str) -> None:
        W, D, _ = self.room_size_m
        lo, hi = builder.local_bounds()
        r = max(hi[0] - lo[0], hi[1] - lo[1]) / 2 + 0.05
        corners = [(r, r), (W - r, r), (W - r, D - r), (r, D - r)]
        order = rng.permutation(4)
        for k in order:
            x, y = corners[int(k)]
            x += float(rng.uniform(0, 0.3)) * (1 if x < W / 2 else -1)
            y += float(rng.uniform(0, 0.3)) * (1 if y < D / 2 else -1)
            if self._place_free(rng, builder, category, x, y, float(rng.uniform(0, 2 * math.pi))) is not None:
                return
        for _ in range(20):  # no free corner: anywhere along a wall
            wall_obj = self._place_on_wall(rng, builder, category, attempts=1)
            if wall_obj is not None:
                return
