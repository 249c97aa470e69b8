"""The ``openfusion`` console script.

Subcommands live in a registry (:data:`SUBCOMMANDS`): each entry names a ``module:attribute``
whose object has ``add_arguments(parser)`` and ``run(args) -> int``. Only the module of the
chosen subcommand is imported (``openfusion version`` does not load torch); an entry whose
module does not exist (yet) is left out. Add a subcommand with one line::

    Subcommand("run", "openfusion.app.run:RunCommand", "start all services on this machine"),

Errors a user can cause (bad options or config, nothing answering, a port in use) end with
one line on stderr and a non-zero exit code, no traceback (set ``OPENFUSION_DEBUG=1`` to get
one). Exit codes: 0 ok, 1 failure, 2 bad usage or configuration, 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import importlib.util
import json
import logging
import os
import platform
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from types import FrameType
from typing import Any

import openfusion
from openfusion.config import ConfigError, add_config_arguments, config_from_args, setup_logging

logger = logging.getLogger(__name__)


class CliError(Exception):
    """A user-facing failure: printed as one line, exit with ``exit_code``."""

    def __init__(self, message: str, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code


@dataclass(frozen=True)
class Subcommand:
    """A registry entry: ``target`` is ``"module:attribute"`` of an object with
    ``add_arguments(parser)`` and ``run(args) -> int``."""

    name: str
    target: str
    help: str

    @property
    def module(self) -> str:
        return self.target.partition(":")[0]

    def available(self) -> bool:
        try:
            return importlib.util.find_spec(self.module) is not None
        except ModuleNotFoundError:
            return False

    def load(self) -> Any:
        module = importlib.import_module(self.module)
        return getattr(module, self.target.partition(":")[2])


SUBCOMMANDS: list[Subcommand] = [
    Subcommand("version", "openfusion.app.cli:VersionCommand", "print the version of openfusion-z and its bus"),
    Subcommand("router", "openfusion.app.cli:RouterCommand", "run a Zenoh router (Python session in router mode)"),
    Subcommand("health", "openfusion.app.cli:HealthCommand", "list the live services of a map and their stats"),
    Subcommand("service", "openfusion.app.service_cmd:ServiceCommand", "run one service (bridge, geometry, semantic, query)"),
    Subcommand("run", "openfusion.app.run:RunCommand", "run everything on this machine: services, synthetic scene, queries"),
    Subcommand("query", "openfusion.app.query_cmd:QueryCommand", "ask a running map (or --map-dir) in plain text"),
    Subcommand("segment", "openfusion.app.query_cmd:SegmentCommand", "label a saved map's surface points by class names"),
    Subcommand("eval", "openfusion.app.eval_cmd:EvalCommand", "evaluate mapping quality, geometry and speed"),
    Subcommand("render", "openfusion.app.render_cmd:RenderCommand", "headless PNG render of a saved map"),
    Subcommand("export", "openfusion.app.export_cmd:ExportCommand", "export a saved map as PLY/GLB, coloured"),
    # Later subcommands register here (their modules are imported only when chosen).
]


def _stop_on_signals() -> threading.Event:
    """An event set by SIGINT/SIGTERM."""
    stop = threading.Event()

    def _handler(signum: int, _frame: FrameType | None) -> None:
        logger.info("got %s, stopping", signal.Signals(signum).name)
        stop.set()

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _handler)
    return stop


# ----------------------------------------------------------------------------- subcommands


class VersionCommand:
    """``openfusion version``: package, Zenoh and Python versions."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--json", action="store_true", help="print JSON")

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        try:
            zenoh_version = importlib.metadata.version("eclipse-zenoh")
        except importlib.metadata.PackageNotFoundError:
            zenoh_version = "not installed"
        info = {"openfusion-z": openfusion.__version__, "eclipse-zenoh": zenoh_version, "python": platform.python_version()}
        if args.json:
            print(json.dumps(info))
        else:
            print(f"openfusion-z {info['openfusion-z']} (eclipse-zenoh {zenoh_version}, python {info['python']})")
        return 0


class RouterCommand:
    """``openfusion router``: a Zenoh router from Python until SIGINT/SIGTERM."""

    DEFAULT_LISTEN = "tcp/[::]:7447"

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        add_config_arguments(parser)

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        import zenoh

        from openfusion.bus import open_session

        args.mode = "router"
        config = config_from_args(args)
        if not config.zenoh.listen:
            config.zenoh.listen = [RouterCommand.DEFAULT_LISTEN]
        setup_logging(config.log_level)
        stop = _stop_on_signals()
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
        from openfusion.bus import collect_health, live_services, open_session

        if args.timeout <= 0:
            raise CliError(f"--timeout must be positive, got {args.timeout}", 2)
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
            stats = collect_health(session, keys, timeout_s=max(0.5, deadline - time.monotonic())) if live else {}
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
        if not live:
            raise CliError(f"no live services on map {keys.map_id!r} (waited {args.timeout:g} s)")
        missing = sorted(set(args.require) - set(live))
        if missing:
            raise CliError(f"required service(s) not alive on map {keys.map_id!r}: {', '.join(missing)}")
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


# ------------------------------------------------------------------------------------ main


def _chosen(argv: Sequence[str], names: set[str]) -> str | None:
    for token in argv:
        if not token.startswith("-"):
            return token if token in names else None
    return None


def build_parser(argv: Sequence[str] = ()) -> tuple[argparse.ArgumentParser, dict[str, Any]]:
    """The parser; only the subcommand named in ``argv`` gets its arguments (and module) loaded."""
    parser = argparse.ArgumentParser(
        prog="openfusion", description="OpenFusion-Z: real-time open-vocabulary 3D mapping over Eclipse Zenoh."
    )
    parser.add_argument("--version", action="version", version=f"openfusion-z {openfusion.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    available = [c for c in SUBCOMMANDS if c.available()]
    chosen = _chosen(argv, {c.name for c in available})
    loaded: dict[str, Any] = {}
    for command in available:
        sp = sub.add_parser(command.name, help=command.help, description=command.help)
        if command.name == chosen:
            loaded[command.name] = command.load()
            loaded[command.name].add_arguments(sp)
    return parser, loaded


def _user_errors() -> tuple[type[BaseException], ...]:
    import zenoh

    from openfusion.bus import BusError, QueryError
    from openfusion.wire.codec import DecodeError

    # ValueError / OSError: the library's way of refusing bad input (an unknown source spec, a
    # missing file, a port in use); shown as one line, with OPENFUSION_DEBUG=1 for the traceback.
    return (CliError, ConfigError, BusError, QueryError, DecodeError, zenoh.ZError, ValueError, OSError)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``openfusion`` console script; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, loaded = build_parser(argv)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(loaded[args.command].run(args) or 0)
    except KeyboardInterrupt:
        print("openfusion: interrupted", file=sys.stderr)
        return 130
    except _user_errors() as exc:
        if os.environ.get("OPENFUSION_DEBUG"):
            raise
        code = exc.exit_code if isinstance(exc, CliError) else 2 if isinstance(exc, ConfigError) else 1
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if not isinstance(exc, _user_errors()[:6]):  # a generic ValueError/OSError: say how to see more
            message += " (OPENFUSION_DEBUG=1 shows the traceback)"
        print(f"openfusion {args.command}: error: {message}", file=sys.stderr)
        return code


if __name__ == "__main__":
    # Run the imported module, not this __main__ copy, so exception classes such as CliError are
    # the ones subcommand modules import from openfusion.app.cli.
    from openfusion.app.cli import main as _main

    sys.exit(_main())
