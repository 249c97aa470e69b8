"""The options of a ``synthetic[:world,]key=value,...`` source spec, parsed without building the world.

Two worlds: the furnished room (``synthetic:seed=1,frames=120``, the default) and the building
(``synthetic:building,rooms=8,route=0-3``: rooms along a corridor, a walk through a route of them).
:func:`split_world` takes the world's name off the spec's options; :func:`synthetic_options` turns
the options' strings into keyword arguments of :class:`~openfusion.sources.synthetic.SyntheticSource`
or :class:`~openfusion.sources.synthetic.BuildingSource` (plus ``seed``, and ``rooms`` for the
building) and checks them against each other (a route's rooms exist, ``revisit`` is not longer than
the route). It imports nothing heavy (the synthetic package needs Open3D), so
:func:`~openfusion.sources.registry.check_source_spec` can refuse an unknown or malformed option
before a command starts anything, with the same message the source gives when it opens.

Routes (``route=``): rooms joined by ``+``, each a room index or an inclusive range ``A-B``
(``3-0`` walks 3, 2, 1, 0): ``route=0-3``, ``route=4-7``, ``route=0-3+6``. A room appears once;
``revisit=N`` walks the route's first N rooms again at the end (default 2).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

#: The synthetic worlds a spec may name (the first option, without ``=``); ``room`` is the default.
WORLDS: tuple[str, ...] = ("room", "building")
#: Rooms of ``synthetic:building`` by default: at least 300 m^2 of floor for every seed.
DEFAULT_ROOMS = 10
#: Rooms walked again at the end of a building's walk by default.
DEFAULT_REVISIT = 2
#: More rooms than this is a typo, not a building (each room costs about 4,500 triangles).
MAX_ROOMS = 200


def parse_route(text: str) -> tuple[int, ...]:
    """``0-3+6`` -> (0, 1, 2, 3, 6); ValueError naming the bad part. Rooms are not checked
    against a building here (:func:`synthetic_options` does, knowing ``rooms``)."""
    out: list[int] = []
    for part in text.split("+"):
        lo, sep, hi = part.strip().partition("-")
        try:
            a = int(lo)
            b = int(hi) if sep else a
        except ValueError:
            raise ValueError(f"route part {part!r} must be a room number or a range A-B (e.g. route=0-3+6)") from None
        if a < 0 or b < 0:
            raise ValueError(f"route part {part!r}: room numbers start at 0")
        out.extend(range(a, b + 1) if a <= b else range(a, b - 1, -1))
    twice = sorted({k for k in out if out.count(k) > 1})
    if twice:
        raise ValueError(f"route {text!r} has room(s) {twice} twice (revisit=N walks the route's first rooms again)")
    return tuple(out)


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise ValueError(f"must be >= 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise ValueError(f"must be >= 0, got {value}")
    return value


_KINDS: dict[Callable[[str], Any], str] = {
    parse_route: "route", _positive_int: "whole number >= 1", _non_negative_int: "whole number >= 0"
}

#: spec key -> (keyword of ``SyntheticSource``, converter; None for a 0/1 flag).
SPEC_KEYS: dict[str, tuple[str, Callable[[str], Any] | None]] = {
    "seed": ("seed", int),
    "frames": ("num_frames", int),
    "width": ("width_px", int),
    "height": ("height_px", int),
    "fps": ("fps", float),
    "lap": ("frames_per_lap", int),
    "noise": ("depth_noise", None),
    "stop": ("stop_frames", _non_negative_int),
}

#: spec key -> (keyword of ``BuildingSource`` or ``SyntheticBuilding``, converter) for ``synthetic:building``.
BUILDING_SPEC_KEYS: dict[str, tuple[str, Callable[[str], Any] | None]] = {
    "seed": ("seed", int),
    "rooms": ("rooms", _positive_int),
    "route": ("route", parse_route),
    "revisit": ("revisit", _non_negative_int),
    "frames": ("num_frames", _positive_int),
    "width": ("width_px", int),
    "height": ("height_px", int),
    "fps": ("fps", float),
    "noise": ("depth_noise", None),
}


def split_world(rest: str) -> tuple[str, str]:
    """(world, the options after it) of the text after ``synthetic:``: ``building,rooms=4`` ->
    ("building", "rooms=4"); options alone are the room's. ValueError for a first option that is
    neither ``key=value`` nor a world's name."""
    first, _sep, tail = rest.partition(",")
    word = first.strip()
    if not word or "=" in word:
        return "room", rest
    if word.lower() in WORLDS:
        return word.lower(), tail
    raise ValueError(
        f"synthetic option {word!r} must look like key=value or name a world ({', '.join(WORLDS)}), "
        "e.g. synthetic:seed=1,frames=100 or synthetic:building,rooms=8"
    )


def synthetic_options(spec_options: Mapping[str, str], *, world: str = "room") -> dict[str, Any]:
    """Keyword arguments (``seed``, ``num_frames``, ...) from spec options (strings) of ``world``;
    ValueError naming an unknown key, a value of the wrong type or options that disagree."""
    keys = BUILDING_SPEC_KEYS if world == "building" else SPEC_KEYS
    out: dict[str, Any] = {}
    for key, text in spec_options.items():
        if key not in keys:
            hint = " (a building's walk has no laps: frames=N spreads N frames over it)" if key == "lap" else ""
            raise ValueError(f"unknown synthetic{' building' if world == 'building' else ''} option {key!r}{hint}; "
                             f"known: {', '.join(sorted(keys))}")
        name, conv = keys[key]
        if conv is None:
            if text.lower() not in ("0", "1", "true", "false"):
                raise ValueError(f"synthetic option {key} must be 0/1/true/false, got {text!r}")
            out[name] = text.lower() in ("1", "true")
            continue
        try:
            out[name] = conv(text)
        except ValueError as exc:
            if str(exc).startswith(("invalid literal", "could not convert")):  # int() / float() refusing the text
                kind = _KINDS.get(conv, getattr(conv, "__name__", "value"))
                raise ValueError(f"synthetic option {key}={text!r} is not a valid {kind}") from None
            raise ValueError(f"synthetic option {key}={text!r}: {exc}") from None
    if world == "building":
        _check_building(out)
    return out


def default_revisit(route_rooms: int) -> int:
    """Rooms revisited when ``revisit`` is not given: :data:`DEFAULT_REVISIT`, or the whole route when shorter."""
    return min(DEFAULT_REVISIT, route_rooms)


def _check_building(options: dict[str, Any]) -> None:
    rooms = options.get("rooms", DEFAULT_ROOMS)
    if rooms > MAX_ROOMS:
        raise ValueError(f"synthetic option rooms={rooms} is more than {MAX_ROOMS}")
    route = options.get("route", tuple(range(rooms)))
    missing = [k for k in route if k >= rooms]
    if missing:
        raise ValueError(f"synthetic option route: room(s) {missing} do not exist: the building has "
                         f"rooms 0-{rooms - 1} (set rooms=N)")
    revisit = options.get("revisit", default_revisit(len(route)))
    if revisit > len(route):
        raise ValueError(f"synthetic option revisit={revisit} is more than the route's {len(route)} room(s)")
