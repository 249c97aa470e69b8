"""``openfusion run``: the embedded default — every service on this machine, one command.

The command opens a Zenoh session in router mode on a free loopback port (multicast off), starts
geometry, semantic and query as separate processes in peer mode connected to it, waits until they
are alive, then starts the bridge on the chosen source (the built-in synthetic scene by default).
It shows progress from the services' health stats, waits until geometry has integrated every
published frame and semantics has caught up, saves the map to ``OUT/map``, runs example queries,
writes the mesh and query results, writes ``OUT/run.json`` and stops the services (SIGTERM).

``--in-process`` runs the same pipeline in this process (no bus), for notebooks and debugging.

Outputs in ``--out DIR`` (default ``out``): ``map/`` (the saved map), ``mesh.ply``,
``queries.json``, ``query_<i>.ply`` (points of the best region of each query), ``run.json``,
``logs/<service>.log``.

Speed figures in run.json: ``rec_fps`` (3D-Rec) = frames integrated / time the geometry
service spent integrating them; ``sem_rec_fps`` (Sem-3D-Rec) = 1 / (integration time per frame +
semantic step time per semantic frame), i.e. the rate of a pipeline that runs semantics on every
frame, from the same measurements.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from openfusion.app.launcher import Cluster, RunError, wait_for_services
from openfusion.app.outputs import open_rerun, surface_mesh, write_query_outputs
from openfusion.bus import free_loopback_port
from openfusion.config import ServiceConfig, ZenohSettings

logger = logging.getLogger(__name__)

DEFAULT_QUERIES = ("chair", "table", "something to sit on", "a plant", "monitor")
SERVICE_START_TIMEOUT_S = 180.0


def _counter(stats: dict[str, Any], service: str, name: str, default: float = 0.0) -> float:
    s = stats.get(service)
    return float(s.counters.get(name, default)) if s is not None else default


def run_services(args: argparse.Namespace) -> dict[str, Any]:
    """The multi-process embedded run; returns the run summary (also written to run.json)."""
    import zenoh

    from openfusion.bus import open_session
    from openfusion.client import OpenFusionClient

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router_cfg = ServiceConfig(map_id=args.map_id, zenoh=ZenohSettings(mode="router", listen=[endpoint],
                                                                        multicast_scouting=False))
    router = open_session(router_cfg)
    cluster = Cluster(args.map_id, endpoint, out / "logs")
    client_cfg = ServiceConfig(map_id=args.map_id, zenoh=ZenohSettings(mode="client", connect=[endpoint],
                                                                        multicast_scouting=False))
    client = OpenFusionClient.from_config(client_cfg, timeout_s=30.0)
    rerun = open_rerun(args.rerun)
    subscribers: list = []  # rerun viewer feeds, closed before the services stop
    started = time.monotonic()
    try:
        if rerun is not None:
            from openfusion.bus import Subscriber
            from openfusion.bus.instance_join import InstanceBuffer
            from openfusion.wire.schemas import InstanceFrame, RgbdFrame

            # Instance images come on their own key just before their frame: shown when there.
            instances = InstanceBuffer()
            subscribers.append(Subscriber(client.session, client.keys.sensor_instance, InstanceFrame, instances.add,
                                          queue_size=8))
            subscribers.append(Subscriber(client.session, client.keys.sensor_rgbd, RgbdFrame,
                                          lambda msg: rerun.log_frame(msg.to_frame(instances.take(msg))),
                                          latest_only=True))
        cluster.start("geometry", ["--map-dir", str(out / "checkpoints"), "--checkpoint-period-s", "0",
                                   "--set", "geometry.load_on_start=false"])
        semantic_args = ["--encoder", args.encoder, "--semantic-every", str(args.semantic_every)]
        if args.noise:
            semantic_args += ["--noise", args.noise]
        cluster.start("semantic", semantic_args)
        cluster.start("query", ["--text-encoder", args.text_encoder])
        _say(args, f"starting services on {endpoint} (logs in {cluster.log_dir})")
        wait_for_services(client, cluster, {"geometry", "semantic", "query"}, SERVICE_START_TIMEOUT_S)
        bridge_args = ["--source", args.source, "--max-frames", str(args.frames)]
        if args.rate_hz is not None:
            bridge_args += ["--rate-hz", str(args.rate_hz)]
        cluster.start("bridge", bridge_args)
        stats = _follow_progress(args, client, cluster)
        _say(args, "saving the map")
        client.control("save", str((out / "map").resolve()))
        replies = []
        for text in args.queries:
            reply = client.query_text(text, top_k=args.top_k, with_points=True, max_points=50_000)
            replies.append((text, reply.embedding_space, reply.regions))
        mesh = client.mesh()
        write_query_outputs(out, replies, (mesh.vertices, mesh.triangles, mesh.vertex_colors, mesh.vertex_keys),
                            say=None if args.quiet else (lambda t: _say(args, t)))
        if rerun is not None:
            rerun.log_mesh(surface_mesh(mesh.vertices, mesh.triangles, mesh.vertex_colors, mesh.vertex_keys))
            for text, _space, hits in replies:
                rerun.log_query(text, hits)
        summary = _summary(args, stats, time.monotonic() - started)
    finally:
        for sub in subscribers:
            sub.close()
        if rerun is not None:
            rerun.close()
        cluster.stop()
        client.close()
        try:
            router.close()
        except zenoh.ZError as exc:
            logger.debug("router close: %s", exc)
    (out / "run.json").write_text(json.dumps(summary, indent=2))
    return summary


def _follow_progress(args: argparse.Namespace, client: Any, cluster: Cluster) -> dict[str, Any]:
    from tqdm import tqdm

    from openfusion.bus import collect_health

    bar = tqdm(total=args.frames, desc="frames integrated", unit="frame", disable=args.quiet)
    stable_since: float | None = None
    last_key: tuple[float, ...] = ()
    stats: dict[str, Any] = {}
    deadline = time.monotonic() + args.timeout_s
    while True:
        cluster.check_alive()
        stats = collect_health(client.session, client.keys, timeout_s=1.0) or stats
        integrated = _counter(stats, "geometry", "frames_integrated")
        bar.n = int(integrated)
        bar.set_postfix(semantic=int(_counter(stats, "semantic", "semantic_frames")),
                        regions=int(_counter(stats, "semantic", "regions")))
        bar.refresh()
        done = _counter(stats, "bridge", "playback_done") >= 1
        published = _counter(stats, "bridge", "frames_published")
        key = (integrated, _counter(stats, "semantic", "semantic_frames"), _counter(stats, "geometry", "updates_applied"))
        if done and integrated >= published:
            if key == last_key and stable_since is not None and time.monotonic() - stable_since > 2.0:
                break
            if key != last_key:
                stable_since = time.monotonic()
        last_key = key
        if time.monotonic() > deadline:
            bar.close()
            raise RunError(f"the run did not finish within {args.timeout_s:.0f} s "
                           f"(integrated {integrated:.0f} of {published:.0f} published frames)")
        time.sleep(0.5)
    bar.close()
    return stats


def _summary(args: argparse.Namespace, stats: dict[str, Any], wall_s: float) -> dict[str, Any]:
    def c(service: str, name: str) -> float:
        return _counter(stats, service, name)

    integrated = c("geometry", "frames_integrated")
    integrate_s = c("geometry", "integrate_busy_s")
    semantic_frames = c("semantic", "semantic_frames")
    semantic_s = c("semantic", "busy_s")
    per_frame = integrate_s / integrated if integrated else 0.0
    per_sem = semantic_s / semantic_frames if semantic_frames else 0.0
    bridge = stats.get("bridge")
    skipped = {k.removeprefix("skipped_"): int(v) for k, v in (bridge.counters.items() if bridge else [])
               if k.startswith("skipped_")}
    return {
        "source": args.source,
        "encoder": args.encoder,
        "noise": args.noise or "off",
        "semantic_every": args.semantic_every,
        "frames_read": int(c("bridge", "frames_read")),
        "frames_skipped": skipped,
        "frames_published": int(c("bridge", "frames_published")),
        "frames_integrated": int(integrated),
        "semantic_frames": int(semantic_frames),
        "regions": int(c("semantic", "regions")),
        "rec_fps": round(1.0 / per_frame, 2) if per_frame else None,
        "sem_rec_fps": round(1.0 / (per_frame + per_sem), 2) if per_sem else None,
        "wall_s": round(wall_s, 1),
        "map_dir": "map",
    }


def _say(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(text, file=sys.stderr, flush=True)


class RunCommand:
    """Registry entry for ``openfusion run``."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--out", type=Path, default=Path("out"), help="output folder (default ./out)")
        parser.add_argument("--source", default="synthetic", help="frame source spec (default the built-in synthetic "
                            "scene); scannet:PATH, replica:PATH, tum:PATH, redwood:PATH, folder:PATH, replay:FILE")
        parser.add_argument("--encoder", default="gt", help="region encoder: gt (default), onnx, clip-regions")
        parser.add_argument("--text-encoder", default="minilm", help="text encoder of the map's space (default minilm)")
        parser.add_argument("--frames", type=int, default=120, help="frames to play (default 120)")
        parser.add_argument("--semantic-every", type=int, default=1, help="semantics on every k-th frame (0 = off)")
        parser.add_argument("--noise", default=None, help="gt encoder noise profile: off, standard, heavy")
        parser.add_argument("--rate-hz", type=float, default=None,
                            help="playback rate (default the frames' timestamps; 0 = as fast as possible)")
        parser.add_argument("--map", dest="map_id", default="demo", help="map id (default demo)")
        parser.add_argument("--query", dest="queries", action="append", default=None,
                            help="example query (repeatable; default a few furniture queries)")
        parser.add_argument("--top-k", type=int, default=3, help="regions per query (default 3)")
        parser.add_argument("--timeout-s", type=float, default=900.0, help="give up after this many seconds")
        parser.add_argument("--in-process", action="store_true", help="run the pipeline in this process (no bus)")
        parser.add_argument("--rerun", metavar="SINK", default=None,
                            help="log frames, trajectory, mesh and query results to rerun: save:FILE.rrd | spawn | "
                            "serve (needs the viz extra)")
        parser.add_argument("--quiet", action="store_true", help="no progress output")

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        from openfusion.errors import UsageError
        from openfusion.wire.keys import validate_map_id

        try:
            validate_map_id(args.map_id)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        if args.frames <= 0:
            raise UsageError(f"--frames must be positive, got {args.frames}")
        if args.semantic_every < 0:
            raise UsageError(f"--semantic-every must be >= 0, got {args.semantic_every}")
        args.queries = args.queries or list(DEFAULT_QUERIES)
        if args.source == "synthetic":
            # The built-in scene: one lap of the room in the frames played, so the map covers it.
            args.source = f"synthetic:lap={args.frames}"
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        if args.in_process:
            from openfusion.app.run_in_process import run_in_process

            summary = run_in_process(args)
        else:
            summary = run_services(args)
        print(json.dumps(summary, indent=2))
        _say(args, f"outputs in {args.out.resolve()}")
        return 0
