"""``openfusion export``: a saved map's mesh or points as PLY / GLB, coloured, with a legend.

::

    openfusion export --map-dir out/map --out mesh.ply                    # camera colours
    openfusion export --map-dir out/map --out regions.glb --colour region # one colour per region key
    openfusion export --map-dir out/map --out points.ply --points --colour label
    openfusion export --map-dir out/map --out chair.ply --query "chair"   # match red, rest grey

Coloured exports also write ``<name>.legend.json`` and ``<name>.legend.md`` (colour -> key / label).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from openfusion.app.viz_args import (
    add_colour_arguments,
    add_map_arguments,
    check_colour_arguments,
    check_export_target,
    make_text_encoder_for,
)
from openfusion.errors import UsageError
from openfusion.viz.errors import VizError

logger = logging.getLogger(__name__)


class ExportCommand:
    """``openfusion export``: mesh / point cloud files of a map (see module docstring)."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        add_map_arguments(parser)
        parser.add_argument("--out", required=True, type=Path, metavar="FILE", help="file to write: .ply or .glb")
        parser.add_argument("--points", action="store_true", help="write surface points instead of the mesh (.ply)")
        parser.add_argument("--max-points", type=int, default=None, metavar="N", help="with --points: subsample to N points")
        add_colour_arguments(parser)
        parser.add_argument("--json", action="store_true", help="print a JSON summary instead of one line")

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        from openfusion.viz.export import export_mesh, export_points
        from openfusion.viz.picture import colour_mesh, open_map
        from openfusion.viz.query import query_text

        out = Path(args.out)
        suffix = out.suffix.lower()
        if suffix not in (".ply", ".glb"):
            raise UsageError(f"--out must end in .ply or .glb, got {out}")
        if args.points and suffix != ".ply":
            raise UsageError("--points writes a .ply point cloud; use an --out ending in .ply")
        if args.max_points is not None and (not args.points or args.max_points < 1):
            raise UsageError("--max-points needs --points and a value >= 1")
        check_export_target(out, "--out")
        classes = check_colour_arguments(args)
        loaded = open_map(args.map_dir)
        text_encoder = make_text_encoder_for(args, loaded.dictionary)
        hits = None
        if args.query is not None:
            if len(loaded.dictionary) == 0:
                raise VizError("the map has no regions to query (it was mapped without semantics)")
            hits = query_text(loaded.dictionary, args.query, top_k=args.top_k, text_encoder=text_encoder)
        if args.points:
            geometry = loaded.volume.extract_points(max_points=args.max_points)
        else:
            geometry = loaded.volume.extract_mesh()
        if len(geometry.keys) == 0:
            raise VizError("the map has no surface to export (no integrated geometry)")
        colouring = None
        if args.colour != "rgb" or hits is not None:
            colouring = colour_mesh(
                geometry,
                loaded.dictionary,
                colour=args.colour,
                hits=hits,
                query=args.query or "",
                class_names=classes,
                text_encoder=text_encoder,
            )
        if args.points:
            written = export_points(geometry, out, colouring=colouring)
        else:
            written = export_mesh(geometry, out, colouring=colouring)
        summary = {
            "files": [str(p) for p in written],
            "elements": int(len(geometry.keys)),
            "kind": "points" if args.points else "mesh",
            "colour": "query" if hits is not None else args.colour,
            "hits": [{"rank": i + 1, "key": h.key, "label": h.label, "score": round(h.score, 4)} for i, h in enumerate(hits or [])],
        }
        if args.json:
            print(json.dumps(summary))
        else:
            what = f"{summary['elements']:,} {'points' if args.points else 'vertices'}"
            print(f"wrote {', '.join(summary['files'])} ({what}, colour {summary['colour']})")
        return 0
