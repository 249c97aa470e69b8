"""``open_source(spec, **options)``: one entry point from a spec string to a ``FrameSource``.

Specs::

    synthetic[:seed=N,frames=N,width=W,height=H,fps=F,noise=0|1,lap=N]   (the built-in room)
    synthetic:building[,rooms=N,route=A-B+C,revisit=N,seed=N,frames=N,width=W,height=H,fps=F,noise=0|1]
                   (rooms along a corridor; see openfusion.sources.synthetic_spec)
    scannet:PATH   replica:PATH   tum:PATH   redwood:PATH   folder:PATH   replay:FILE
    live:kinect-t265   (Azure Kinect + T265; optional extra 'live')
    rosbag:PATH[,color=/topic,depth=/topic,...]   (rosbag2 folder, .mcap or .db3; see sources.rosbag)
    ros2[:layout=bridge|rmw_zenoh,connect=EP,namespace=NS,domain_id=N,color=/topic,...]   (live ROS 2 over Zenoh)

``options`` are keyword arguments of the reader class (e.g. ``stride=2``, ``max_frames=100``,
``intrinsics=...``); readers are imported only when their scheme is used.
``check_source_spec(spec)`` checks a spec's form (scheme, path, options) without opening it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from openfusion.errors import OpenFusionError
from openfusion.sources.base import FrameSource, SourceError

logger = logging.getLogger(__name__)


def _synthetic(rest: str, options: dict[str, Any]) -> FrameSource:
    from openfusion.sources.synthetic import open_synthetic
    from openfusion.sources.synthetic_spec import split_world

    world, rest = split_world(rest)
    return open_synthetic(parse_key_values(rest, scheme="synthetic"), world=world, **options)


def _existing_path(module: str, rest: str) -> Path:
    if not rest:
        raise SourceError(f"source spec needs a path after the scheme, e.g. {module}:/data/scene")
    path = Path(rest).expanduser()
    if not path.exists():
        raise SourceError(f"{module} source: {path} does not exist (check the path after '{module}:')")
    return path


def _path_reader(module: str, cls: str) -> Callable[[str, dict[str, Any]], FrameSource]:
    def build(rest: str, options: dict[str, Any]) -> FrameSource:
        import importlib

        path = _existing_path(module, rest)
        reader = getattr(importlib.import_module(f"openfusion.sources.{module}"), cls)
        return reader(path, **options)

    return build


def _recording(rest: str) -> Path:
    if not rest:
        raise SourceError("source spec needs a file after the scheme, e.g. replay:/data/run.ofrec")
    path = Path(rest).expanduser()
    if not path.is_file():
        raise SourceError(f"replay source: recording {path} does not exist (record one with FrameRecorder)")
    return path


def _replay(rest: str, options: dict[str, Any]) -> FrameSource:
    path = _recording(rest)
    from openfusion.sources.record import ReplaySource

    return ReplaySource(path, **options)


def _rosbag(rest: str, options: dict[str, Any]) -> FrameSource:
    from openfusion.sources.rosbag import RosbagSource, parse_rosbag_spec

    path, spec_options = parse_rosbag_spec(rest)
    return RosbagSource(path, **{**spec_options, **options})


def _ros2_options(rest: str) -> dict[str, str]:
    from openfusion.sources.ros2 import SPEC_KEYS

    options = parse_key_values(rest, scheme="ros2")
    unknown = sorted(set(options) - set(SPEC_KEYS))
    if unknown:
        raise SourceError(f"unknown ros2 option(s) {', '.join(unknown)}; known: {', '.join(SPEC_KEYS)}")
    return options


def _ros2(rest: str, options: dict[str, Any]) -> FrameSource:
    from openfusion.sources.ros2 import Ros2Source, ros2_config_from_spec

    config, kwargs = ros2_config_from_spec(_ros2_options(rest))
    return Ros2Source(config, **{**kwargs, **options})


def _rosbag_check(rest: str) -> None:
    from openfusion.sources.rosbag import parse_rosbag_spec  # light: rosbags is imported on open

    parse_rosbag_spec(rest)


def _live_devices(rest: str) -> None:
    if rest not in ("", "kinect-t265"):
        raise SourceError(f"unknown live device set {rest!r}; supported: live:kinect-t265")


def _live(rest: str, options: dict[str, Any]) -> FrameSource:
    _live_devices(rest)
    from openfusion.sources.live import KinectT265Source

    return KinectT265Source(**options)


_SCHEMES: dict[str, Callable[[str, dict[str, Any]], FrameSource]] = {
    "synthetic": _synthetic,
    "scannet": _path_reader("scannet", "ScanNetSource"),
    "replica": _path_reader("replica", "ReplicaSource"),
    "tum": _path_reader("tum", "TumSource"),
    "redwood": _path_reader("redwood", "RedwoodSource"),
    "folder": _path_reader("folder", "FolderSource"),
    "replay": _replay,
    "live": _live,
    "rosbag": _rosbag,
    "ros2": _ros2,
}

SCHEMES: tuple[str, ...] = tuple(_SCHEMES)

def _synthetic_options(rest: str) -> dict[str, Any]:
    from openfusion.sources.synthetic_spec import split_world, synthetic_options  # light: not the world

    try:
        world, options = split_world(rest)
        return synthetic_options(parse_key_values(options, scheme="synthetic"), world=world)
    except SourceError:
        raise
    except ValueError as exc:
        raise SourceError(f"cannot open source 'synthetic:{rest}': {exc}") from None


#: What :func:`check_source_spec` checks per scheme (the cheap part of opening: no reader imported).
_CHECKS: dict[str, Callable[[str], object]] = {
    "synthetic": _synthetic_options,
    **{scheme: (lambda rest, scheme=scheme: _existing_path(scheme, rest))
       for scheme in ("scannet", "replica", "tum", "redwood", "folder")},
    "replay": _recording,
    "live": _live_devices,
    "rosbag": _rosbag_check,
    "ros2": _ros2_options,
}


def parse_key_values(text: str, *, scheme: str) -> dict[str, str]:
    """``a=1,b=2`` -> {"a": "1", "b": "2"}; ValueError naming the bad item."""
    out: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise SourceError(f"{scheme} option {item!r} must look like key=value (e.g. {scheme}:seed=1,frames=100)")
        out[key.strip()] = value.strip()
    return out


def _guess_scheme(path: Path) -> str | None:
    if not path.exists():
        return None
    if path.is_file():
        return "rosbag" if path.suffix in (".mcap", ".db3") else "replay"
    if (path / "metadata.yaml").is_file() and any(path.glob("*.mcap")) | any(path.glob("*.db3")):
        return "rosbag"
    if (path / "pose").is_dir() and (path / "depth").is_dir():
        return "scannet"
    if (path / "traj.txt").is_file() and (path / "results").is_dir():
        return "replica"
    if (path / "groundtruth.txt").is_file() and (path / "rgb.txt").is_file():
        return "tum"
    if (path / "trajectory.log").is_file():
        return "redwood"
    if (path / "openfusion_source.json").is_file():
        return "folder"
    return None


def _split_spec(spec: str) -> tuple[str, str, str]:
    """(stripped spec, known scheme, rest after ``scheme:``); SourceError for an empty spec or an
    unknown scheme."""
    if not isinstance(spec, str) or not spec.strip():
        raise SourceError(f"source spec must be a non-empty string like 'synthetic' or 'scannet:PATH', got {spec!r}")
    spec = spec.strip()
    scheme, _sep, rest = spec.partition(":")
    scheme = scheme.lower()
    if scheme not in _SCHEMES:
        hint = ""
        guess = _guess_scheme(Path(spec).expanduser())
        if guess is not None:
            hint = f"; {spec!r} looks like a {guess} source: use '{guess}:{spec}'"
        raise SourceError(f"unknown source scheme {scheme!r} in {spec!r}; known: {', '.join(SCHEMES)}{hint}")
    return spec, scheme, rest


def describe_source(spec: str) -> str | None:
    """One line on what a source found, for sources that choose among inputs (a rosbag: the topics
    it has and the ones it uses); None for the others. SourceError when the choice fails (a bag
    without a colour, depth, camera info or pose topic), before anything is started."""
    spec, scheme, rest = _split_spec(spec)
    if scheme != "rosbag":
        return None
    from openfusion.sources.rosbag import inspect_bag, parse_rosbag_spec

    path, options = parse_rosbag_spec(rest)
    return inspect_bag(path, options).describe(path)


def check_source_spec(spec: str) -> str:
    """Refuse a spec :func:`open_source` would refuse for its form, without opening the source:
    an unknown scheme, a missing path or recording, malformed ``key=value`` options, an unknown
    synthetic option or a value of the wrong type, an unknown live device set. Nothing is imported or read, so a command can check a source before it starts
    anything (``openfusion run``); the reader still checks the folder's contents when it opens.
    A synthetic spec's option keys and values are checked as the source checks them.
    Returns the stripped spec; raises :class:`SourceError`."""
    spec, scheme, rest = _split_spec(spec)
    _CHECKS[scheme](rest)
    return spec


def open_source(spec: str, **options: Any) -> FrameSource:
    """Open a frame source from ``scheme:argument`` (see module docstring).

    Raises :class:`SourceError` (a user error) for an unknown scheme, bad options, a missing path
    or a folder its reader cannot read.
    """
    spec, scheme, rest = _split_spec(spec)
    try:
        source = _SCHEMES[scheme](rest, options)
    except OpenFusionError:
        raise
    except (ValueError, TypeError, OSError) as exc:  # a reader refusing its folder or options
        raise SourceError(f"cannot open source {spec!r}: {exc}") from exc
    logger.info("opened source %s from spec %r", source.name, spec)
    return source
