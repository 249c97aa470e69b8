"""``openfusion run --in-process``: the same pipeline and outputs as the service run, in one
process and without a bus (for notebooks and debugging)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from openfusion.app.outputs import open_rerun, write_query_outputs
from openfusion.encoders import make_region_encoder, make_text_encoder
from openfusion.frame import Frame
from openfusion.mapping import VolumeParams, query_regions, save_map
from openfusion.mapping.params import ROOM_SCALE_INITIAL_BLOCKS
from openfusion.mapping.pipeline import PipelineStats, map_scene
from openfusion.sources import open_source


def run_in_process(args: argparse.Namespace) -> dict[str, Any]:
    """``openfusion run --in-process``: the same outputs as the service run, in this process."""
    from tqdm import tqdm

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    source = open_source(args.source, max_frames=args.frames)
    options: dict[str, Any] = {"noise": args.noise} if (args.encoder == "gt" and args.noise) else {}
    encoder = make_region_encoder(args.encoder, **options)
    rerun = open_rerun(getattr(args, "rerun", None))
    log_frame = rerun.frame_hook() if rerun is not None else None
    bar = tqdm(total=args.frames, desc="frames integrated", unit="frame", disable=args.quiet)

    def on_frame(frame: Frame, stats: PipelineStats) -> None:
        bar.update(1)
        if log_frame is not None:
            log_frame(frame, stats)

    try:
        result = map_scene(
            source,
            region_encoder=encoder,
            volume_params=VolumeParams(initial_block_count=ROOM_SCALE_INITIAL_BLOCKS),  # as the service
            semantic_every=args.semantic_every,
            on_frame=on_frame,
        )
    finally:
        bar.close()
    save_map(out / "map", result.volume, result.dictionary, meta={"map_id": args.map_id})
    text = make_text_encoder(args.text_encoder)
    replies = []
    for query in args.queries:
        vec = text.encode([query])[0]
        hits = query_regions(result.dictionary, result.volume, vec, args.top_k, with_points=True, max_points=50_000,
                             embedding_space=text.embedding_space)
        replies.append((query, text.embedding_space, hits))
    write_query_outputs(out, replies, result.volume.extract_mesh(), say=None if args.quiet else print)
    if rerun is not None:
        rerun.log_map(result.volume, result.dictionary)
        for query, _space, hits in replies:
            rerun.log_query(query, hits)
        rerun.close()
    summary = {"source": args.source, "encoder": args.encoder, "noise": args.noise or "off",
               "semantic_every": args.semantic_every, "mode": "in-process", **result.stats.as_dict(),
               "frames_published": result.stats.frames_integrated, "regions": len(result.dictionary),
               "wall_s": round(time.monotonic() - started, 1), "map_dir": "map"}
    (out / "run.json").write_text(json.dumps(summary, indent=2))
    return summary
