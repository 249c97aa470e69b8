#!/usr/bin/env python3
"""Two laps of the built-in room, in process, before and after region merging: regions at the end
of lap 1 (after a merge pass, as the end of a run does) and at the end of lap 2, in one run per map.

    python bench/bench_laps.py            # --quick (default): laps of 120 frames (synthetic:lap=120)
    python bench/bench_laps.py --full     # the built-in room's own lap (LAP_FRAMES = 360 frames)
    python bench/bench_laps.py --lap 200  # any lap length

"before" = no merge pass and no join (the previous behaviour); "after" = the defaults. "regions" =
dictionary entries; "answers" = regions with at least ``query.min_region_points`` surface points
(what a query can return). The count at the end of lap 1 needs the map mid-run: ``map_scene``
exposes it only at the end, so the mapper is picked up by a subclass that records itself.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from openfusion.app.run_config import RunConfig
from openfusion.mapping import pipeline
from openfusion.mapping.merging import merge_regions
from openfusion.mapping.params import MatchParams, MergeParams
from openfusion.services.semantic.service import region_encoder_from_section
from openfusion.sources import open_source
from openfusion.sources.synthetic.camera import LAP_FRAMES


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="laps of 120 frames (default)")
    size.add_argument("--full", action="store_true", help=f"the room's own lap ({LAP_FRAMES} frames)")
    size.add_argument("--lap", type=int, default=None, help="frames per lap")
    args = parser.parse_args(argv)
    lap = args.lap or (LAP_FRAMES if args.full else 120)
    spec = f"synthetic:lap={lap},frames={2 * lap}"
    cfg = RunConfig()
    least = cfg.query.min_region_points

    def count(volume, dictionary) -> tuple[int, int]:  # noqa: ANN001
        pts = volume.extract_points()
        _, c = np.unique(pts.keys[pts.keys >= 0], return_counts=True)
        return len(dictionary), int((c >= least).sum())

    print(f"### Two laps of the built-in room ({spec}, in process, gt encoder)")
    print()
    print(f"| map | lap 1: regions | lap 1: answers (>= {least} points) | lap 2: regions | lap 2: answers | "
          "keys created | merged | ms / merge pass | wall (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    original = pipeline.SemanticMapper
    for name, match, merge in [("before (no merge, no join)", MatchParams(join_min_coverage=None),
                                MergeParams(merge_every=0)), ("after", MatchParams(), MergeParams())]:
        t0 = time.perf_counter()
        held: dict = {}

        class Recorded(original):  # type: ignore[misc, valid-type]
            def __init__(self, *args, held=held, **kwargs) -> None:  # noqa: ANN001, ANN002, ANN003
                super().__init__(*args, **kwargs)
                held["mapper"] = self

        def on_frame(_frame, stats, merge=merge, held=held) -> None:  # noqa: ANN001
            if stats.frames_integrated == lap:
                m = held["mapper"]
                if merge.merge_every:
                    merge_regions(m.volume, m.dictionary, merge)
                held["lap1"] = count(m.volume, m.dictionary)

        pipeline.SemanticMapper = Recorded
        try:
            r = pipeline.map_scene(open_source(spec), region_encoder=region_encoder_from_section(cfg.semantic),
                                   volume_params=cfg.geometry.volume_params(), match_params=match,
                                   merge_params=merge, semantic_every=cfg.semantic.every_k, on_frame=on_frame)
        finally:
            pipeline.SemanticMapper = original
        lap2 = count(r.volume, r.dictionary)
        per_pass = 1e3 * r.stats.merge_s / r.stats.merge_passes if r.stats.merge_passes else None
        print(f"| {name} | {held['lap1'][0]} | {held['lap1'][1]} | {lap2[0]} | {lap2[1]} | {r.dictionary.next_key} | "
              f"{r.stats.regions_merged} | {'n/a' if per_pass is None else f'{per_pass:.0f}'} | "
              f"{time.perf_counter() - t0:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
