"""The end of ``openfusion run`` at any map size (``openfusion.app.end_of_run``), with a stand-in
client: a save that outlasts the request's timeout is waited for until geometry counts it saved (a
periodic checkpoint meanwhile is not the save), a save geometry counts as failed or a geometry that
dies meanwhile ends the wait with a RunError, geometry shards are waited for together, and a mesh
refused as too large for one reply is built from the saved map instead."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from openfusion.app import end_of_run
from openfusion.app.launcher import RunError
from openfusion.bus.query import QueryError
from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams, save_map
from openfusion.sources import open_source
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.schemas import HealthStats


def _stats(service: str, counters: dict[str, float]) -> HealthStats:
    return HealthStats(service=service, map_id="m", pid=1, uptime_s=1.0, fps=1.0, latency_ms_p50=0.0,
                       latency_ms_p99=0.0, drops=0, errors=0, counters=counters)


class _Client:
    def __init__(self, health: list[dict[str, float]], *, control_error: str = "timeout", mesh_error: str | None = None) -> None:
        self._health = health
        self.control_error = control_error
        self.mesh_error = mesh_error
        self.polls = 0

    def control(self, action: str, path: str) -> None:
        raise QueryError("openfusion/m/control/save", self.control_error, "no answer")

    def health(self, *, timeout_s: float) -> dict[str, object]:
        self.polls += 1
        counters = self._health[min(self.polls - 1, len(self._health) - 1)]
        if isinstance(next(iter(counters.values()), None), dict):  # by service: geometry shards
            return {name: _stats(name, c) for name, c in counters.items()}
        return {"geometry": SimpleNamespace(counters=counters)}

    def mesh(self) -> object:
        raise QueryError("openfusion/m/geometry/mesh", self.mesh_error or "too_large", "mesh has 9 vertices")


@pytest.fixture(autouse=True)
def _fast_polls(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(end_of_run, "_POLL_S", 0.0)
    monkeypatch.setattr(end_of_run, "PROGRESS_EVERY_S", 0.0)


def test_a_long_save_is_waited_for_with_progress(tmp_path: Path) -> None:
    saving = {GeometryCounter.SAVING: 1.0, GeometryCounter.SAVES: 3.0}
    done = {GeometryCounter.SAVING: 0.0, GeometryCounter.SAVES: 4.0}
    client = _Client([{GeometryCounter.SAVES: 3.0}, saving, saving, saving, done])
    said: list[str] = []
    end_of_run.save_and_wait(client, tmp_path, say=said.append, alive=lambda: True)
    assert any("still writing" in line for line in said) and said[-1].startswith("saved the map")


def test_zenohs_own_timeout_reply_is_waited_through_too(tmp_path: Path) -> None:
    """A queryable that does not answer in time gets Zenoh's error reply ``Timeout`` (code
    ``error``): the run waits for the save all the same (the failure the issue reported)."""
    client = _Client([{GeometryCounter.SAVES: 1.0},
                      {GeometryCounter.SAVING: 0.0, GeometryCounter.SAVES: 2.0}], control_error="error")
    client.control = lambda *_a: (_ for _ in ()).throw(QueryError("k", "error", "Timeout"))  # type: ignore[method-assign]
    said: list[str] = []
    end_of_run.save_and_wait(client, tmp_path, say=said.append, alive=lambda: True)
    assert said[-1].startswith("saved the map")


def test_a_periodic_checkpoint_is_not_the_save_and_a_failed_save_ends_the_wait(tmp_path: Path) -> None:
    """Bad input to wait on: the save timed out, a periodic checkpoint completed meanwhile
    (``checkpoints`` up, ``saving`` 0), then geometry counted the save as failed: the run says so
    (it used to take the checkpoint for the save and report the map saved)."""
    start = {GeometryCounter.CHECKPOINTS: 3.0, GeometryCounter.SAVES: 1.0}
    checkpointed = {GeometryCounter.CHECKPOINTS: 4.0, GeometryCounter.SAVING: 0.0, GeometryCounter.SAVES: 1.0}
    failed = {**checkpointed, GeometryCounter.SAVE_FAILURES: 1.0}
    client = _Client([start, checkpointed, checkpointed, failed])
    said: list[str] = []
    with pytest.raises(RunError, match="could not save the map"):
        end_of_run.save_and_wait(client, tmp_path, say=said.append, alive=lambda: True)
    assert not any(line.startswith("saved the map") for line in said)
    assert client.polls == 4


def test_geometry_shards_are_waited_for_until_every_shard_saved(tmp_path: Path) -> None:
    """Two shards: the save is done when both counted it (the combined view's smallest ``saves``)."""
    def shards(first: float, second: float) -> dict[str, dict[str, float]]:
        return {"geometry-0of2": {GeometryCounter.SAVES: first}, "geometry-1of2": {GeometryCounter.SAVES: second}}

    client = _Client([shards(0, 0), shards(1, 0), shards(1, 0), shards(1, 1)])
    said: list[str] = []
    end_of_run.save_and_wait(client, tmp_path, say=said.append, alive=lambda: True)
    assert said[-1].startswith("saved the map") and client.polls == 4


def test_geometry_dying_during_the_save_ends_the_wait(tmp_path: Path) -> None:
    client = _Client([{GeometryCounter.SAVING: 1.0}])
    with pytest.raises(RunError, match="died while saving"):
        end_of_run.save_and_wait(client, tmp_path, say=lambda _: None, alive=lambda: client.polls < 3)


def test_a_refused_save_is_not_waited_for(tmp_path: Path) -> None:
    """Bad input to wait on: a save geometry refuses (e.g. checkpoint_failed) raises at once."""
    client = _Client([{}], control_error="checkpoint_failed")
    with pytest.raises(QueryError, match="checkpoint_failed"):
        end_of_run.save_and_wait(client, tmp_path, say=lambda _: None, alive=lambda: True)


def test_a_mesh_too_large_for_one_reply_is_built_from_the_saved_map(tmp_path: Path) -> None:
    volume = SemanticVolume(VolumeParams(voxel_size_m=0.05))
    for frame in open_source("synthetic:seed=1,frames=4,width=80,height=60,lap=4"):
        volume.integrate(frame)
    save_map(tmp_path / "map", volume, RegionDictionary("none", 1))
    said: list[str] = []
    mesh = end_of_run.fetch_mesh(_Client([{}]), tmp_path / "map", say=said.append)
    expected = volume.extract_mesh()
    assert len(mesh.triangles) == len(expected.triangles) > 0
    np.testing.assert_allclose(np.sort(mesh.vertices, axis=0), np.sort(expected.vertices, axis=0))
    assert "too large" in said[0]
    with pytest.raises(QueryError):  # any other refusal is not papered over
        end_of_run.fetch_mesh(_Client([{}], mesh_error="no_map"), tmp_path / "map", say=said.append)
