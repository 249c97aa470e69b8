"""run.json and ``openfusion health`` account for every frame the semantic service received:
received = the outcomes + pending (wire.counters.SEMANTIC_FRAME_OUTCOMES). From health counters,
no bus."""

from __future__ import annotations

from openfusion.app.bus_cmds import semantic_frames_line
from openfusion.app.summary import RunSummary
from openfusion.wire.counters import PoolCounter, SemanticCounter
from openfusion.wire.schemas import HealthStats


def _health(service: str, counters: dict[str, float]) -> HealthStats:
    return HealthStats(service=service, map_id="m", pid=1, stamp_ns=0, uptime_s=1.0, fps=0.0, latency_ms_p50=0.0,
                       latency_ms_p99=0.0, drops=0, errors=0, counters={str(k): v for k, v in counters.items()})


COUNTERS = {SemanticCounter.FRAMES_RECEIVED: 90, SemanticCounter.SEMANTIC_FRAMES: 20,
            SemanticCounter.FRAMES_SUPERSEDED: 60, SemanticCounter.FRAMES_DROPPED: 3,
            SemanticCounter.SKIPPED_NO_RENDER: 1, PoolCounter.RESULTS_STALE: 1,
            SemanticCounter.ENCODER_CALLS: 21, SemanticCounter.REGIONS: 30}


def test_run_json_names_each_outcome_and_the_frames_with_none() -> None:
    summary = RunSummary.from_health({"semantic": _health("semantic", COUNTERS)}, source="s", encoder="gt",
                                     noise="off", semantic_every=1, wall_s=1.0)
    assert summary.semantic_frames_received == 90
    assert summary.semantic_outcomes == {"semantic_frames": 20, "frames_superseded": 60, "frames_dropped": 3,
                                         "skipped_no_render": 1, "results_stale": 1}
    assert summary.semantic_frames_pending == 5  # 90 received, 85 with an outcome
    assert "encoder_calls" not in summary.semantic_outcomes  # a call is not an outcome of its own


def test_health_prints_the_frames_received_as_the_sum_of_their_outcomes() -> None:
    line = semantic_frames_line({str(k): float(v) for k, v in COUNTERS.items()})
    assert line == ("semantic frames: received 90 = semantic_frames 20 + frames_superseded 60 + skipped_no_render 1 "
                    "+ frames_dropped 3 + results_stale 1 + pending 5")
