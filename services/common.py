"""What every service shell shares: the ``openfusion service NAME`` plumbing from command line
and config to :func:`openfusion.bus.run_service`.

A service module defines a :class:`ServiceDefinition`: its name, its config model (a
:class:`~openfusion.config.ServiceConfig` subclass with one typed section named after the
service) and a factory that builds the service object (plain library code; ``setup(runner)``
declares its entities, ``loop(runner)`` optionally runs until ``runner.stopping``, ``close()``
releases what it holds). The service's flags are derived from its section's fields
(:func:`openfusion.config.add_section_options`), so a parameter is declared once, in the section.

A supervisor that restarts a service (``openfusion run``'s launcher) sets :data:`RESTARTS_ENV` to
the number of restarts so far; the service publishes it as its ``restarts`` health counter
(:attr:`~openfusion.wire.counters.CommonCounter.RESTARTS`; 0 when unset), so ``openfusion health``
and ``run.json`` show it.
"""

from __future__ import annotations

import argparse
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from openfusion.bus import ServiceRunner, run_service
from openfusion.config import (
    ServiceConfig,
    add_config_arguments,
    add_section_options,
    config_from_args,
    setup_logging,
)
from openfusion.wire.counters import CommonCounter

logger = logging.getLogger(__name__)

#: The restart count a supervisor gives a restarted service (published as the ``restarts`` counter).
RESTARTS_ENV = "OPENFUSION_RESTARTS"


def restarts_from_env() -> int:
    """The service's restart count from :data:`RESTARTS_ENV` (0 when unset or not a count)."""
    text = os.environ.get(RESTARTS_ENV, "0").strip()
    return int(text) if text.isdigit() else 0


class ServiceApp(Protocol):
    def setup(self, runner: ServiceRunner) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class ServiceDefinition:
    """How to build and run one service from its command line."""

    name: str
    help: str
    config_model: type[ServiceConfig]
    build: Callable[[Any], ServiceApp]
    #: the name its health and liveliness use, when several instances share a map (encoder workers)
    instance_name: Callable[[Any], str] | None = None

    @property
    def section_model(self) -> Any:
        """The model of the service's own config section (the field named after the service)."""
        return self.config_model.model_fields[self.name].annotation

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        add_config_arguments(parser)
        add_section_options(parser, self.section_model, self.name)

    def config_from_args(self, args: argparse.Namespace) -> Any:
        return config_from_args(args, self.config_model, sections=[self.name])

    def run(self, args: argparse.Namespace) -> int:
        config = self.config_from_args(args)
        setup_logging(config.log_level)
        app = self.build(config)
        loop = getattr(app, "loop", None)
        restarts = restarts_from_env()

        def setup(runner: ServiceRunner) -> None:
            runner.stats.set(CommonCounter.RESTARTS, restarts)
            app.setup(runner)

        try:
            name = self.instance_name(config) if self.instance_name is not None else self.name
            return run_service(config, name, setup, loop=loop)
        finally:
            app.close()
