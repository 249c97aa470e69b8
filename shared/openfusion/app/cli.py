"""The ``openfusion`` console script.

Subcommands live in a registry (:data:`SUBCOMMANDS`): each entry names a ``module:attribute``
whose object has ``add_arguments(parser)`` and ``run(args) -> int``. Only the module of the
chosen subcommand is imported (``openfusion version`` does not load torch); a module that fails
to import is an error, never a silently missing command. Add a subcommand with one line::

    Subcommand("run", "openfusion.app.run:RunCommand", "start all services on this machine"),

Errors (``openfusion.errors``): a :class:`~openfusion.errors.UserError` (bad option, value,
config or file) prints one line naming it and exits with code 2, as do argparse's own usage
errors; any other :class:`~openfusion.errors.OpenFusionError` (the bus, a service that refused
or did not answer, a service that died) prints one line and exits with code 1; anything else is a
bug and prints its traceback. ``OPENFUSION_DEBUG=1`` shows the traceback of every error. An error
with ``details`` (a dead service's last log lines) prints them above its one-line error. Ctrl-C
(KeyboardInterrupt) and :class:`~openfusion.errors.Interrupted` (a command that stopped cleanly and
says what it kept) print one line and exit with code 130.
Exit codes: 0 ok, 1 failure, 2 bad usage or configuration, 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import json
import os
import platform
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NoReturn

import openfusion
from openfusion.app.exit_status import keep_exit_status
from openfusion.errors import Interrupted, OpenFusionError, UserError

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class OneLineParser(argparse.ArgumentParser):
    """argparse with usage errors on one line (``openfusion run: error: ... (see --help)``), exit 2."""

    #: The subcommands' parsers by name (set on the top-level parser by :func:`build_parser`).
    subcommand_parsers: dict[str, argparse.ArgumentParser]

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


@dataclass(frozen=True)
class Subcommand:
    """A registry entry: ``target`` is ``"module:attribute"`` of an object with
    ``add_arguments(parser)`` and ``run(args) -> int``."""

    name: str
    target: str
    help: str

    def load(self) -> Any:
        module, _, attribute = self.target.partition(":")
        return getattr(importlib.import_module(module), attribute)


SUBCOMMANDS: list[Subcommand] = [
    Subcommand("version", "openfusion.app.cli:VersionCommand", "print the version of openfusion-z and its bus"),
    Subcommand("router", "openfusion.app.bus_cmds:RouterCommand", "run a Zenoh router (Python session in router mode)"),
    Subcommand("health", "openfusion.app.bus_cmds:HealthCommand", "list the live services of a map and their stats"),
    Subcommand("service", "openfusion.app.service_cmd:ServiceCommand", "run one service (bridge, geometry, semantic, query)"),
    Subcommand("run", "openfusion.app.run:RunCommand", "run everything on this machine: services, synthetic scene, queries"),
    Subcommand("query", "openfusion.app.query_cmd:QueryCommand", "ask a running map (or --map-dir) in plain text"),
    Subcommand("web", "openfusion.app.web_cmd:WebCommand", "serve a query page of a running map in the browser"),
    Subcommand("segment", "openfusion.app.query_cmd:SegmentCommand", "label a saved map's surface points by class names"),
    Subcommand("ros-publish", "openfusion.app.ros_publish_cmd:RosPublishCommand", "publish a running map's answers as ROS 2 topics (RViz, Foxglove)"),
    Subcommand("eval", "openfusion.app.eval_cmd:EvalCommand", "evaluate mapping quality, geometry and speed"),
    Subcommand("render", "openfusion.app.render_cmd:RenderCommand", "headless PNG render of a saved map"),
    Subcommand("export", "openfusion.app.export_cmd:ExportCommand", "export a saved map as PLY/GLB, coloured"),
    Subcommand("config", "openfusion.app.config_cmd:ConfigCommand", "print a service's parameters and their sources"),
]


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


# ------------------------------------------------------------------------------------ main


def _chosen(argv: Sequence[str], names: set[str]) -> str | None:
    for token in argv:
        if not token.startswith("-"):
            return token if token in names else None
    return None


def build_parser(argv: Sequence[str] = ()) -> tuple[argparse.ArgumentParser, dict[str, Any]]:
    """The parser; only the subcommand named in ``argv`` gets its arguments (and module) loaded."""
    parser = OneLineParser(
        prog="openfusion", description="OpenFusion-Z: real-time open-vocabulary 3D mapping over Eclipse Zenoh."
    )
    parser.add_argument("--version", action="version", version=f"openfusion-z {openfusion.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    chosen = _chosen(argv, {c.name for c in SUBCOMMANDS})
    loaded: dict[str, Any] = {}
    parser.subcommand_parsers = {}
    for command in SUBCOMMANDS:
        sp = sub.add_parser(command.name, help=command.help, description=command.help)
        parser.subcommand_parsers[command.name] = sp
        if command.name == chosen:
            loaded[command.name] = command.load()
            loaded[command.name].add_arguments(sp)
    return parser, loaded


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``openfusion`` console script; returns the exit code."""
    keep_exit_status()
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, loaded = build_parser(argv)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # named by the subcommand they were given to: `openfusion run: error: ...`
        parser.subcommand_parsers.get(args.command, parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    try:
        return int(loaded[args.command].run(args) or 0)
    except KeyboardInterrupt as exc:
        print(f"openfusion {args.command}: interrupted" + (f": {exc}" if str(exc) else ""), file=sys.stderr)
        return EXIT_INTERRUPTED
    except Interrupted as exc:  # stopped by the user, cleanly: the message says what was kept
        print(f"openfusion {args.command}: {exc}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OpenFusionError as exc:
        if os.environ.get("OPENFUSION_DEBUG"):
            raise
        details = getattr(exc, "details", "")
        if details:  # e.g. the last lines of a dead service's log, above the one-line error
            print(details, file=sys.stderr)
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"openfusion {args.command}: error: {message}", file=sys.stderr)
        return EXIT_USAGE if isinstance(exc, UserError) else EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
