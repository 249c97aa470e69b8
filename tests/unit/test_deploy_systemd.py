"""deploy/systemd/openfusion-geometry.service: a real unit (no systemd runs here, so it is checked as
data): restarted on failure after a pause, not restarted for a refused config (exit 2), its
settings from an environment file that exists in the repository, and an ExecStart the real
`openfusion` argument parser accepts once the file's variables are filled in.

Bad input guarded: a unit that is never restarted, restarts in a tight loop, an option the CLI
does not have, a variable the environment file does not set."""

from __future__ import annotations

import configparser
import re
import shlex
from pathlib import Path

import pytest

from openfusion.app.cli import build_parser
from openfusion.app.launcher import USAGE_EXIT_CODE

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
UNIT = ROOT / "deploy" / "systemd" / "openfusion-geometry.service"
ENV_FILE = ROOT / "deploy" / "systemd" / "geometry.env"

pytestmark = pytest.mark.timeout(60)


def _unit() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(interpolation=None, strict=True)
    parser.optionxform = str  # systemd keys are case-sensitive
    parser.read_string(UNIT.read_text())
    return parser


def _env() -> dict[str, str]:
    pairs = [line.split("=", 1) for line in ENV_FILE.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return {k.strip(): v.strip() for k, v in pairs}


def test_the_unit_restarts_the_service_on_failure_with_a_pause_and_a_limit() -> None:
    unit = _unit()
    service = unit["Service"]
    assert service["Restart"] == "on-failure"
    assert float(service["RestartSec"]) >= 1
    assert service["RestartPreventExitStatus"] == str(USAGE_EXIT_CODE)
    assert int(unit["Unit"]["StartLimitBurst"]) >= 2 and int(unit["Unit"]["StartLimitIntervalSec"]) > 0
    assert service["KillSignal"] == "SIGTERM" and int(service["TimeoutStopSec"]) >= 30  # time for the last checkpoint
    assert Path(service["EnvironmentFile"]).name == ENV_FILE.name
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_exec_start_is_a_real_geometry_command_with_the_env_files_variables() -> None:
    command = _unit()["Service"]["ExecStart"]
    env = _env()
    used = set(re.findall(r"\$\{(\w+)\}", command))
    assert used and used <= set(env), f"{used - set(env)} not set in {ENV_FILE.name}"
    argv = shlex.split(re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], command))
    assert Path(argv[0]).name == "openfusion" and argv[1:3] == ["service", "geometry"]
    args = build_parser(argv[1:])[0].parse_args(argv[1:])
    assert args.map_id == env["OPENFUSION_MAP"]
    assert str(args.geometry__map_dir).startswith("/var/lib/openfusion")
    assert args.geometry__checkpoint_period_s > 0  # a restart resumes from a recent checkpoint
    for name in env:
        assert name.startswith("OPENFUSION_")
