"""The ``openfusion`` console script as a user runs it (subprocesses): version, health against a
real service, the router relaying between two clients, and user errors as one line, no traceback."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

import openfusion
from openfusion.app import cli
from openfusion.bus import Publisher, Subscriber, open_session
from openfusion.config import ServiceConfig
from openfusion.testing.bus import (
    ServiceProcess,
    endpoint,
    free_port,
    loopback_args,
    processes_mentioning,
    subprocess_env,
    unique_map_id,
    wait_until,
)
from openfusion.wire.keys import KeySpace
from openfusion.wire.schemas import TextQuery

#: The repository root (deploy files, docs, the README's commands).
ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())

pytestmark = pytest.mark.timeout(120)

_SCRIPT = Path(sys.executable).parent / "openfusion"
OPENFUSION = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "openfusion.app.cli"]


def _run(*args: str, timeout_s: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*OPENFUSION, *args], capture_output=True, text=True, timeout=timeout_s, cwd=ROOT, env=subprocess_env()
    )


def _assert_one_line_error(proc: subprocess.CompletedProcess[str], rc: int, text: str) -> None:
    assert proc.returncode == rc, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and text in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def test_version() -> None:
    """`openfusion version` prints the package version (text and JSON) and exits 0."""
    proc = _run("version")
    assert proc.returncode == 0 and proc.stdout.startswith(f"openfusion-z {openfusion.__version__} (eclipse-zenoh ")
    info = json.loads(_run("version", "--json").stdout)
    assert info["openfusion-z"] == openfusion.__version__


def test_no_subcommand_prints_usage_and_exits_2() -> None:
    """Without a subcommand the user sees the list of commands."""
    proc = _run()
    assert proc.returncode == 2 and "version" in proc.stderr and "health" in proc.stderr


def test_user_errors_are_one_line_without_traceback() -> None:
    """A bad map id (config error, exit 2) and a health check of an empty map (exit 1)."""
    _assert_one_line_error(_run("health", "--map", "a/b"), 2, "map id 'a/b' is not a valid key segment")
    _assert_one_line_error(
        _run("health", "--map", unique_map_id(), "--no-multicast", "--connect", endpoint(free_port()), "--timeout", "0.5"),
        1,
        "no live services on map",
    )
    _assert_one_line_error(_run("health", "--set", "zenoh.mode=bogus"), 2, "zenoh.mode = 'bogus' (from --set zenoh.mode)")


def test_bad_values_are_refused_before_anything_starts(tmp_path: Path) -> None:
    """The real command refuses a bad source, a bad --top-k and a bad service source with one line
    and exit code 2 before it starts anything: no output folder, no service process of the map.
    (`run --source scannet:MISSING` used to start every service and end with exit 1 after ~40 s;
    `run --top-k 0` mapped the whole scene and ended with a pydantic traceback.)"""
    map_id = unique_map_id("badarg")
    out = tmp_path / "out"
    cases = [
        (["run", "--source", f"scannet:{tmp_path}/missing"], f"scannet source: {tmp_path}/missing does not exist"),
        (["run", "--top-k", "0"], "--top-k must be from 1 to 100, got 0"),
    ]
    for args, text in cases:
        proc = _run(*args, "--map", map_id, "--out", str(out), "--quiet")
        _assert_one_line_error(proc, 2, text)
        assert proc.stderr.startswith("openfusion run: error: "), proc.stderr
        assert proc.stdout == ""
    proc = _run("service", "bridge", "--source", "nosuch:/x", "--map", map_id, "--no-multicast")
    _assert_one_line_error(proc, 2, "unknown source scheme 'nosuch' in 'nosuch:/x'")
    assert proc.stderr.startswith("openfusion service: error: "), proc.stderr
    assert not out.exists(), sorted(p.name for p in out.iterdir())
    assert processes_mentioning(map_id) == []


def test_health_lists_a_live_service_with_its_stats() -> None:
    """With the demo service running, `openfusion health` shows it (table and JSON with its pid)."""
    map_id = unique_map_id("cli")
    port = free_port()
    with ServiceProcess("openfusion.testing.demo_service", loopback_args(map_id, listen=[port])) as svc:
        args = ["health", "--map", map_id, "--no-multicast", "--connect", endpoint(port), "--timeout", "20"]
        proc = _run(*args, "--json")
        assert proc.returncode == 0, proc.stderr + svc.output()
        report = json.loads(proc.stdout)
        assert report["map_id"] == map_id
        assert [s["service"] for s in report["services"]] == ["demo"]
        assert report["services"][0]["stats"]["pid"] == svc.pid
        table = _run(*args)
        assert table.returncode == 0 and table.stdout.splitlines()[0].split()[:3] == ["service", "pid", "uptime_s"]
        assert table.stdout.splitlines()[1].split()[:2] == ["demo", str(svc.pid)]


def test_router_relays_between_clients_and_exits_0_on_sigterm() -> None:
    """Two client-mode sessions talk only through `openfusion router`; SIGTERM stops it with 0."""
    port = free_port()
    map_id = unique_map_id("router")
    keys = KeySpace("openfusion", map_id)
    router = ServiceProcess("openfusion.app.cli", ["router", "--listen", endpoint(port), "--no-multicast"])
    with router:
        wait_until(lambda: "listening on" in router.output(), timeout_s=30)
        client = ServiceConfig.model_validate(
            {"map_id": map_id, "zenoh": {"mode": "client", "connect": [endpoint(port)], "multicast_scouting": False}}
        )
        a, b = open_session(client), open_session(client)
        try:
            sub = Subscriber(a, keys.key("test", "relay"), TextQuery)
            pub = Publisher(b, keys.key("test", "relay"), congestion_control=zenoh.CongestionControl.BLOCK)
            assert pub.wait_for_subscribers(10.0)
            pub.put(TextQuery(text="through the router"))
            msg = sub.recv(timeout_s=10)
            assert msg is not None and msg.text == "through the router"
            sub.close()
            pub.close()
        finally:
            a.close()
            b.close()
        router.signal(signal.SIGTERM)
        assert router.wait(10) == 0, router.output()


def test_registry_loads_only_the_chosen_command_and_a_broken_one_fails_loudly(monkeypatch: pytest.MonkeyPatch) -> None:
    """`version` does not import the heavy modules other subcommands need; a registered
    subcommand whose module cannot be imported is listed and fails when chosen (it used to be
    dropped silently, so a typo hid a whole command)."""
    extra = cli.Subcommand("later", "openfusion.no_such_module_yet:Command", "added by a later issue")
    monkeypatch.setattr(cli, "SUBCOMMANDS", [*cli.SUBCOMMANDS, extra])
    parser, loaded = cli.build_parser(["version"])
    assert set(loaded) == {"version"}
    assert "later" in parser.format_help() and "health" in parser.format_help()
    with pytest.raises(ModuleNotFoundError, match="no_such_module_yet"):
        cli.build_parser(["later"])
    code = "import sys; from openfusion.app.cli import main; main(['version']); print('torch' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=subprocess_env())
    assert proc.stdout.strip().splitlines()[-1] == "False"


