"""``openfusion run --in-process``: the same pipeline and outputs as the service run, in one
process and without a bus (for notebooks and debugging).

The first SIGINT (Ctrl-C) or SIGTERM ends the loop before the next frame; the map of the frames
integrated so far is saved, ``run.json`` says ``interrupted: true`` and the command exits with
code 130 (:class:`~openfusion.errors.Interrupted`). A second signal aborts at once.

``--timeout-s``: mapping that is not done by then ends with the same error as the service run's
(:class:`~openfusion.app.launcher.RunError`, exit code 1). Progress lines go to stderr, as in the
service run: stdout carries only the run summary."""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from openfusion.app.launcher import RunError, StopSignals
from openfusion.app.outputs import open_rerun, say_progress, write_query_outputs
from openfusion.app.run_config import RunConfig
from openfusion.app.summary import RunSummary
from openfusion.frame import Frame
from openfusion.mapping import save_map
from openfusion.mapping.params import MatchParams, MergeParams, SelectParams
from openfusion.mapping.pipeline import PipelineStats, map_scene
from openfusion.mapping.queries import RegionTable, answer_texts, subsample_points
from openfusion.progress import progress_bar
from openfusion.services.encoder.options import region_encoder_from_section
from openfusion.services.query.service import text_encoder_from_section
from openfusion.sources import open_source


class _UntilStopped:
    """``source`` until the run is asked to stop: no further frame is read once ``signals.requested``
    is set; past ``timeout_s`` (from the first frame asked for) :class:`RunError`. ``taken``: frames
    handed to the loop; ``stats``: the source's."""

    def __init__(self, source: Any, signals: StopSignals, timeout_s: float | None = None) -> None:
        self.source = source
        self.signals = signals
        self.timeout_s = timeout_s
        self.taken = 0

    @property
    def stats(self) -> Any:
        return self.source.stats

    def __iter__(self) -> Iterator[Frame]:
        frames = iter(self.source)
        deadline = None if self.timeout_s is None else time.monotonic() + self.timeout_s
        while not self.signals.requested:
            if deadline is not None and time.monotonic() > deadline:
                raise RunError(f"the run did not finish within {self.timeout_s:g} s "
                               f"(integrated {self.taken} frames)")
            frame = next(frames, None)
            if frame is None:
                return
            self.taken += 1
            yield frame


def run_in_process(args: argparse.Namespace, config: RunConfig) -> RunSummary:
    """``openfusion run --in-process``: the same outputs as the service run, in this process, from
    the same config sections the services read."""
    with StopSignals() as signals:
        return _run_in_process(args, config, signals)


def _run_in_process(args: argparse.Namespace, config: RunConfig, signals: StopSignals) -> RunSummary:
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    source = _UntilStopped(open_source(config.bridge.source, max_frames=config.bridge.max_frames), signals,
                           timeout_s=getattr(args, "timeout_s", None))
    encoder = region_encoder_from_section(config.semantic)
    rerun = open_rerun(getattr(args, "rerun", None))
    log_frame = rerun.frame_hook() if rerun is not None else None
    bar = progress_bar(config.bridge.max_frames, "frames integrated", disable=args.quiet)

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
            merge_params=MergeParams.from_section(config.semantic),
            semantic_every=config.semantic.every_k,
            select_params=SelectParams.from_section(config.semantic),
            on_frame=on_frame,
        )
    finally:
        bar.close()

    def summary_now() -> RunSummary:
        return RunSummary.from_pipeline(
            result.stats, regions=len(result.dictionary), source=config.bridge.source,
            encoder=config.semantic.encoder, noise=config.semantic.noise, semantic_every=config.semantic.every_k,
            wall_s=time.monotonic() - started, frames_requested=config.bridge.max_frames, frames_played=source.taken,
            interrupted=signals.requested is not None)

    if signals.requested:
        if rerun is not None:
            rerun.close()
        summary = summary_now()
        if summary.frames_integrated:
            save_map(out / "map", result.volume, result.dictionary, meta={"map_id": config.map_id})
            summary.map_saved = str((out / "map").resolve())
        (out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
        if not summary.frames_integrated:
            raise signals.interrupted("no frame was integrated yet; nothing saved")
        raise signals.interrupted(f"saved the map of {summary.frames_integrated} integrated frames to {out / 'map'}")
    surface = result.volume.extract_points()
    table = RegionTable.of_points(surface.keys, surface.points)
    save_map(out / "map", result.volume, result.dictionary, meta={"map_id": config.map_id}, regions=table)
    text = text_encoder_from_section(config.query)
    replies = []
    # as the query service answers: relevancy, match, nearby regions, "X next to Y" (one encoder call)
    answers = answer_texts(result.dictionary, table, list(args.queries), text, top_k=args.top_k,
                           min_points=config.query.min_region_points, up_axis=config.query.up_axis)
    for query, (hits, _answer) in zip(args.queries, answers, strict=True):
        for hit in hits:
            hit.points = subsample_points(surface.points[surface.keys == hit.key], 50_000, seed=hit.key)
        replies.append((query, text.embedding_space, hits))
    write_query_outputs(out, replies, result.volume.extract_mesh(), say=say_progress(args.quiet))
    if rerun is not None:
        rerun.log_map(result.volume, result.dictionary)
        for query, _space, hits in replies:
            rerun.log_query(query, hits)
        rerun.close()
    summary = summary_now()
    summary.map_saved = str((out / "map").resolve())
    (out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
    return summary
