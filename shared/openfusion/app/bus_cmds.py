"""``openfusion router`` and ``openfusion health``: the bus itself and who is alive on it."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading
import time
from types import FrameType
from typing import Any

import numpy as np
import zenoh

from openfusion.bus import collect_health, live_services, open_session
from openfusion.config import add_config_arguments, config_from_args, setup_logging
from openfusion.errors import OpenFusionError, UsageError
from openfusion.wire.counters import GeometryCounter, SemanticCounter, semantic_frame_outcomes
from openfusion.wire.keys import ShardId

logger = logging.getLogger(__name__)


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT/SIGTERM."""
    stop = threading.Event()

    def _handler(signum: int, _frame: FrameType | None) -> None:
        logger.info("got %s, stopping", signal.Signals(signum).name)
        stop.set()

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _handler)
    return stop


class ServicesNotAlive(OpenFusionError):
    """``openfusion health`` found none (or not all required) of the map's services alive."""


class RouterCommand:
    """``openfusion router``: a Zenoh router from Python until SIGINT/SIGTERM. It routes every map,
    always in router mode: ``--mode`` (other than router), ``--map`` and ``--prefix`` are refused."""

    DEFAULT_LISTEN = "tcp/[::]:7447"

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        add_config_arguments(parser)

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        if args.mode not in (None, "router"):
            raise UsageError(f"--mode {args.mode}: openfusion router always runs in router mode")
        given = [flag for attr, flag in (("map_id", "--map"), ("prefix", "--prefix")) if getattr(args, attr) is not None]
        if given:
            raise UsageError(f"{' and '.join(given)}: a router routes every map; give them to the services and clients")
        args.mode = "router"
        config = config_from_args(args)
        if not config.zenoh.listen:
            config.zenoh.listen = [RouterCommand.DEFAULT_LISTEN]
        setup_logging(config.log_level)
        stop = stop_on_signals()
        session = open_session(config)
        try:
            print(f"router {session.zid()} listening on {', '.join(config.zenoh.listen)}", flush=True)
            while not stop.wait(0.2):
                pass
        finally:
            try:
                session.close()
            except zenoh.ZError as exc:
                logger.warning("closing the router session: %s", exc)
        return 0


class HealthCommand:
    """``openfusion health``: live services of a map (liveliness) with their latest stats."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        add_config_arguments(parser)
        parser.add_argument("--timeout", type=float, default=3.0, metavar="S", help="wait up to S seconds (default 3)")
        parser.add_argument("--json", action="store_true", help="print JSON")
        parser.add_argument(
            "--require", action="append", default=[], metavar="SERVICE",
            help="exit 0 only when this service is alive (repeatable; for container health checks)",
        )

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        if args.timeout <= 0:
            raise UsageError(f"--timeout must be positive, got {args.timeout}")
        config = config_from_args(args)
        setup_logging(config.log_level if args.log_level else "WARNING")
        keys = config.keys
        deadline = time.monotonic() + args.timeout
        session = open_session(config)
        try:
            live: list[str] = []
            while True:
                remaining = deadline - time.monotonic()
                live = live_services(session, keys, timeout_s=max(0.1, min(1.0, remaining)))
                satisfied = set(args.require) <= set(live) if args.require else bool(live)
                if satisfied or time.monotonic() >= deadline:
                    break
                time.sleep(0.1)
            stats: dict[str, Any] = {}
            while live:  # stats of every live service, or what came until the deadline
                stats.update(collect_health(session, keys, timeout_s=max(0.5, min(2.0, deadline - time.monotonic()))))
                if set(live) <= set(stats) or time.monotonic() >= deadline:
                    break
        finally:
            session.close()
        if args.json:
            services = [
                {"service": name, "alive": True, "stats": stats[name].model_dump() if name in stats else None}
                for name in live
            ]
            print(json.dumps({"map_id": keys.map_id, "prefix": keys.prefix, "services": services}))
        elif live:
            print(_health_table(live, stats))
            if "semantic" in stats:
                print(semantic_frames_line(stats["semantic"].counters))
            robots = robots_table(stats)
            if robots:
                print()
                print(robots)
            copies = peer_copy_table(stats)
            if copies:
                print()
                print(copies)
        if not live:
            raise ServicesNotAlive(f"no live services on map {keys.map_id!r} (waited {args.timeout:g} s)")
        missing = sorted(set(args.require) - set(live))
        if missing:
            raise ServicesNotAlive(f"required service(s) not alive on map {keys.map_id!r}: {', '.join(missing)}")
        return 0


def _health_table(live: list[str], stats: dict[str, Any]) -> str:
    header = ("service", "pid", "uptime_s", "fps", "latency_ms_p50", "latency_ms_p99", "drops", "errors")
    rows = [header]
    for name in live:
        s = stats.get(name)
        if s is None:
            rows.append((name, "?", "?", "?", "?", "?", "?", "?"))
        else:
            rows.append(
                (name, str(s.pid), f"{s.uptime_s:.1f}", f"{s.fps:.1f}", f"{s.latency_ms_p50:.2f}",
                 f"{s.latency_ms_p99:.2f}", str(s.drops), str(s.errors))
            )
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip() for row in rows)


def semantic_frames_line(counters: dict[str, float]) -> str:
    """What became of the frames the semantic service received: each ends in one outcome."""
    outcomes = semantic_frame_outcomes(counters)
    received = int(counters.get(SemanticCounter.FRAMES_RECEIVED, 0))
    pending = max(0, received - sum(outcomes.values()))
    parts = " + ".join(f"{name} {n}" for name, n in outcomes.items()) or "none"
    return f"semantic frames: received {received} = {parts} + pending {pending}"


def peer_copy_table(stats: dict[str, Any]) -> str:
    """The geometry replicas that copied a peer's checkpoint at start, or served theirs (docs/SHARDS.md,
    "Replicas"); "" when none did."""
    header = ("geometry", "copied", "failed", "tiles", "MB", "up_to_frame", "copy_s", "served", "MB_served")
    rows = [header]
    for name, s in sorted(stats.items()):
        if ShardId.of_service(name) is None:
            continue
        c = {k: s.counter(k) for k in (GeometryCounter.PEER_COPIES, GeometryCounter.PEER_COPY_FAILURES,
                                       GeometryCounter.PEER_SNAPSHOTS_SERVED)}
        if not any(c.values()):
            continue
        copied = c[GeometryCounter.PEER_COPIES] > 0
        rows.append((name, str(int(c[GeometryCounter.PEER_COPIES])), str(int(c[GeometryCounter.PEER_COPY_FAILURES])),
                     str(int(s.counter(GeometryCounter.PEER_COPY_TILES))),
                     f"{s.counter(GeometryCounter.PEER_COPY_BYTES) / 1e6:.1f}",
                     str(int(s.counter(GeometryCounter.PEER_COPY_FRAME_ID))) if copied else "-",
                     f"{s.counter(GeometryCounter.PEER_COPY_S):.2f}" if copied else "-",
                     str(int(c[GeometryCounter.PEER_SNAPSHOTS_SERVED])),
                     f"{s.counter(GeometryCounter.PEER_BYTES_SERVED) / 1e6:.1f}"))
    if len(rows) == 1:
        return ""
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip() for row in rows)


def robots_table(stats: dict[str, Any]) -> str:
    """Each robot's stream as geometry reports it (README "Several robots"); "" when none does."""
    geometry = stats.get("geometry") or next(  # geometry shards (docs/SHARDS.md): each follows every robot
        (s for name, s in sorted(stats.items()) if name.startswith("geometry-") and s.robots), None)
    if geometry is None or not geometry.robots:
        return ""
    header = ("robot", "state", "integrated", "held", "skipped", "queued", "lag_s", "x_m", "y_m", "z_m", "yaw_deg",
              "join")
    rows = [header]
    for name, r in sorted(geometry.robots.items()):
        T = np.asarray(r.T_map_odom, np.float64).reshape(4, 4)
        skipped = ", ".join(f"{reason} {n}" for reason, n in sorted(r.skipped.items())) or "-"
        if r.state == "held":
            join = f"{r.join_attempts} attempt(s)" + (f": {r.join_reason}" if r.join_reason else "")
        else:
            join = r.join_method + (f" (fitness {r.join_fitness:.2f})" if r.join_fitness else "")
            join += f", {r.corrections} correction(s)" if r.corrections else ""
        rows.append((name, r.state, str(r.frames_integrated), str(r.frames_held), skipped, str(r.queued),
                     f"{r.lag_s:.2f}", f"{T[0, 3]:.3f}", f"{T[1, 3]:.3f}", f"{T[2, 3]:.3f}",
                     f"{np.degrees(np.arctan2(T[1, 0], T[0, 0])):.2f}", join))
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip() for row in rows)
