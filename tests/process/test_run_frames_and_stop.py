"""``openfusion run`` as a new user meets it: ``--frames N`` plays N frames (the built-in room walks
its lap again; a shorter source says so), Ctrl-C keeps the map, a second Ctrl-C aborts, and a
service that dies shows why. Each run is small (160x120 frames, a few dozen frames).

Waiting is on events: the run's progress is read from the services' health (the endpoint the run
prints), never from a fixed sleep."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from supervision_support import run_endpoint

from openfusion.bus import collect_health, open_session
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.mapping import load_map
from openfusion.testing.bus import processes_mentioning, scaled, subprocess_env, unique_map_id, wait_until
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.keys import KeySpace

pytestmark = pytest.mark.timeout(300)

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())
OPENFUSION = [sys.executable, "-m", "openfusion.app.cli"]
SMALL = "width=160,height=120"


def _run(*args: str, timeout_s: float = 240) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*OPENFUSION, "run", *args], capture_output=True, text=True, timeout=scaled(timeout_s), cwd=ROOT,
                          env=subprocess_env(HF_HUB_OFFLINE="1"))


@pytest.mark.slow  # ~40 s on 2 cores; the lap walked again: tests/unit/test_synthetic.py
def test_frames_beyond_a_lap_are_all_played(tmp_path: Path) -> None:
    """A lap of 6 frames and --frames 15: the room is walked 2.5 times and every frame is mapped
    (it used to play one lap's worth, the source's own length, whatever --frames said)."""
    out = tmp_path / "out"
    proc = _run("--out", str(out), "--map", unique_map_id("laps"), "--source", f"synthetic:seed=1,{SMALL},lap=6",
                "--frames", "15", "--rate-hz", "0", "--quiet", "--query", "chair")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "run.json").read_text())
    assert summary["source"] == f"synthetic:seed=1,{SMALL},lap=6,frames=15"
    assert summary["frames_requested"] == summary["frames_played"] == summary["frames_integrated"] == 15
    assert summary["interrupted"] is False
    assert "played" not in proc.stderr


@pytest.mark.parametrize("in_process", [pytest.param(False, marks=pytest.mark.slow), True], ids=["services", "in-process"])
def test_a_source_shorter_than_frames_plays_what_it_has_and_says_so(tmp_path: Path, in_process: bool) -> None:
    out = tmp_path / "out"
    mode = ["--in-process"] if in_process else ["--rate-hz", "0"]
    proc = _run("--out", str(out), "--map", unique_map_id("short"), "--source", f"synthetic:seed=1,{SMALL},frames=5",
                "--frames", "12", "--quiet", "--query", "chair", *mode)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "played 5 of 12 frames: the source has 5" in proc.stderr.splitlines(), proc.stderr
    summary = json.loads((out / "run.json").read_text())
    assert (summary["frames_requested"], summary["frames_played"], summary["frames_integrated"]) == (12, 5, 5)


class _Run:
    """``openfusion run`` in the background, its stderr in a file, its health read over the bus."""

    def __init__(self, tmp_path: Path, *args: str) -> None:
        self.out = tmp_path / "out"
        self.map_id = unique_map_id("stop")
        self.err_path = tmp_path / "stderr.txt"
        self._err = self.err_path.open("w")
        self.proc = subprocess.Popen(
            [*OPENFUSION, "run", "--out", str(self.out), "--map", self.map_id, "--source", f"synthetic:seed=1,{SMALL}",
             "--frames", "400", "--rate-hz", "8", "--query", "chair", *args],
            stdout=subprocess.PIPE, stderr=self._err, text=True, cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"))
        self.session = None

    def stderr(self) -> str:
        return self.err_path.read_text(errors="replace").replace("\r", "\n")

    def integrated(self) -> float:
        """Frames geometry has integrated (0 until the run's services are up: they are started with
        ``--connect`` to the run's router, the endpoint used here)."""
        if self.session is None:
            endpoint = run_endpoint(self.map_id)
            if endpoint is None:
                return 0.0
            self.session = open_session(ServiceConfig(map_id=self.map_id, zenoh=ZenohSettings(
                mode="client", connect=[endpoint], multicast_scouting=False)))
        stats = collect_health(self.session, KeySpace("openfusion", self.map_id), timeout_s=1.0).get("geometry")
        return stats.counter(GeometryCounter.FRAMES_INTEGRATED) if stats is not None else 0.0

    def wait_integrated(self, frames: int) -> float:
        def enough() -> float:
            assert self.proc.poll() is None, self.stderr()[-3000:]
            n = self.integrated()
            return n if n >= frames else 0.0

        return wait_until(enough, timeout_s=180, interval_s=0.2)

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(30)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._err.close()


@pytest.fixture
def run(tmp_path: Path):
    runs: list[_Run] = []

    def start(*args: str) -> _Run:
        runs.append(_Run(tmp_path, *args))
        return runs[-1]

    yield start
    for r in runs:
        r.close()


def test_ctrl_c_saves_the_map_of_what_was_integrated(run, tmp_path: Path) -> None:
    """SIGINT once geometry has integrated a few frames: playback stops, the frames in flight are
    integrated, the map is saved to OUT/map and answers a query, run.json says interrupted, exit
    130, and no process of the run is left (it used to exit 130 with no map)."""
    r = run("--quiet")
    r.wait_integrated(4)
    r.proc.send_signal(signal.SIGINT)
    assert r.proc.wait(scaled(120)) == 130, r.stderr()[-3000:]
    lines = r.stderr().strip().splitlines()
    assert len(lines) == 1, lines  # --quiet: only where the map is
    assert re.fullmatch(rf"openfusion run: interrupted: saved the map of (\d+) integrated frames to {re.escape(str(r.out))}/map",
                        lines[-1]), lines
    saved = int(re.search(r"map of (\d+) integrated", lines[-1]).group(1))
    summary = json.loads((r.out / "run.json").read_text())
    assert summary["interrupted"] is True and summary["frames_requested"] == 400
    assert summary["frames_integrated"] == saved >= 4 and summary["frames_played"] >= saved
    assert summary["map_saved"] == str((r.out / "map").resolve())  # it was null though the map was saved
    assert not (r.out / "queries.json").exists()  # the example queries were skipped
    assert r.proc.stdout.read() == ""
    assert processes_mentioning(r.map_id) == []
    answer = subprocess.run([*OPENFUSION, "query", "--map-dir", str(r.out / "map"), "chair"], capture_output=True,
                            text=True, timeout=scaled(120), cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"))
    assert answer.returncode == 0, answer.stderr[-3000:]
    assert answer.stdout.strip()


@pytest.mark.slow  # ~30 s on 2 cores; the first Ctrl-C's save stays in the fast suite
def test_a_second_ctrl_c_aborts_at_once(run) -> None:
    """The second SIGINT, while the run finishes its frames: every service is killed, exit 130 within
    seconds, no map promised, no process left."""
    r = run()
    r.wait_integrated(2)
    r.proc.send_signal(signal.SIGINT)
    wait_until(lambda: "stopping playback" in r.stderr() or r.proc.poll() is not None, timeout_s=60)
    r.proc.send_signal(signal.SIGINT)
    assert r.proc.wait(scaled(30)) == 130, r.stderr()[-3000:]
    last = r.stderr().strip().splitlines()[-1]
    assert last.startswith("openfusion run: interrupted: aborted by a second SIGINT"), last
    assert processes_mentioning(r.map_id) == []


def test_ctrl_c_in_process_stops_at_the_next_frame_and_saves_the_map(tmp_path: Path) -> None:
    """--in-process: SIGINT once the progress bar shows a few frames; the loop ends before the next
    frame, the map is saved and loads, run.json says interrupted, exit 130."""
    out = tmp_path / "out"
    err_path = tmp_path / "stderr.txt"
    with err_path.open("w") as err:
        proc = subprocess.Popen([*OPENFUSION, "run", "--in-process", "--out", str(out), "--source",
                                 f"synthetic:seed=1,{SMALL}", "--frames", "400", "--query", "chair"],
                                stdout=subprocess.DEVNULL, stderr=err, cwd=ROOT, env=subprocess_env(HF_HUB_OFFLINE="1"))
        try:
            def progress() -> int:
                assert proc.poll() is None, err_path.read_text()[-3000:]
                done = re.findall(r"(\d+)/400", err_path.read_text())
                return int(done[-1]) if done and int(done[-1]) >= 3 else 0

            wait_until(progress, timeout_s=180, interval_s=0.2)
            proc.send_signal(signal.SIGINT)
            assert proc.wait(scaled(120)) == 130, err_path.read_text()[-3000:]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(30)
    last = err_path.read_text().replace("\r", "\n").strip().splitlines()[-1]
    summary = json.loads((out / "run.json").read_text())
    assert summary["interrupted"] is True and summary["mode"] == "in-process"
    assert summary["map_saved"] == str((out / "map").resolve())
    assert 3 <= summary["frames_integrated"] == summary["frames_played"] < 400
    assert last == f"openfusion run: interrupted: saved the map of {summary['frames_integrated']} integrated frames " \
        f"to {out}/map", last
    assert len(load_map(out / "map").dictionary) > 0


def test_a_service_that_dies_shows_why(tmp_path: Path) -> None:
    """The bridge cannot read its folder: the launcher's error says why (from the bridge's log), not
    just that it exited (it used to print `last lines of .../bridge.log:` and nothing after)."""
    empty = tmp_path / "empty"
    empty.mkdir()
    map_id = unique_map_id("dies")
    proc = _run("--out", str(tmp_path / "out"), "--map", map_id, "--source", f"folder:{empty}", "--frames", "3",
                "--quiet")
    assert proc.returncode == 1, proc.stderr[-3000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("openfusion run: error: the bridge service exited with code 2: "), last
    assert "openfusion_source.json" in last and "bridge.log" in last
    assert "Traceback" not in proc.stderr
    assert processes_mentioning(map_id) == []
