"""What ``openfusion run`` plays: the built-in scene's spec for ``--frames`` (the room walks its lap
again for longer runs, the building spreads the frames over its walk), how many frames a source
is asked for, the robots of several ``--source`` options (``name=ROBOT``), and the note a run
prints when its source had fewer frames than asked for (the :mod:`openfusion.app.run` docstring,
"Frames")."""

from __future__ import annotations

from collections.abc import Sequence

from openfusion.app.summary import RunSummary
from openfusion.errors import UsageError
from openfusion.sources.registry import parse_key_values
from openfusion.sources.synthetic_spec import split_world
from openfusion.wire.schemas.base import check_robot_name

#: Frames of one lap of the built-in room in ``openfusion run`` (the default ``--frames``, so the
#: default run goes once round the room); longer runs walk the lap again.
BUILTIN_LAP_FRAMES = 120


def builtin_scene_spec(spec: str, frames: int | None) -> str:
    """The source spec that plays ``frames`` frames (None: the default) of the built-in world: a
    room spec gets ``frames=N`` (default :data:`BUILTIN_LAP_FRAMES`) and ``lap=BUILTIN_LAP_FRAMES``
    unless it sets them; a building spec gets ``frames=N`` only when N is given (its walk has its
    own frame count); any other spec is unchanged."""
    scheme, _sep, rest = spec.strip().partition(":")
    if scheme.lower() != "synthetic":
        return spec
    world, rest = split_world(rest)
    options = parse_key_values(rest, scheme="synthetic")
    if world == "building":
        if frames is not None:
            options.setdefault("frames", str(frames))
        return "synthetic:" + ",".join(["building", *(f"{k}={v}" for k, v in options.items())])
    options.setdefault("frames", str(frames if frames is not None else BUILTIN_LAP_FRAMES))
    options.setdefault("lap", str(BUILTIN_LAP_FRAMES))
    return "synthetic:" + ",".join(f"{k}={v}" for k, v in options.items())


def frames_to_play(spec: str, frames: int | None) -> int:
    """``--frames``, or without it: the walk's frame count for a building spec (opened here: the
    plan and the walk, no rendering), else :data:`BUILTIN_LAP_FRAMES`."""
    if frames is not None:
        return frames
    scheme, _sep, rest = spec.strip().partition(":")
    if scheme.lower() == "synthetic" and split_world(rest)[0] == "building":
        from openfusion.sources.registry import open_source

        return len(open_source(spec))
    return BUILTIN_LAP_FRAMES


def shortfall_note(summary: RunSummary) -> str | None:
    """``played 300 of 2000 frames: the source has 300`` when a finished run played fewer frames
    than asked for, else None."""
    wanted, played = summary.frames_requested, summary.frames_played
    if summary.interrupted or wanted is None or played is None or played >= wanted:
        return None
    note = f"played {played} of {wanted} frames: the source has {played}"
    skipped = sum(summary.frames_skipped.values())
    if skipped:
        reasons = ", ".join(f"{reason} {n}" for reason, n in sorted(summary.frames_skipped.items()))
        note += f" usable frames ({skipped} skipped: {reasons})"
    return note


def split_robot_name(spec: str) -> tuple[str, str | None]:
    """A ``--source`` spec and the robot name its ``name=ROBOT`` option gives (the option removed;
    None without one): ``synthetic:building,route=0-3,name=alpha`` -> (``synthetic:building,route=0-3``,
    ``alpha``)."""
    scheme, colon, rest = spec.partition(":")
    items = rest.split(",") if colon else spec.split(",")[1:]
    head = scheme if colon else spec.split(",")[0]
    names = [item.strip()[len("name="):] for item in items if item.strip().startswith("name=")]
    if len(names) > 1:
        raise UsageError(f"--source {spec!r}: name= is given {len(names)} times")
    kept = ",".join(item for item in items if not item.strip().startswith("name="))
    return (f"{head}:{kept}" if kept else head), (names[0] if names else None)


def robot_sources(specs: Sequence[str], *, default_robot: str) -> dict[str, str]:
    """Robot name -> source spec of the ``--source`` options: ``name=`` names a robot, the others are
    ``robot0``, ``robot1``, ... by position (the first one, unnamed, is ``default_robot``)."""
    robots: dict[str, str] = {}
    for i, spec in enumerate(specs):
        plain, name = split_robot_name(spec)
        name = name if name is not None else (default_robot if i == 0 else f"robot{i}")
        try:
            check_robot_name(name)
        except ValueError as exc:
            raise UsageError(f"--source {spec!r}: {exc}") from None
        if name in robots:
            raise UsageError(f"--source {spec!r}: robot {name!r} has a source already (one bridge per robot; "
                             "name= names them)")
        robots[name] = plain
    return robots
