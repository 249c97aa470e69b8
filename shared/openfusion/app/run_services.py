"""The multi-process run of ``openfusion run`` (:func:`run_services`): a router on a free loopback
port, the services started and supervised (:mod:`openfusion.app.launcher`), the bridges playing,
progress followed (:mod:`openfusion.app.run_progress`), the map saved, the example queries, the
outputs, and ``--web``'s page beside them (the :mod:`openfusion.app.run` docstring says what a
run does on every path)."""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import time
import uuid
from pathlib import Path
from typing import Any

from openfusion.app import shard_run
from openfusion.app.end_of_run import fetch_mesh, save_and_wait
from openfusion.app.launcher import Cluster, RunError, StopSignals, wait_for_services
from openfusion.app.outputs import open_rerun, say_progress, surface_mesh, write_query_outputs
from openfusion.app.run_config import RunConfig, write_service_config
from openfusion.app.run_progress import follow_progress, refresh_stats, with_carried
from openfusion.app.summary import RunSummary
from openfusion.bus import free_loopback_port, open_session
from openfusion.client import OpenFusionClient
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.services.bridge.service import bridge_name
from openfusion.services.query.instances import query_service_name
from openfusion.wire.endpoints import SENSOR_INSTANCE, SENSOR_RGBD

logger = logging.getLogger(__name__)

#: Points returned with each example query's regions.
QUERY_MAX_POINTS = 50_000
SERVICE_START_TIMEOUT_S = 180.0


def run_services(args: argparse.Namespace, config: RunConfig) -> RunSummary:
    """The multi-process embedded run; returns the run summary (also written to run.json).

    Raises :class:`~openfusion.errors.Interrupted` after a first SIGINT/SIGTERM (the map kept as
    far as it got) and KeyboardInterrupt after a second; the services are stopped on every path."""
    import zenoh

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    # The run's own choices for geometry: checkpoints under OUT, every supervision.checkpoint_period_s,
    # a fresh map (an earlier run's checkpoints are removed), loaded again by a restarted geometry.
    config.geometry.map_dir = out / "checkpoints"
    config.geometry.checkpoint_period_s = config.supervision.checkpoint_period_s
    config.geometry.load_on_start = True
    shutil.rmtree(config.geometry.map_dir / config.map_id, ignore_errors=True)
    # One playback name for the run: a restarted bridge continues it (geometry drops what it holds).
    config.bridge.playback = config.bridge.playback or uuid.uuid4().hex[:16]
    config.bridge.geometry_shards = args.geometry_shards  # playback waits for every shard (docs/SHARDS.md)
    if args.encoder_workers:
        config.use_encoder_pool()
    config_file = write_service_config(config, out / "run-config.json")
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cluster = Cluster(config.map_id, endpoint, out / "logs", config_file=config_file,
                      restart_policy=config.supervision.policy())
    # From here on the first SIGINT/SIGTERM stops playback and keeps the map, a second one kills
    # every service at once; the handlers stay until the services are stopped.
    with StopSignals(on_abort=cluster.kill, aborted="every service was killed, no map was saved") as signals:
        router = open_session(ServiceConfig(map_id=config.map_id, zenoh=ZenohSettings(
            mode="router", listen=[endpoint], multicast_scouting=False)))
        client = None
        page = None  # the query page of --web
        rerun = None
        subscribers: list = []  # rerun viewer feeds, closed before the services stop
        try:
            client = OpenFusionClient.from_config(ServiceConfig(map_id=config.map_id, zenoh=ZenohSettings(
                mode="client", connect=[endpoint], multicast_scouting=False)), timeout_s=30.0)
            if getattr(args, "web", None) is not None:
                page = _start_page(args, client)
            rerun = open_rerun(args.rerun)
            summary = _run_with_services(args, config, cluster, client, rerun, subscribers, signals)
            if page is not None:
                _serve_page_until_stopped(args, page, summary, signals)
        finally:
            if page is not None:
                page.close()
            for sub in subscribers:
                sub.close()
            if rerun is not None:
                rerun.close()
            cluster.stop()
            if client is not None:
                client.close()
            try:
                router.close()
            except zenoh.ZError as exc:
                logger.debug("router close: %s", exc)
    (out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
    return summary


def _run_with_services(args: argparse.Namespace, config: RunConfig, cluster: Cluster, client: Any, rerun: Any,
                       subscribers: list, signals: StopSignals) -> RunSummary:
    out: Path = args.out
    started = time.monotonic()
    if rerun is not None:
        from openfusion.bus import Subscriber
        from openfusion.bus.instance_join import InstanceBuffer

        # Instance images come on their own key just before their frame: shown when there.
        instances = InstanceBuffer()
        subscribers.append(Subscriber(client.session, SENSOR_INSTANCE.key(client.keys), SENSOR_INSTANCE.message,
                                      instances.add, queue_size=8))
        subscribers.append(Subscriber(client.session, SENSOR_RGBD.key(client.keys), SENSOR_RGBD.message,
                                      lambda msg: rerun.log_frame(msg.to_frame(instances.take(msg))),
                                      latest_only=True))
    geometry_names = shard_run.start_geometry(cluster, args.geometry_shards)  # one, or a process per shard
    for name in ("semantic", "query"):
        cluster.start(name)
    # more query services on the same map: Zenoh delivers each request to one of them (services/query/instances.py)
    more_queries = [query_service_name(i) for i in range(2, args.query_services + 1)]
    for i, name in enumerate(more_queries, start=2):
        cluster.start(name, ["--instance", str(i)], service="query", optional=True)
    workers = [f"w{i + 1}" for i in range(args.encoder_workers)]
    for worker_id in workers:  # the encoder pool: workers of this run's private router
        cluster.start(f"encoder-{worker_id}", ["--worker-id", worker_id], service="encoder", optional=True)
    say(args, f"starting services on {cluster.endpoint} (logs in {cluster.log_dir})")
    wait_for_services(client, cluster, {*geometry_names, "semantic", "query", *more_queries,
                                        *(f"encoder-{w}" for w in workers)},
                      SERVICE_START_TIMEOUT_S, should_stop=lambda: signals.requested is not None)
    if signals.requested:
        raise signals.interrupted("stopped before playback started; nothing to save")
    for robot, spec in config.robots.items():  # several robots: one bridge each
        cluster.start(bridge_name(robot), ["--source", spec, "--robot", robot, "--max-frames",
                                           str(config.robot_frames[robot])], service="bridge")
    if not config.robots:
        cluster.start("bridge")
    stats: dict[str, Any] = {}
    carried: dict[str, dict[str, float]] = {}
    map_dir = out / "map"
    saved_to: str | None = None  # where the map went, once saved (run.json's map_saved)

    def summary_now(error: str | None = None) -> RunSummary:
        summary = RunSummary.from_health(
            with_carried(stats, carried), source=config.bridge.source, encoder=config.semantic.encoder, noise=config.semantic.noise,
            semantic_every=config.semantic.every_k, wall_s=time.monotonic() - started,
            frames_requested=sum(config.robot_frames.values()) if config.robots else config.bridge.max_frames,
            interrupted=signals.requested is not None, robot_sources=config.robot_sources(),
            restarts=cluster.restarts, error=error, encoder_workers=args.encoder_workers,
            select=config.semantic.select)
        summary.map_saved = saved_to
        summary.query_services = args.query_services
        summary.geometry_shards = args.geometry_shards
        summary.shards = shard_run.shard_health(stats, args.geometry_shards)
        return summary

    try:
        stats = follow_progress(args, client, cluster, signals, stats, carried)
    except RunError as exc:  # past the restart limit (or a timeout): keep what can be kept, then fail
        # The stats are from the loop's last poll, up to a poll before the death it noticed; the
        # services still alive are asked once more, so the save and run.json see what they hold now.
        refresh_stats(client, stats, carried)
        _save_what_is_left(args, client, cluster, map_dir, summary_now(str(exc)))
        raise
    if signals.requested:
        summary = summary_now()
        if summary.frames_integrated == 0:
            (out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
            raise signals.interrupted("no frame was integrated yet; nothing saved")
    say(args, "saving the map")
    save_and_wait(client, map_dir, say=lambda line: say(args, line),
                  alive=lambda: shard_run.geometry_alive(cluster, args.geometry_shards))
    saved_to = str(map_dir.resolve())
    replies = []
    for text in args.queries:
        if signals.requested:
            break
        reply = client.query_text(text, top_k=args.top_k, with_points=True, max_points=QUERY_MAX_POINTS)
        replies.append((text, reply.embedding_space, reply.regions))
    if signals.requested:  # the map is saved; the example queries and the mesh are skipped
        summary = summary_now()
        (out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
        raise signals.interrupted(f"saved the map of {summary.frames_integrated} integrated frames to {map_dir}")
    mesh = fetch_mesh(client, map_dir, say=lambda line: say(args, line))  # too large for a reply: from OUT/map
    write_query_outputs(out, replies, mesh, say=say_progress(args.quiet))
    if rerun is not None:
        rerun.log_mesh(mesh if not isinstance(mesh, tuple) else surface_mesh(*mesh))
        for text, _space, hits in replies:
            rerun.log_query(text, hits)
    return summary_now()


def _save_what_is_left(args: argparse.Namespace, client: Any, cluster: Cluster, map_dir: Path,
                       summary: RunSummary) -> None:
    """A run that fails after playback started: save the map geometry holds (when it is alive) and
    write ``run.json`` with the error; neither may hide the error itself."""
    if shard_run.geometry_alive(cluster, args.geometry_shards) and summary.frames_integrated > 0:
        try:  # waited for as the end of a run that went well waits (a large map's save outlasts a request)
            save_and_wait(client, map_dir, say=lambda line: say(args, line),
                          alive=lambda: shard_run.geometry_alive(cluster, args.geometry_shards))
            summary.map_saved = str(map_dir.resolve())
            say(args, f"saved the map of {summary.frames_integrated} integrated frames to {map_dir}")
        except Exception as exc:  # noqa: BLE001 - the run's own error is what the user must see
            logger.warning("could not save the map after the run failed: %s", exc)
    try:
        (args.out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
    except OSError as exc:
        logger.warning("could not write run.json: %s", exc)


def _start_page(args: argparse.Namespace, client: Any) -> Any:
    """``--web``: the query page beside the services (127.0.0.1); its URL on stderr, even with --quiet."""
    from openfusion.app.web_cmd import start_query_page

    page = start_query_page(client, port=args.web)
    print(f"query page: {page.url}", file=sys.stderr, flush=True)
    return page


def _serve_page_until_stopped(args: argparse.Namespace, page: Any, summary: RunSummary,
                              signals: StopSignals) -> None:
    """``--web``: after the run, its outputs written, the services and the page stay until Ctrl-C."""
    (args.out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
    print(f"the run is done (outputs in {args.out}); the query page stays at {page.url} until Ctrl-C",
          file=sys.stderr, flush=True)
    while signals.requested is None:
        time.sleep(0.2)


def say(args: argparse.Namespace, text: str) -> None:
    """A line of progress on stderr (none with ``--quiet``)."""
    write = say_progress(args.quiet)
    if write is not None:
        write(text)
