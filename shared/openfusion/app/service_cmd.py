"""``openfusion service NAME``: run one service (bridge, geometry, semantic, query, encoder)."""

from __future__ import annotations

import argparse
import importlib

from openfusion.app.launcher import follow_launcher
from openfusion.errors import UsageError
from openfusion.services.common import ServiceDefinition

SERVICE_NAMES = ("bridge", "geometry", "semantic", "query", "encoder")


def definition(name: str) -> ServiceDefinition:
    """The :class:`ServiceDefinition` of service ``name`` (imports only that service)."""
    if name not in SERVICE_NAMES:
        raise UsageError(f"unknown service {name!r}; known: {', '.join(SERVICE_NAMES)}")
    module = importlib.import_module(f"openfusion.services.{name}.service")
    return module.DEFINITION


class ServiceCommand:
    """Registry entry for ``openfusion service``."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        sub = parser.add_subparsers(dest="service_name", metavar="SERVICE", required=True)
        for name in SERVICE_NAMES:
            defn = definition(name)
            p = sub.add_parser(name, help=defn.help, description=defn.help)
            defn.add_arguments(p)

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        follow_launcher()  # started by `openfusion run`: end with it, however it ends
        return definition(args.service_name).run(args)
