"""``python -m openfusion.sources.record_scannet SPEC OUT_DIR``: a ScanNet-layout recording of any source.

Opens ``SPEC`` (``open_source``: e.g. ``synthetic:building,rooms=10``, ``rosbag:PATH``) and writes
every frame with :func:`~openfusion.sources.scannet_writer.write_scannet_layout` (and, for a
synthetic source, its ground-truth surface and metadata such as the building's floor area), so
``--source scannet:OUT_DIR`` and ``openfusion eval --scenes scannet:OUT_DIR`` play and score it.
A command of its own (not in the writer) because it opens sources by spec: the registry already
imports the synthetic package, which exports the writer.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from openfusion.errors import OpenFusionError
from openfusion.sources.registry import open_source
from openfusion.sources.scannet_writer import write_scannet_layout


def main(argv: list[str] | None = None) -> int:
    """``python -m openfusion.sources.record_scannet SPEC OUT_DIR``: write any source (e.g.
    ``synthetic:building``) as a ScanNet-layout scene that ``--source scannet:OUT_DIR`` and
    ``openfusion eval --scenes scannet:OUT_DIR`` read. Bad input: one line on stderr, exit 2."""
    parser = argparse.ArgumentParser(prog="python -m openfusion.sources.record_scannet", description=main.__doc__.splitlines()[0])
    parser.add_argument("spec", help="source spec, e.g. synthetic:building,rooms=10")
    parser.add_argument("out_dir", type=Path, help="scene folder to write (its name is the scene's, e.g. building0000_00)")
    parser.add_argument("--color", choices=("jpg", "png"), default="jpg", help="color image format (default jpg, quality 100)")
    parser.add_argument("--gt-spacing", type=float, default=0.02, metavar="M",
                        help="ground-truth surface sampling of a synthetic source in metres (default 0.02; 0: none)")
    parser.add_argument("--overwrite", action="store_true", help="replace OUT_DIR when it exists")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.gt_spacing < 0:
            raise ValueError(f"--gt-spacing must be >= 0, got {args.gt_spacing:g}")
        source = open_source(args.spec)
        written = write_scannet_layout(source, args.out_dir, color_format=args.color, overwrite=args.overwrite,
                                       ground_truth_spacing_m=args.gt_spacing or None)
    except FileExistsError:
        print(f"{parser.prog}: error: {args.out_dir} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    except (OpenFusionError, ValueError) as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    meta = getattr(source, "metadata", {}) or {}
    area = f", {meta['floor_area_m2']:.0f} m² of floor" if "floor_area_m2" in meta else ""
    print(f"wrote {written.num_frames} frames of {source.name} to {written.path} "
          f"({written.ground_truth_points} ground-truth points{area})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
