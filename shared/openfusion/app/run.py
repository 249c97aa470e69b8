"""``openfusion run``: the embedded default — every service on this machine, one command.

The command opens a Zenoh session in router mode on a free loopback port (multicast off), starts
geometry, semantic and query as separate processes in peer mode connected to it, waits until they
are alive, then starts the bridge on the chosen source (the built-in synthetic scene by default).
It shows progress from the services' health stats, waits until geometry has integrated every
published frame and semantics has caught up, saves the map to ``OUT/map``, runs example queries,
writes the mesh and query results, writes ``OUT/run.json`` and stops the services (SIGTERM).

``--in-process`` runs the same pipeline in this process (no bus), for notebooks and debugging.
``--web [PORT]`` also serves the query page (:mod:`openfusion.app.web_cmd`) on 127.0.0.1 from the
moment the services start, prints its URL on stderr, and after the run keeps the services and the
page until Ctrl-C.

Frames: ``--frames N`` plays N frames. The built-in room (``--source synthetic[:...]``) plays N
frames whatever N is: its camera walks a closed lap of :data:`BUILTIN_LAP_FRAMES` frames and walks it
again for longer runs (same poses, frame ids and stamps keep increasing); a spec that sets
``frames=`` or ``lap=`` keeps them. The building (``--source synthetic:building,...``) walks its
route once: ``--frames N`` spreads N frames over the walk (unless the spec sets ``frames=``), and
without it the walk plays at its own density (a frame every 0.3 m or 20 degrees). Other sources play
at most ``--frames`` (default :data:`BUILTIN_LAP_FRAMES`). A source with fewer frames plays what it
has, and the run says so (``played 300 of 2000 frames: the source has 300``) and records it in
``run.json``.

Stopping: the first SIGINT (Ctrl-C) or SIGTERM stops playback (the bridge), lets geometry and
semantic finish the frames they already have, saves the map to ``OUT/map``, writes ``run.json``
(``interrupted: true``), skips the example queries and exits with code 130; a second signal aborts
at once (every service killed, no map). The services run in their own process group, so a
terminal's Ctrl-C reaches only this process, and none outlives it (:mod:`openfusion.app.launcher`).

Supervision: a service that dies during the run is restarted (``--max-restarts``, default 3 per
service, ``--restart-backoff-s``, doubled for each restart; :mod:`openfusion.app.launcher`) and
``run.json`` counts ``restarts`` per service. Geometry checkpoints to ``OUT/checkpoints`` every
``supervision.checkpoint_period_s`` (10 s; a save of the room takes about 24 frames' integration,
``bench/bench_checkpoint.py``); a restarted geometry loads the last checkpoint and announces the
last frame it holds, the bridge replays the frames after it, and geometry ignores frames it
already holds, so every frame is integrated exactly once (README, "Crash-proof mapping").
Past the restart limit the run fails as without supervision, but first saves the map geometry
holds (when it is alive) and writes ``run.json`` with the ``error``. ``run.json``'s ``map_saved``
says where the map went on every path that saved one (done, interrupted, failed after saving);
the progress line and ``run.json`` count semantic frames the same way across restarts
(:func:`~openfusion.app.run_progress.progress_counts`).

Settings: one :class:`~openfusion.app.run_config.RunConfig` (every service's section), validated
before anything starts, written to ``OUT/run-config.json`` and read by every service.

Where it is: this module is the command (its options, their checks, the run config from them);
:mod:`openfusion.app.run_sources` what a run plays, :mod:`openfusion.app.run_services` the run with
services, :mod:`openfusion.app.run_progress` following it until it is done,
:mod:`openfusion.app.run_in_process` the run in this process.

Outputs in ``--out DIR`` (default ``out``): ``map/`` (the saved map), ``mesh.ply``,
``queries.json``, ``query_<i>.ply`` (points of the best region of each query), ``run.json``
(:class:`~openfusion.app.summary.RunSummary`), ``run-config.json``, ``logs/<service>.log``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from openfusion.app.run_config import RUN_FLAGS, SECTION_MODELS, RunConfig
from openfusion.app.run_services import run_services, say
from openfusion.app.run_sources import (
    BUILTIN_LAP_FRAMES,
    builtin_scene_spec,
    frames_to_play,
    robot_sources,
    shortfall_note,
)
from openfusion.config import add_section_options, config_from_args
from openfusion.errors import UsageError
from openfusion.services.bridge.service import BridgeSection
from openfusion.sources.registry import check_source_spec, describe_source
from openfusion.wire.keys import MAX_SHARDS, validate_map_id
from openfusion.wire.limits import LimitError, check_text, check_top_k

__all__ = ["BUILTIN_LAP_FRAMES", "DEFAULT_QUERIES", "RunCommand", "builtin_scene_spec", "frames_to_play", "run_services",
           "shortfall_note"]

DEFAULT_QUERIES = ("chair", "table", "something to sit on", "a plant", "monitor")


def _check_out_dir(out: Path) -> None:
    """Refuse an output folder the run could not write (a file in the way, no write permission),
    before the scene is mapped: the map would otherwise be lost at the end."""
    if out.exists():
        if not out.is_dir():
            raise UsageError(f"--out {out}: exists and is not a folder")
        existing = out
    else:
        existing = next(p for p in out.absolute().parents if p.exists())
        if not existing.is_dir():
            raise UsageError(f"--out {out}: cannot make a folder there, {existing} is a file")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise UsageError(f"--out {out}: {existing} is not writable")


def _check_queries(queries: Sequence[str], top_k: int) -> None:
    """Refuse example queries the query service would refuse (empty or too long a text, ``--top-k``
    out of range) with the one set of limits (:mod:`openfusion.wire.limits`), before the scene is mapped."""
    for text in queries:
        try:
            check_text(text)
        except LimitError as exc:
            raise UsageError(f"--query {text[:40]!r}: {exc}") from None
    check_top_k(top_k, name="--top-k")


def _check_text_encoder(config: RunConfig) -> None:
    """Refuse a query text encoder that cannot read the map the gt encoder makes (its regions are
    embedded with MiniLM): the example queries would be refused only after the scene was mapped."""
    text = config.query.text_encoder.strip().lower()
    if config.semantic.encoder == "gt" and text not in ("minilm", "gt"):
        raise UsageError(f"--text-encoder {config.query.text_encoder!r} cannot query the regions of the gt "
                         "encoder: they are in the MiniLM space (use --text-encoder minilm)")


#: More encoder workers than this on one machine is a typo, not a plan.
MAX_ENCODER_WORKERS = 16
MAX_QUERY_SERVICES = 8


class RunCommand:
    """Registry entry for ``openfusion run``."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (default ./out)")
        parser.add_argument("--source", dest="sources", action="append", default=None, metavar="SPEC",
                            help="frame source: " + str(BridgeSection.model_fields["source"].description) + ". Repeat "
                            "it for several robots in one map (one bridge each; ',name=ROBOT' names one, else "
                            "robot0, robot1, ...; README 'Several robots')")
        parser.add_argument("--map", dest="map_id", default="demo", help="map id (default demo)")
        parser.add_argument("--frames", type=int, default=None,
                            help=f"frames to play (default {BUILTIN_LAP_FRAMES}); one lap of the built-in room is "
                            f"{BUILTIN_LAP_FRAMES} frames, more frames walk it again; synthetic:building walks its "
                            "route once in N frames (default: its own, a frame every 0.3 m or 20 degrees); "
                            "a shorter source plays what it has")
        parser.add_argument("--query", dest="queries", action="append", default=None,
                            help="example query (repeatable; default a few furniture queries)")
        parser.add_argument("--top-k", type=int, default=3, help="regions per query (default 3)")
        parser.add_argument("--timeout-s", type=float, default=900.0,
                            help="give up when mapping the frames takes longer than this many seconds (default 900)")
        parser.add_argument("--in-process", action="store_true",
                            help="run the pipeline in this process (no bus; no --rate-hz: frames go as fast as they are mapped)")
        parser.add_argument("--rerun", metavar="SINK", default=None,
                            help="log frames, trajectory, mesh and query results to rerun: save:FILE.rrd | spawn | "
                            "serve (needs the viz extra)")
        parser.add_argument("--web", nargs="?", type=int, const=0, default=None, metavar="PORT",
                            help="also serve the query page (openfusion web) on 127.0.0.1:PORT (no PORT: a free "
                            "one), printing its URL; after the run it stays, with the services, until Ctrl-C")
        parser.add_argument("--encoder-workers", type=int, default=0, metavar="N",
                            help="start N encoder workers (the encoder pool, `openfusion service encoder`) and let the "
                            "semantic service send them its frames (default 0: it encodes them itself)")
        parser.add_argument("--query-services", type=int, default=1, metavar="N",
                            help="start N query services on the map (query, query-2, …): each holds the dictionary "
                            "and summaries, a request is answered by one of them (default 1)")
        parser.add_argument("--geometry-shards", type=int, default=1, metavar="N",
                            help="split the map by tile across N geometry processes (geometry-0ofN, …), each "
                            "integrating only its tiles' blocks of every frame (docs/SHARDS.md; default 1)")
        parser.add_argument("--quiet", action="store_true",
                            help="no progress output (stderr); the run summary still goes to stdout")
        parser.add_argument("--config", metavar="FILE", help="TOML/JSON/YAML file with [bridge], [geometry], "
                            "[semantic], [query] sections (or $OPENFUSION_CONFIG)")
        parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                            help="any parameter of any service, e.g. --set geometry.voxel_size_m=0.04 (repeatable; "
                            "`openfusion config --show SERVICE` lists them)")
        for section, fields in RUN_FLAGS.items():
            add_section_options(parser, SECTION_MODELS[section], section, fields=fields,
                                title="supervision (services that die are restarted)" if section == "supervision"
                                else f"{section} service")

    @staticmethod
    def config_from_args(args: argparse.Namespace) -> RunConfig:
        """The validated run config (bad values are refused here, before any process starts)."""
        validate_map_id(args.map_id)
        _check_out_dir(args.out)
        if args.frames is not None and args.frames <= 0:
            raise UsageError(f"--frames must be positive, got {args.frames}")
        if not 0 <= args.encoder_workers <= MAX_ENCODER_WORKERS:
            raise UsageError(f"--encoder-workers must be between 0 and {MAX_ENCODER_WORKERS}, got {args.encoder_workers}")
        if args.in_process and args.encoder_workers:
            raise UsageError("--encoder-workers starts encoder services; --in-process has none")
        if not 1 <= args.query_services <= MAX_QUERY_SERVICES:
            raise UsageError(f"--query-services must be between 1 and {MAX_QUERY_SERVICES}, got {args.query_services}")
        if args.in_process and args.query_services > 1:
            raise UsageError("--query-services starts query services; --in-process has none")
        if not 1 <= args.geometry_shards <= MAX_SHARDS:
            raise UsageError(f"--geometry-shards must be between 1 and {MAX_SHARDS}, got {args.geometry_shards}")
        if args.in_process and args.geometry_shards > 1:
            raise UsageError("--geometry-shards starts geometry services; --in-process has none")
        if args.timeout_s <= 0:
            raise UsageError(f"--timeout-s must be positive, got {args.timeout_s:g}")
        _check_queries(args.queries or DEFAULT_QUERIES, args.top_k)
        if args.rerun:  # the sink's form and the package; the run opens the sink only after the router
            from openfusion.viz.errors import MissingDependencyError
            from openfusion.viz.rerun_log import parse_sink, rerun_available

            parse_sink(args.rerun)
            if not rerun_available():
                raise MissingDependencyError("rerun-sdk", "--rerun")
        if args.web is not None:
            from openfusion.app.web_server import DEFAULT_MAX_POINTS, check_page_options

            if args.in_process:
                raise UsageError("--web serves the page of the running services; --in-process runs none")
            check_page_options(port=args.web, max_points=DEFAULT_MAX_POINTS, port_flag="--web PORT")
        if args.in_process and args.bridge__rate_hz is not None:
            raise UsageError("--rate-hz paces the bridge service; --in-process has none (it maps every frame "
                             "as soon as the last one is done)")
        config = config_from_args(args, RunConfig, sections=list(RUN_FLAGS))
        config.map_id = args.map_id
        _check_text_encoder(config)
        sources = robot_sources(args.sources or [config.bridge.source], default_robot=config.bridge.robot)
        if len(sources) > 1 and args.in_process:
            raise UsageError("--in-process plays one source; several --source need the services (one bridge each)")
        frames: dict[str, int] = {}
        for robot, spec in sources.items():
            # The source's form (scheme, path, options): the bridge would refuse it only after the other
            # services had started.
            check_source_spec(spec)
            # The built-in room plays --frames frames (laps of BUILTIN_LAP_FRAMES), the building its walk;
            # other sources stop there.
            sources[robot] = builtin_scene_spec(spec, args.frames)
            frames[robot] = frames_to_play(sources[robot], args.frames)
        (config.bridge.robot, config.bridge.source), *_others = sources.items()
        config.robots = sources if len(sources) > 1 else {}
        config.robot_frames = frames if len(sources) > 1 else {}
        args.frames = sum(frames.values())  # the progress bar's total
        config.bridge.max_frames = frames[config.bridge.robot]
        return config

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        import json

        config = RunCommand.config_from_args(args)
        args.queries = args.queries or list(DEFAULT_QUERIES)
        described = describe_source(config.bridge.source)  # a rosbag: its topics and the ones used
        if described:
            say(args, described)
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        if args.in_process:
            from openfusion.app.run_in_process import run_in_process

            summary = run_in_process(args, config)
        else:
            summary = run_services(args, config)
        note = shortfall_note(summary)
        if note:  # said even with --quiet: the run did less than asked
            print(note, file=sys.stderr, flush=True)
        print(json.dumps(summary.model_dump(), indent=2))
        say(args, f"outputs in {args.out.resolve()}")
        return 0
