"""``openfusion config --show SERVICE``: every effective parameter of a service and where its
value came from (default, a config file, an ``OPENFUSION_*`` variable, an option or ``--set``)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from openfusion.app.service_cmd import SERVICE_NAMES, definition
from openfusion.config import explain_config

SHOWABLE = (*SERVICE_NAMES, "run")


def _model(name: str) -> Any:
    if name == "run":
        from openfusion.app.run_config import RunConfig

        return RunConfig
    return definition(name).config_model


class ConfigCommand:
    """Registry entry for ``openfusion config``."""

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--show", required=True, choices=SHOWABLE, metavar="SERVICE",
                            help=f"the service whose parameters to print: {', '.join(SHOWABLE)} (run: every section)")
        parser.add_argument("--config", metavar="FILE", help="a config file, as the service would read it")
        parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                            help="an override, as the service would take it (repeatable)")
        parser.add_argument("--json", action="store_true", help="print JSON")

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        _, rows = explain_config(_model(args.show), config_file=args.config, overrides=args.overrides)
        if args.json:
            print(json.dumps([{"name": n, "value": v, "source": s} for n, v, s in rows], default=str, indent=2))
            return 0
        width = max(len(n) for n, _, _ in rows)
        for name, value, source in rows:
            shown = json.dumps(value, default=str)
            print(f"{name.ljust(width)}  {shown}  ({source})")
        return 0
