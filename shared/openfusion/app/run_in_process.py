"""``openfusion run --in-process``: the same pipeline and outputs as the service run, in one
process and without a bus (for notebooks and debugging)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from openfusion.app.outputs import open_rerun, write_query_outputs
from openfusion.app.run_config import RunConfig
from openfusion.app.summary import RunSummary
from openfusion.frame import Frame
from openfusion.mapping import query_regions, save_map
from openfusion.mapping.params import MatchParams
from openfusion.mapping.pipeline import PipelineStats, map_scene
from openfusion.services.query.service import text_encoder_from_section
from openfusion.services.semantic.service import region_encoder_from_section
from openfusion.sources import open_source


def run_in_process(args: argparse.Namespace, config: RunConfig) -> RunSummary:
    """``openfusion run --in-process``: the same outputs as the service run, in this process, from
    the same config sections the services read."""
    from tqdm import tqdm

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    source = open_source(config.bridge.source, max_frames=config.bridge.max_frames)
    encoder = region_encoder_from_section(config.semantic)
    rerun = open_rerun(getattr(args, "rerun", None))
    log_frame = rerun.frame_hook() if rerun is not None else None
    bar = tqdm(total=config.bridge.max_frames, desc="frames integrated", unit="frame", disable=args.quiet)

    def on_frame(frame: Frame, stats: PipelineStats) -> None:
        bar.update(1)
        if log_frame is not None:
            log_frame(frame, stats)

    try:
        result = map_scene(
            source,
            region_encoder=encoder,
            volume_params=config.geometry.volume_params(),
            match_params=MatchParams.from_section(config.semantic),
            semantic_every=config.semantic.every_k,
            on_frame=on_frame,
        )
    finally:
        bar.close()
    save_map(out / "map", result.volume, result.dictionary, meta={"map_id": config.map_id})
    text = text_encoder_from_section(config.query)
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
    summary = RunSummary.from_pipeline(
        result.stats, regions=len(result.dictionary), source=config.bridge.source, encoder=config.semantic.encoder,
        noise=config.semantic.noise, semantic_every=config.semantic.every_k, wall_s=time.monotonic() - started)
    (out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
    return summary
