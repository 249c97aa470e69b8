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
(:func:`progress_counts`).

Settings: one :class:`~openfusion.app.run_config.RunConfig` (every service's section), validated
before anything starts, written to ``OUT/run-config.json`` and read by every service.

Outputs in ``--out DIR`` (default ``out``): ``map/`` (the saved map), ``mesh.ply``,
``queries.json``, ``query_<i>.ply`` (points of the best region of each query), ``run.json``
(:class:`~openfusion.app.summary.RunSummary`), ``run-config.json``, ``logs/<service>.log``.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from openfusion.app.end_of_run import fetch_mesh, save_and_wait
from openfusion.app.launcher import Cluster, RunError, StopSignals, wait_for_services
from openfusion.app.outputs import open_rerun, say_progress, surface_mesh, write_query_outputs
from openfusion.app.run_config import RUN_FLAGS, SECTION_MODELS, RunConfig, write_service_config
from openfusion.app.summary import RunSummary
from openfusion.bus import collect_health, free_loopback_port, open_session
from openfusion.client import OpenFusionClient
from openfusion.config import ServiceConfig, ZenohSettings, add_section_options, config_from_args
from openfusion.errors import UsageError
from openfusion.services.bridge.service import BridgeSection, bridge_name
from openfusion.services.query.instances import query_service_name
from openfusion.sources.registry import check_source_spec, describe_source, parse_key_values
from openfusion.sources.synthetic_spec import split_world
from openfusion.wire.counters import BridgeCounter, CommonCounter, GeometryCounter, SemanticCounter
from openfusion.wire.endpoints import SENSOR_INSTANCE, SENSOR_RGBD
from openfusion.wire.keys import validate_map_id
from openfusion.wire.limits import LimitError, check_text, check_top_k
from openfusion.wire.schemas.base import check_robot_name

logger = logging.getLogger(__name__)

DEFAULT_QUERIES = ("chair", "table", "something to sit on", "a plant", "monitor")
#: Points returned with each example query's regions.
QUERY_MAX_POINTS = 50_000
SERVICE_START_TIMEOUT_S = 180.0
#: Frames of one lap of the built-in room in ``openfusion run`` (the default ``--frames``, so the
#: default run goes once round the room); longer runs walk the lap again.
BUILTIN_LAP_FRAMES = 120
#: geometry and semantic have settled when their counters did not change for this long.
SETTLE_S = 2.0


def _counter(stats: dict[str, Any], service: str, name: str) -> float:
    s = stats.get(service)
    return s.counter(name) if s is not None else 0.0


def builtin_scene_spec(spec: str, frames: int | None) -> str:
    """The source spec that plays ``frames`` frames (None: the default) of the built-in world: a
    room spec gets ``frames=N`` (default :data:`BUILTIN_LAP_FRAMES`) and ``lap=BUILTIN_LAP_FRAMES``
    unless it sets them; a building spec gets ``frames=N`` only when N is given (its walk has its
    own frame count); any other spec is unchanged."""
    scheme, _sep, rest = spec.strip().partition(":")
    if scheme.lower() != "synthetic":
        return spec
    world, rest = split_world(rest)
    options = parse_key_values(rest, scheme="synthetic")
    if world == "building":
        if frames is not None:
            options.setdefault("frames", str(frames))
        return "synthetic:" + ",".join(["building", *(f"{k}={v}" for k, v in options.items())])
    options.setdefault("frames", str(frames if frames is not None else BUILTIN_LAP_FRAMES))
    options.setdefault("lap", str(BUILTIN_LAP_FRAMES))
    return "synthetic:" + ",".join(f"{k}={v}" for k, v in options.items())


def frames_to_play(spec: str, frames: int | None) -> int:
    """``--frames``, or without it: the walk's frame count for a building spec (opened here: the
    plan and the walk, no rendering), else :data:`BUILTIN_LAP_FRAMES`."""
    if frames is not None:
        return frames
    scheme, _sep, rest = spec.strip().partition(":")
    if scheme.lower() == "synthetic" and split_world(rest)[0] == "building":
        from openfusion.sources.registry import open_source

        return len(open_source(spec))
    return BUILTIN_LAP_FRAMES


def shortfall_note(summary: RunSummary) -> str | None:
    """``played 300 of 2000 frames: the source has 300`` when a finished run played fewer frames
    than asked for, else None."""
    wanted, played = summary.frames_requested, summary.frames_played
    if summary.interrupted or wanted is None or played is None or played >= wanted:
        return None
    note = f"played {played} of {wanted} frames: the source has {played}"
    skipped = sum(summary.frames_skipped.values())
    if skipped:
        reasons = ", ".join(f"{reason} {n}" for reason, n in sorted(summary.frames_skipped.items()))
        note += f" usable frames ({skipped} skipped: {reasons})"
    return note


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
    for name in ("geometry", "semantic", "query"):
        cluster.start(name)
    # more query services on the same map: Zenoh delivers each request to one of them (services/query/instances.py)
    more_queries = [query_service_name(i) for i in range(2, args.query_services + 1)]
    for i, name in enumerate(more_queries, start=2):
        cluster.start(name, ["--instance", str(i)], service="query", optional=True)
    workers = [f"w{i + 1}" for i in range(args.encoder_workers)]
    for worker_id in workers:  # the encoder pool: workers of this run's private router
        cluster.start(f"encoder-{worker_id}", ["--worker-id", worker_id], service="encoder", optional=True)
    _say(args, f"starting services on {cluster.endpoint} (logs in {cluster.log_dir})")
    wait_for_services(client, cluster, {"geometry", "semantic", "query", *more_queries,
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
            _with_carried(stats, carried), source=config.bridge.source, encoder=config.semantic.encoder, noise=config.semantic.noise,
            semantic_every=config.semantic.every_k, wall_s=time.monotonic() - started,
            frames_requested=sum(config.robot_frames.values()) if config.robots else config.bridge.max_frames,
            interrupted=signals.requested is not None, robot_sources=config.robot_sources(),
            restarts=cluster.restarts, error=error, encoder_workers=args.encoder_workers,
            select=config.semantic.select)
        summary.map_saved = saved_to
        summary.query_services = args.query_services
        return summary

    try:
        stats = _follow_progress(args, client, cluster, signals, stats, carried)
    except RunError as exc:  # past the restart limit (or a timeout): keep what can be kept, then fail
        # The stats are from the loop's last poll, up to a poll before the death it noticed; the
        # services still alive are asked once more, so the save and run.json see what they hold now.
        _refresh_stats(client, stats, carried)
        _save_what_is_left(args, client, cluster, map_dir, summary_now(str(exc)))
        raise
    if signals.requested:
        summary = summary_now()
        if summary.frames_integrated == 0:
            (out / "run.json").write_text(summary.model_dump_json(indent=2) + "\n")
            raise signals.interrupted("no frame was integrated yet; nothing saved")
    _say(args, "saving the map")
    geometry = cluster.processes.get("geometry")
    save_and_wait(client, map_dir, say=lambda line: _say(args, line),
                  alive=lambda: geometry is not None and geometry.alive())
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
    mesh = fetch_mesh(client, map_dir, say=lambda line: _say(args, line))  # too large for a reply: from OUT/map
    write_query_outputs(out, replies, mesh, say=say_progress(args.quiet))
    if rerun is not None:
        rerun.log_mesh(mesh if not isinstance(mesh, tuple) else surface_mesh(*mesh))
        for text, _space, hits in replies:
            rerun.log_query(text, hits)
    return summary_now()


def _refresh_stats(client: Any, stats: dict[str, Any], carried: dict[str, dict[str, float]]) -> None:
    """One more health poll into ``stats`` (a service that does not answer keeps its last stats)."""
    import zenoh

    try:
        fresh = collect_health(client.session, client.keys, timeout_s=1.0)
    except zenoh.ZError as exc:
        logger.warning("could not ask the services for their last stats: %s", exc)
        return
    _carry_over(stats, fresh, carried)
    stats.update(fresh)


def _save_what_is_left(args: argparse.Namespace, client: Any, cluster: Cluster, map_dir: Path,
                       summary: RunSummary) -> None:
    """A run that fails after playback started: save the map geometry holds (when it is alive) and
    write ``run.json`` with the error; neither may hide the error itself."""
    geometry = cluster.processes.get("geometry")
    if geometry is not None and geometry.alive() and summary.frames_integrated > 0:
        try:  # waited for as the end of a run that went well waits (a large map's save outlasts a request)
            save_and_wait(client, map_dir, say=lambda line: _say(args, line), alive=geometry.alive)
            summary.map_saved = str(map_dir.resolve())
            _say(args, f"saved the map of {summary.frames_integrated} integrated frames to {map_dir}")
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


#: Counters of a service that add up over its restarts in run.json (a restarted process counts from 0).
CARRIED_COUNTERS: dict[str, tuple[str, ...]] = {
    "semantic": (SemanticCounter.SEMANTIC_FRAMES, SemanticCounter.BUSY_S, SemanticCounter.FRAMES_FAILED),
}


def _carry_over(stats: dict[str, Any], fresh: dict[str, Any], carried: dict[str, dict[str, float]]) -> None:
    """Before ``fresh`` stats replace ``stats``: a service whose ``restarts`` went up leaves its
    last counts of :data:`CARRIED_COUNTERS` in ``carried`` (geometry restores its own from its
    checkpoint)."""
    for name, counters in CARRIED_COUNTERS.items():
        old, new = stats.get(name), fresh.get(name)
        if old is None or new is None or new.counter(CommonCounter.RESTARTS) <= old.counter(CommonCounter.RESTARTS):
            continue
        into = carried.setdefault(name, {})
        for counter in counters:
            into[counter] = into.get(counter, 0.0) + old.counter(counter)


def progress_counts(stats: dict[str, Any]) -> dict[str, int]:
    """The progress line's semantic counts, from the stats run.json is made of (with the counts of
    earlier processes of a restarted service added: :func:`_with_carried`), so the line ends on
    the ``semantic_frames`` that run.json says."""
    return {"semantic": int(_counter(stats, "semantic", SemanticCounter.SEMANTIC_FRAMES)),
            "regions": int(_counter(stats, "semantic", SemanticCounter.REGIONS))}


def _with_carried(stats: dict[str, Any], carried: dict[str, dict[str, float]]) -> dict[str, Any]:
    """``stats`` with the counts of earlier processes of a restarted service added."""
    out = dict(stats)
    for name, extra in carried.items():
        if name in out:
            counters = dict(out[name].counters)
            for counter, value in extra.items():
                counters[counter] = counters.get(counter, 0.0) + value
            out[name] = out[name].model_copy(update={"counters": counters})
    return out


def _current(stats: dict[str, Any], cluster: Cluster) -> bool:
    """Every service is running and the stats held for it come from its current process (its
    ``restarts`` counter matches the launcher's count): a dead or restarted service's last stats
    must not make the run look finished."""
    if cluster.restarting:
        return False
    for name, sp in cluster.processes.items():
        if sp.stopped:
            continue
        s = stats.get(name)
        if not sp.alive() or s is None or int(s.counter(CommonCounter.RESTARTS)) != sp.restarts:
            return False
    return True


def _follow_progress(args: argparse.Namespace, client: Any, cluster: Cluster,
                     signals: StopSignals | None = None, stats: dict[str, Any] | None = None,
                     carried: dict[str, dict[str, float]] | None = None) -> dict[str, Any]:
    """Show progress until geometry has taken every frame the bridge published and geometry and
    semantic have settled (no counter changed for :data:`SETTLE_S`); the last stats of each service
    (also kept in ``stats``, so a caller has them when this raises).

    Services that die are restarted (:meth:`Cluster.check_alive` with the run's restart policy);
    the run is not finished while one is down or its stats are from before its restart.
    After a stop signal (``signals.requested``) the bridge is stopped (no more frames) and the same
    wait lets geometry and semantic finish the frames they already have; the bridge's last stats
    are kept."""
    from tqdm import tqdm

    bar = tqdm(total=args.frames, desc="frames integrated", unit="frame", disable=args.quiet)
    try:
        stable_since: float | None = None
        last_key: tuple[float, ...] = ()
        stats = {} if stats is None else stats
        playback_stopped = False
        deadline = time.monotonic() + args.timeout_s
        while True:
            if signals is not None and signals.requested and not playback_stopped:
                if not args.quiet:
                    bar.write(f"{signals.requested}: stopping playback; finishing the frames in flight, then saving the "
                              "map (press Ctrl-C again to abort)", file=sys.stderr)
                for name in bridge_names(cluster):
                    cluster.stop(name)
                playback_stopped = True
                stable_since = None
            cluster.check_alive()
            fresh = collect_health(client.session, client.keys, timeout_s=1.0)
            carried = {} if carried is None else carried
            _carry_over(stats, fresh, carried)
            stats.update(fresh)
            integrated = _counter(stats, "geometry", GeometryCounter.FRAMES_INTEGRATED)
            refused = (_counter(stats, "geometry", GeometryCounter.CAPACITY_REFUSED)
                       + _counter(stats, "geometry", GeometryCounter.FRAMES_FAILED))
            bar.n = int(integrated)
            bar.set_postfix(**progress_counts(_with_carried(stats, carried)))
            bar.refresh()
            bridges = bridge_names(cluster)
            done = playback_stopped or all(_counter(stats, b, BridgeCounter.PLAYBACK_DONE) >= 1 for b in bridges)
            published = sum(_counter(stats, b, BridgeCounter.FRAMES_PUBLISHED) for b in bridges)
            # Frames of robots not joined yet wait in their submaps: taken, not integrated (yet).
            refused += _held_now(stats)
            key = (integrated, refused, _counter(stats, "semantic", SemanticCounter.SEMANTIC_FRAMES),
                   _counter(stats, "geometry", GeometryCounter.UPDATES_APPLIED), *cluster.restarts.values())
            if done and _joins_pending(stats):  # a held robot may still join: its frames would go in
                stable_since = None
            elif done and integrated + refused >= published and _current(stats, cluster):
                if key == last_key and stable_since is not None and time.monotonic() - stable_since > SETTLE_S:
                    break
                if key != last_key or stable_since is None:
                    stable_since = time.monotonic()
            last_key = key
            if time.monotonic() > deadline:
                raise RunError(f"the run did not finish within {args.timeout_s:.0f} s "
                               f"(integrated {integrated:.0f} of {published:.0f} published frames)")
            time.sleep(0.5)
    finally:  # the bar ends its line whatever ends the wait (an error, a second Ctrl-C)
        bar.close()
    return stats


def bridge_names(cluster: Cluster) -> list[str]:
    """The run's bridges (one per robot: ``bridge``, ``bridge-ROBOT``)."""
    return [name for name in cluster.processes if name == "bridge" or name.startswith("bridge-")] or ["bridge"]


def _held_now(stats: dict[str, Any]) -> float:
    """Frames of held robots waiting in geometry's holds now (taken, not in the map yet)."""
    geometry = stats.get("geometry")
    return float(sum(r.frames_held for r in geometry.robots.values())) if geometry is not None else 0.0


def _joins_pending(stats: dict[str, Any]) -> bool:
    """A held robot's registration runs or is due in geometry."""
    geometry = stats.get("geometry")
    return geometry is not None and any(r.join_pending for r in geometry.robots.values())


def split_robot_name(spec: str) -> tuple[str, str | None]:
    """A ``--source`` spec and the robot name its ``name=ROBOT`` option gives (the option removed;
    None without one): ``synthetic:building,route=0-3,name=alpha`` -> (``synthetic:building,route=0-3``,
    ``alpha``)."""
    scheme, colon, rest = spec.partition(":")
    items = rest.split(",") if colon else spec.split(",")[1:]
    head = scheme if colon else spec.split(",")[0]
    names = [item.strip()[len("name="):] for item in items if item.strip().startswith("name=")]
    if len(names) > 1:
        raise UsageError(f"--source {spec!r}: name= is given {len(names)} times")
    kept = ",".join(item for item in items if not item.strip().startswith("name="))
    return (f"{head}:{kept}" if kept else head), (names[0] if names else None)


def robot_sources(specs: Sequence[str], *, default_robot: str) -> dict[str, str]:
    """Robot name -> source spec of the ``--source`` options: ``name=`` names a robot, the others are
    ``robot0``, ``robot1``, ... by position (the first one, unnamed, is ``default_robot``)."""
    robots: dict[str, str] = {}
    for i, spec in enumerate(specs):
        plain, name = split_robot_name(spec)
        name = name if name is not None else (default_robot if i == 0 else f"robot{i}")
        try:
            check_robot_name(name)
        except ValueError as exc:
            raise UsageError(f"--source {spec!r}: {exc}") from None
        if name in robots:
            raise UsageError(f"--source {spec!r}: robot {name!r} has a source already (one bridge per robot; "
                             "name= names them)")
        robots[name] = plain
    return robots


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


def _say(args: argparse.Namespace, text: str) -> None:
    say = say_progress(args.quiet)
    if say is not None:
        say(text)


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
            _say(args, described)
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
        _say(args, f"outputs in {args.out.resolve()}")
        return 0
