"""What every service shell shares: the ``openfusion service NAME`` plumbing from command line
and config to :func:`openfusion.bus.run_service`.

A service module defines a :class:`ServiceDefinition`: its name, its config model (a
:class:`~openfusion.config.ServiceConfig` subclass with its own typed section), the service's own
command-line flags and how they map onto that section, and a factory that builds the service
object (plain library code; ``setup(runner)`` declares its entities, ``loop(runner)`` optionally
runs until ``runner.stopping``, ``close()`` releases what it holds).
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from openfusion.bus import ServiceRunner, run_service
from openfusion.config import ServiceConfig, add_config_arguments, cli_values, load_config, setup_logging

logger = logging.getLogger(__name__)


class ServiceApp(Protocol):
    def setup(self, runner: ServiceRunner) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class ServiceDefinition:
    """How to build and run one service from its command line."""

    name: str
    help: str
    config_model: type[ServiceConfig]
    add_options: Callable[[argparse.ArgumentParser], None]
    options_to_config: Callable[[argparse.Namespace], dict[str, Any]]
    build: Callable[[Any], ServiceApp]

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        add_config_arguments(parser)
        self.add_options(parser)

    def config_from_args(self, args: argparse.Namespace) -> Any:
        cli = cli_values(args)
        for section, values in self.options_to_config(args).items():
            given = {k: v for k, v in values.items() if v is not None}
            if given:
                cli.setdefault(section, {}).update(given)
        return load_config(
            self.config_model,
            config_file=getattr(args, "config", None),
            cli=cli,
            overrides=getattr(args, "overrides", None) or (),
        )

    def run(self, args: argparse.Namespace) -> int:
        config = self.config_from_args(args)
        setup_logging(config.log_level)
        app = self.build(config)
        loop = getattr(app, "loop", None)
        try:
            return run_service(config, self.name, app.setup, loop=loop)
        finally:
            app.close()
