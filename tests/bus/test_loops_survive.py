"""Every service loop survives an exception in one message's handling, logged with context and
counted, and a poison message is never retried: the handlers called directly (no Zenoh session).

Bad input tried: a frame whose integration raises (geometry), a checkpoint that raises something
other than an OSError (geometry's loop), a frame whose publishing raises (bridge), a dataset item
whose reader raises (source), a background refresh that raises (query's loop). The semantic
service's loop is covered by tests/bus/test_semantic_service.py (an encoder that raises)."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import pytest
from test_resume_playback import FRAMES, PLAYBACK, _bridge, _geometry, _msg, _Recorder, _Runner

from openfusion.services.query.service import QuerySection, QueryService
from openfusion.sources.base import READ_FAILED
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld
from openfusion.wire.counters import BridgeCounter, GeometryCounter

pytestmark = pytest.mark.timeout(120)


def test_a_frame_that_fails_to_integrate_is_skipped_once_and_the_next_one_integrates(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    geo, runner = _geometry(tmp_path / "maps")
    geo.on_frame(_msg(FRAMES[0], -1))
    real = geo.volume.integrate

    def poison(frame):  # noqa: ANN001, ANN202
        if frame.frame_id == 1:
            raise RuntimeError("bad voxel block")
        return real(frame)

    monkeypatch.setattr(geo.volume, "integrate", poison)
    with caplog.at_level(logging.ERROR):
        geo.on_frame(_msg(FRAMES[1], 0))
    assert "geometry: frame 1 of robot robot0 (synthetic" in caplog.text and "RuntimeError: bad voxel block" in caplog.text
    assert runner.counter(GeometryCounter.FRAMES_FAILED) == 1 and runner.stats.errors == 1
    geo.on_frame(_msg(FRAMES[1], 0))  # replayed: already taken, not retried
    geo.on_frame(_msg(FRAMES[2], 1))
    assert geo.frames_integrated == 2 and geo.last_frame_id == 2
    assert runner.counter(GeometryCounter.FRAMES_DUPLICATE) == 1
    acks = [(m.frame_id, m.integrated) for m in runner.published.sent if m.frame_id >= 0]
    assert acks == [(0, True), (1, False), (1, False), (2, True)]  # the bridge's flow control never stalls
    assert geo.playback == PLAYBACK


def test_a_checkpoint_that_raises_leaves_the_loop_running(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    geo, runner = _geometry(tmp_path / "maps")
    geo.section.checkpoint_period_s = 0.001
    geo.on_frame(_msg(FRAMES[0], -1))
    calls = {"n": 0}

    def broken(*_args: object, **_kwargs: object) -> None:
        calls["n"] += 1
        raise ValueError("cannot pack the dictionary")

    monkeypatch.setattr("openfusion.services.geometry.persistence.checkpoint_store", broken)
    waits = {"n": 0}

    def wait(_timeout_s: float | None = None) -> bool:
        waits["n"] += 1
        if waits["n"] == 2:  # the first try failed a moment ago: the next one is due a period later
            geo._last_checkpoint -= 1.0
        return waits["n"] > 3

    runner.wait = wait  # type: ignore[method-assign]
    geo.loop(runner)  # type: ignore[arg-type]
    assert calls["n"] == 2 and runner.counter(GeometryCounter.CHECKPOINT_FAILURES) == 2 and runner.stats.errors == 2
    geo.on_frame(_msg(FRAMES[1], 0))
    assert geo.frames_integrated == 2


def test_a_frame_that_fails_to_publish_is_skipped_and_the_chain_goes_on(monkeypatch: pytest.MonkeyPatch) -> None:
    bridge = _bridge(4)
    sent = _Recorder()

    def put(msg):  # noqa: ANN001, ANN202
        if msg.frame_id == 1:
            raise RuntimeError("shared memory segment gone")
        return _Recorder.put(sent, msg)

    bridge._pub, bridge._instance_pub = SimpleNamespace(put=put, wait_for_subscribers=lambda _t: True), _Recorder()
    runner = _Runner()
    bridge.loop(runner)  # type: ignore[arg-type]
    assert [(m.frame_id, m.prev_frame_id) for m in sent.sent] == [(0, -1), (2, 0), (3, 2)]
    assert runner.counter(BridgeCounter.SKIPPED_PUBLISH_FAILED) == 1 and runner.stats.errors == 1
    assert runner.counter(BridgeCounter.FRAMES_PUBLISHED) == 3 and runner.counter(BridgeCounter.PLAYBACK_DONE) == 1


def test_a_dataset_item_whose_reader_raises_is_skipped_in_playback_and_in_a_replay(monkeypatch: pytest.MonkeyPatch) -> None:
    """Playback (what the bridge reads) skips it; a plain pass (writers, evaluation) still raises."""
    source = SyntheticSource(SyntheticWorld(0), num_frames=4, width_px=40, height_px=30)
    real = source._load

    def load(index: int):  # noqa: ANN202
        if index == 2:
            raise KeyError("depth")
        return real(index)

    monkeypatch.setattr(source, "_load", load)
    with pytest.raises(KeyError):
        list(source)
    source.start_replayable_pass()
    assert [p for p, _f in source.replay_from(0)] == [0, 1, 3]
    assert source.stats.skipped == {READ_FAILED: 1} and source.stats.read == 4
    assert [p for p, _f in source.replay_from(1)] == [1, 3]  # going back counts nothing twice
    assert source.stats.skipped == {READ_FAILED: 1} and (source.stats.read, source.stats.yielded) == (4, 3)


def test_the_query_loop_survives_a_failing_refresh(caplog: pytest.LogCaptureFixture) -> None:
    section = QuerySection(summary_refresh_s=0.01, resync_period_s=0.01)
    calls = {"n": 0}

    def refresh() -> None:
        calls["n"] += 1
        raise ValueError("summary reply with mismatched arrays")

    fake = SimpleNamespace(section=section, _keep_summaries_warm=refresh,
                           replica=SimpleNamespace(embedding_space="minilm"), resync=lambda: None)
    runner = _Runner(on_wait=lambda: calls["n"] < 3)
    with caplog.at_level(logging.ERROR):
        QueryService.loop(fake, runner)  # type: ignore[arg-type]
    assert calls["n"] == 3 and runner.stats.errors == 3
    assert "query: background refresh failed" in caplog.text
