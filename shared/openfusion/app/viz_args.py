"""Arguments shared by ``openfusion render`` and ``openfusion export``, and their checking.

Every problem a user can cause (no map there, not a map, an unknown colour mode or embedding
space, a bad size) is a :class:`~openfusion.errors.UserError` (one clear line, exit code 2).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from openfusion.errors import UsageError
from openfusion.viz.camera import UP_AXES
from openfusion.viz.errors import MissingDependencyError

logger = logging.getLogger(__name__)

def add_map_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--map-dir", required=True, type=Path, metavar="DIR", help="map folder (holding map.ofz.npz) or the .npz file"
    )


def add_colour_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--colour",
        "--color",
        dest="colour",
        default="rgb",
        choices=("rgb", "region", "label"),
        help="vertex colours: fused camera colour, one colour per region key, or one per label (default rgb)",
    )
    parser.add_argument(
        "--classes",
        default=None,
        metavar="A,B,...",
        help="with --colour label: colour each region by its best-matching class from this comma-separated list",
    )
    parser.add_argument("--query", default=None, metavar="TEXT", help="highlight the regions best matching TEXT")
    parser.add_argument("--top-k", type=int, default=None, metavar="K",
                        help="with --query: highlight the K best regions (default 1)")
    parser.add_argument(
        "--text-encoder",
        default=None,
        metavar="NAME",
        help="text encoder for --query/--classes (default: the one of the map's embedding space)",
    )
    parser.add_argument("--text-model", default=None, metavar="PATH",
                        help="with --query/--classes: model for --text-encoder onnx / clip-regions")


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--width", type=int, default=1024, metavar="W", help="image width in pixels (default 1024)")
    parser.add_argument("--height", type=int, default=768, metavar="H", help="image height in pixels (default 768)")
    parser.add_argument("--up", default="+z", choices=tuple(UP_AXES), help="the map's up axis (default +z)")
    parser.add_argument("--azimuth-deg", type=float, default=235.0, help="camera direction around the up axis (default 235)")
    parser.add_argument("--elevation-deg", type=float, default=55.0,
                        help="camera height angle above the horizon, -89 to 89 (default 55)")
    parser.add_argument("--fov-deg", type=float, default=45.0, help="horizontal field of view, 5 to 150 (default 45)")
    parser.add_argument("--supersample", type=int, default=2, metavar="S", help="anti-aliasing: render SxS samples per pixel (1-4, default 2)")
    parser.add_argument("--no-caption", action="store_true", help="leave the caption out")


def check_colour_arguments(args: argparse.Namespace) -> list[str] | None:
    """Validate query/colour options; returns the class list (or None). ``--top-k`` not given is 1."""
    if args.top_k is not None and args.query is None:
        raise UsageError("--top-k says how many regions --query highlights; give --query too")
    args.top_k = 1 if args.top_k is None else args.top_k
    if args.top_k < 1:
        raise UsageError(f"--top-k must be >= 1, got {args.top_k}")
    if args.query is not None and not args.query.strip():
        raise UsageError("--query is empty")
    if args.query is None and args.classes is None:
        given = [flag for flag, value in (("--text-encoder", args.text_encoder), ("--text-model", args.text_model))
                 if value is not None]
        if given:
            raise UsageError(f"{' and '.join(given)} {'embed' if len(given) > 1 else 'embeds'} the text of --query or "
                             "--classes; give one of them too")
    classes = None
    if args.classes is not None:
        classes = [c.strip() for c in args.classes.split(",") if c.strip()]
        if not classes:
            raise UsageError("--classes is empty; give names separated by commas")
        if args.colour != "label":
            raise UsageError("--classes only applies with --colour label")
    return classes


def make_text_encoder_for(args: argparse.Namespace, dictionary):  # noqa: ANN001, ANN201
    """The text encoder for the map's space when the options need one (query or classes), else None."""
    if args.query is None and args.classes is None:
        return None
    from openfusion.viz.query import text_encoder_for_map

    return text_encoder_for_map(dictionary, name=args.text_encoder, model=args.text_model)


def check_export_target(path: Path, option: str) -> None:
    """Refuse a mesh target we cannot write before any work is done: suffix, folder, trimesh for .glb."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".ply", ".glb"):
        raise UsageError(f"{option} must end in .ply or .glb, got {path}")
    if not Path(path).parent.is_dir():
        raise UsageError(f"{option}: folder {Path(path).parent} does not exist")
    if suffix == ".glb":
        try:
            import trimesh  # noqa: F401
        except ImportError as exc:
            raise MissingDependencyError("trimesh", "GLB export") from exc
