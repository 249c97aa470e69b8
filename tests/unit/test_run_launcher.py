"""The pieces of ``openfusion run`` that need no process: the source spec that plays --frames frames
of the built-in room, the note of a run that played fewer frames than asked for, and the reason a
dead service gives in its log (what the launcher prints instead of an empty tail)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from openfusion.app.launcher import Cluster, RestartPolicy, RunError, ServiceProcess, _reason_and_tail
from openfusion.app.run import BUILTIN_LAP_FRAMES, builtin_scene_spec, shortfall_note
from openfusion.app.summary import RunSummary

TRACEBACK_LOG = """\
INFO openfusion.bus.runner: geometry: ready on openfusion/demo
WARNING openfusion.services.geometry.service: geometry: frame 3 refused: out of blocks
Traceback (most recent call last):
  File "/x/cli.py", line 150, in main
    return int(loaded[args.command].run(args) or 0)
  File "/x/service.py", line 12, in on_frame
    raise RuntimeError("disk on fire")
RuntimeError: disk on fire

"""


def test_the_reason_is_the_exception_line_or_the_one_line_error() -> None:
    reason, tail = _reason_and_tail(TRACEBACK_LOG)
    assert reason == "RuntimeError: disk on fire"
    assert tail[-1] == "RuntimeError: disk on fire" and tail[0].startswith("INFO") and len(tail) == 8
    assert len(_reason_and_tail(TRACEBACK_LOG, lines=3)[1]) == 3
    one_line = "INFO starting\nopenfusion service: error: cannot open source 'folder:/x': no openfusion_source.json\n"
    assert _reason_and_tail(one_line)[0].endswith("no openfusion_source.json")
    logged = "INFO a\nERROR openfusion.bus: cannot join the network\nINFO b\n"
    assert _reason_and_tail(logged)[0] == "ERROR openfusion.bus: cannot join the network"
    assert _reason_and_tail("INFO a\nINFO b\n") == ("", ["INFO a", "INFO b"])  # nothing says why
    assert _reason_and_tail("\n\n") == ("", [])


def _dead(tmp_path: Path, log: str, returncode: int) -> ServiceProcess:
    path = tmp_path / "svc.log"
    path.write_text(log)
    return ServiceProcess("geometry", SimpleNamespace(returncode=returncode, poll=lambda: returncode), path)


def test_a_dead_service_is_reported_with_its_reason_and_last_lines(tmp_path: Path) -> None:
    """One line that says why (what the command prints as its error), the log's last lines above it."""
    crashed = _dead(tmp_path, TRACEBACK_LOG, 1).death()
    assert str(crashed) == f"the geometry service exited with code 1: RuntimeError: disk on fire (log: {tmp_path}/svc.log)"
    assert crashed.details.splitlines()[0] == f"last lines of {tmp_path}/svc.log:"
    assert crashed.details.splitlines()[-1] == "  RuntimeError: disk on fire"
    refused = _dead(tmp_path, "openfusion service: error: cannot open source 'folder:/x'\n", 2).death()
    assert str(refused).startswith("the geometry service exited with code 2: cannot open source 'folder:/x' (log: ")
    assert refused.details == ""  # the one line is already the message
    killed = _dead(tmp_path, "INFO geometry: ready\n", -9).death()
    assert str(killed) == f"the geometry service was killed by SIGKILL (log: {tmp_path}/svc.log)"
    assert killed.details.endswith("  INFO geometry: ready")
    quiet = _dead(tmp_path, "", 3).death()
    assert str(quiet) == f"the geometry service exited with code 3 (log: {tmp_path}/svc.log)" and quiet.details == ""


@pytest.mark.parametrize(("spec", "expected"), [
    ("synthetic", f"synthetic:frames=500,lap={BUILTIN_LAP_FRAMES}"),
    ("synthetic:seed=2,width=160", f"synthetic:seed=2,width=160,frames=500,lap={BUILTIN_LAP_FRAMES}"),
    ("synthetic:frames=40,lap=8", "synthetic:frames=40,lap=8"),  # the user's own choices stay
    ("scannet:/data/scene", "scannet:/data/scene"),
])
def test_the_built_in_room_plays_the_frames_asked_for(spec: str, expected: str) -> None:
    assert builtin_scene_spec(spec, 500) == expected


def _summary(**fields: object) -> RunSummary:
    base = dict(mode="services", source="s", encoder="gt", noise="off", semantic_every=1, frames_read=300,
                frames_skipped={}, frames_published=300, frames_integrated=300, semantic_frames=300, regions=9,
                rec_fps=None, sem_rec_fps=None, wall_s=1.0, frames_requested=2000, frames_played=300)
    return RunSummary.model_validate({**base, **fields})


def test_a_shorter_source_is_said_and_an_old_run_json_still_loads(tmp_path: Path) -> None:
    assert shortfall_note(_summary()) == "played 300 of 2000 frames: the source has 300"
    assert shortfall_note(_summary(frames_skipped={"bad_pose": 4})) == (
        "played 300 of 2000 frames: the source has 300 usable frames (4 skipped: bad_pose 4)")
    assert shortfall_note(_summary(frames_played=2000)) is None
    assert shortfall_note(_summary(interrupted=True)) is None
    old = _summary().model_dump(exclude={"frames_requested", "frames_played", "interrupted"})
    loaded = RunSummary.model_validate(old)
    assert loaded.frames_requested is None and not loaded.interrupted and shortfall_note(loaded) is None
    # map_saved was true/false/null before it said where the map went: such a run.json still loads
    assert RunSummary.model_validate({**old, "map_saved": True}).map_saved == "map"
    assert RunSummary.model_validate({**old, "map_saved": False}).map_saved is None
    assert RunSummary.model_validate({**old, "map_saved": "/tmp/out/map"}).map_saved == "/tmp/out/map"


class _Proc:
    """A stand-in Popen: alive until ``end(code)``."""

    def __init__(self) -> None:
        self.returncode: int | None = None

    def poll(self) -> int | None:
        return self.returncode

    def end(self, code: int) -> None:
        self.returncode = code


def _supervised(tmp_path: Path, policy: RestartPolicy) -> tuple[Cluster, list[tuple[str, int]]]:
    """A cluster whose start() makes stand-in processes (and records (name, restarts))."""
    cluster = Cluster("m", "tcp/127.0.0.1:1", tmp_path, restart_policy=policy)
    started: list[tuple[str, int]] = []

    def start(name: str, extra=(), env=None, *, restarts: int = 0, service: str | None = None,  # noqa: ANN001
              optional: bool = False) -> ServiceProcess:
        log = tmp_path / f"{name}.log"
        log.touch()
        sp = ServiceProcess(name, _Proc(), log, extra=tuple(extra), env=env, log_offset=log.stat().st_size,
                            restarts=restarts, service=service, optional=optional)
        cluster.processes[name] = sp
        started.append((name, restarts))
        return sp

    cluster.start = start  # type: ignore[method-assign]
    return cluster, started


def test_a_dead_service_is_restarted_with_backoff_up_to_the_limit(tmp_path: Path) -> None:
    """Backoff 1 s doubled per restart (capped at 3 s), 3 restarts: each death waits its delay,
    the restarted process keeps its arguments and gets its count, the log is marked with why, and
    the fourth death ends the run with the reason of the last process (not of an earlier one)."""
    cluster, started = _supervised(tmp_path, RestartPolicy(max_restarts=3, backoff_s=1.0, backoff_max_s=3.0))
    cluster.start("geometry", ["--x"])
    cluster.start("query")
    assert [RestartPolicy(backoff_s=1.0, backoff_max_s=3.0).delay_s(n) for n in range(4)] == [1.0, 2.0, 3.0, 3.0]
    t = 100.0
    for n, delay in enumerate([1.0, 2.0, 3.0], start=1):
        geometry = cluster.processes["geometry"]
        with geometry.log_path.open("a") as log:
            log.write(f"Traceback (most recent call last):\n  File x\nRuntimeError: crash {n}\n")
        geometry.proc.end(-9 if n == 1 else 1)
        assert cluster.supervise(t) == [] and cluster.restarting
        assert cluster.supervise(t + delay - 0.01) == []
        assert cluster.supervise(t + delay) == ["geometry"] and not cluster.restarting
        assert started[-1] == ("geometry", n) and cluster.processes["geometry"].extra == ("--x",)
        t += 10
    assert cluster.restarts == {"geometry": 3, "query": 0}
    log = (tmp_path / "geometry.log").read_text()
    assert "---- openfusion run: the geometry service was killed by SIGKILL: RuntimeError: crash 1; restart 1 in 1.0 s ----" in log
    assert "exited with code 1: RuntimeError: crash 3; restart 3 in 3.0 s ----" in log
    with (tmp_path / "geometry.log").open("a") as f:
        f.write("ERROR geometry: out of memory\n")
    cluster.processes["geometry"].proc.end(1)
    with pytest.raises(RunError) as info:
        cluster.supervise(t)
    assert str(info.value).startswith("the geometry service exited with code 1: ERROR geometry: out of memory "
                                      "(restarted 3 times, the limit) (log: ")


def test_a_service_refusing_its_config_or_stopped_on_purpose_is_not_restarted(tmp_path: Path) -> None:
    cluster, started = _supervised(tmp_path, RestartPolicy())
    cluster.start("bridge")
    cluster.start("query")
    cluster.processes["query"].stopped = True
    cluster.processes["query"].proc.end(0)
    assert cluster.supervise(0.0) == [] and not cluster.restarting
    (tmp_path / "bridge.log").write_text("openfusion service: error: cannot open source 'folder:/x'\n")
    cluster.processes["bridge"].proc.end(2)
    with pytest.raises(RunError, match=r"exited with code 2: cannot open source 'folder:/x' \(its config or "
                       r"arguments are refused; not restarted\)"):
        cluster.check_alive()
    assert started == [("bridge", 0), ("query", 0)]
    without = Cluster("m", "e", tmp_path)  # no policy: a death ends the run at once, as before
    without.processes["geometry"] = ServiceProcess("geometry", _Proc(), tmp_path / "bridge.log")
    without.processes["geometry"].proc.end(-9)
    with pytest.raises(RunError, match="killed by SIGKILL"):
        without.check_alive()


def test_an_encoder_worker_is_restarted_and_past_the_limit_the_run_goes_on_without_it(tmp_path: Path) -> None:
    """Encoder workers (optional processes of the ``encoder`` service) are restarted like the others,
    as the same service; past the limit the run goes on with the other workers. Without a restart
    policy a worker's death is logged, not raised."""
    cluster, started = _supervised(tmp_path, RestartPolicy(max_restarts=1, backoff_s=1.0))
    cluster.start("encoder-w1", ["--worker-id", "w1"], service="encoder", optional=True)
    cluster.processes["encoder-w1"].proc.end(-9)
    assert cluster.supervise(0.0) == [] and cluster.supervise(1.0) == ["encoder-w1"]
    worker = cluster.processes["encoder-w1"]
    assert (worker.service, worker.optional, worker.extra, worker.restarts) == ("encoder", True, ("--worker-id", "w1"), 1)
    worker.proc.end(-9)
    assert cluster.supervise(2.0) == [] and worker.stopped  # the limit: no RunError, no restart
    assert started == [("encoder-w1", 0), ("encoder-w1", 1)]
    without = Cluster("m", "e", tmp_path)
    without.processes["encoder-w2"] = ServiceProcess("encoder-w2", _Proc(), tmp_path / "w2.log", optional=True)
    without.processes["encoder-w2"].proc.end(-9)
    without.check_alive()
    assert without.processes["encoder-w2"].stopped


def test_a_restarted_semantic_services_counts_add_up_in_run_json() -> None:
    """A restarted process counts from 0: run.json adds the last counts of the one before."""
    from openfusion.app.run_progress import carry_over, progress_counts, with_carried
    from openfusion.wire.schemas import HealthStats

    def semantic(frames: float, restarts: float) -> HealthStats:
        return HealthStats(service="semantic", map_id="m", pid=1, uptime_s=1.0, fps=0.0, latency_ms_p50=0.0,
                           latency_ms_p99=0.0, drops=0, errors=0, counters={"semantic_frames": frames,
                                                                             "restarts": restarts})

    stats, carried = {"semantic": semantic(40, 0)}, {}
    carry_over(stats, {"semantic": semantic(41, 0)}, carried)  # same process: nothing carried
    assert carried == {}
    stats = {"semantic": semantic(41, 0)}
    carry_over(stats, {"semantic": semantic(3, 1)}, carried)
    stats = {"semantic": semantic(3, 1)}
    assert with_carried(stats, carried)["semantic"].counter("semantic_frames") == 44
    assert stats["semantic"].counter("semantic_frames") == 3  # the live stats are untouched
    # the progress line counts what run.json counts (it showed the live process's 3)
    assert progress_counts(with_carried(stats, carried))["semantic"] == 44
