"""``openfusion render``: a PNG of a saved map, optionally with a text query highlighted.

::

    openfusion render --map-dir out/map --out view.png
    openfusion render --map-dir out/map --query "chair" --top-k 2 --out chair.png --width 1280 --height 960
    openfusion render --map-dir out/map --colour label --out labels.png

CPU only (Open3D ray casting + Pillow): no GPU, no display. See docs/VISUALISE.md.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from openfusion.app.viz_args import (
    add_colour_arguments,
    add_map_arguments,
    add_view_arguments,
    check_colour_arguments,
    check_export_target,
    make_text_encoder_for,
)
from openfusion.errors import UsageError

logger = logging.getLogger(__name__)


class RenderCommand:
    """``openfusion render``: headless picture of a map (see module docstring)."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        add_map_arguments(parser)
        parser.add_argument("--out", required=True, type=Path, metavar="PNG", help="picture to write (.png)")
        add_colour_arguments(parser)
        add_view_arguments(parser)
        parser.add_argument(
            "--export-mesh",
            type=Path,
            default=None,
            metavar="FILE",
            help="also write the mesh with the picture's colours (.ply, or .glb with trimesh) and its legend",
        )
        parser.add_argument("--json", action="store_true", help="print a JSON summary instead of one line")

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        from openfusion.viz.camera import check_image_size, check_view_angles
        from openfusion.viz.export import export_mesh
        from openfusion.viz.picture import ViewOptions, open_map, picture_of_map
        from openfusion.viz.render import MAX_SUPERSAMPLE, save_png

        out = Path(args.out)
        if out.suffix.lower() != ".png":
            raise UsageError(f"--out must name a .png file, got {out}")
        if not out.parent.is_dir():
            raise UsageError(f"--out: folder {out.parent} does not exist")
        if not 1 <= args.supersample <= MAX_SUPERSAMPLE:
            raise UsageError(f"--supersample must be 1..{MAX_SUPERSAMPLE}, got {args.supersample}")
        classes = check_colour_arguments(args)
        if args.export_mesh is not None:
            check_export_target(args.export_mesh, "--export-mesh")
        check_image_size(args.width, args.height)
        check_view_angles(azimuth_deg=args.azimuth_deg, elevation_deg=args.elevation_deg, fov_deg=args.fov_deg)
        loaded = open_map(args.map_dir)
        text_encoder = make_text_encoder_for(args, loaded.dictionary)
        view = ViewOptions(
            width_px=args.width,
            height_px=args.height,
            up=args.up,
            azimuth_deg=args.azimuth_deg,
            elevation_deg=args.elevation_deg,
            fov_deg=args.fov_deg,
            supersample=args.supersample,
        )
        map_name = Path(args.map_dir).name or str(args.map_dir)
        picture = picture_of_map(
            loaded,
            view=view,
            colour=args.colour,
            query=args.query,
            top_k=args.top_k,
            text_encoder=text_encoder,
            class_names=classes,
            caption=not args.no_caption,
            map_name=map_name,
        )
        save_png(picture.image, out)
        written = [out]
        if args.export_mesh is not None:
            written += export_mesh(picture.mesh, args.export_mesh, colouring=picture.colouring)
        summary = {
            "out": str(out),
            "size_px": [args.width, args.height],
            "colour": args.colour,
            "coverage": round(picture.rendered.coverage, 4),
            "files": [str(p) for p in written],
            "query": args.query,
            "hits": [
                {"rank": i + 1, "key": h.key, "label": h.label, "score": round(h.score, 4)} for i, h in enumerate(picture.hits)
            ],
        }
        if picture.highlight_mask is not None:
            summary["highlighted_fraction"] = round(float(picture.highlight_mask.mean()), 5)
        if args.json:
            print(json.dumps(summary))
        else:
            line = f"wrote {out} ({args.width}x{args.height}, map covers {100 * picture.rendered.coverage:.0f}% of the image)"
            if args.query is not None:
                best = picture.hits[0] if picture.hits else None
                line += f"; query {args.query!r}: " + (
                    f"#1 {best.label or '(no label)'} (key {best.key}, score {best.score:.3f}), "
                    f"{100 * summary['highlighted_fraction']:.1f}% of the image highlighted"
                    if best
                    else "no region"
                )
            if len(written) > 1:
                line += "; also wrote " + ", ".join(str(p) for p in written[1:])
            print(line)
        return 0
