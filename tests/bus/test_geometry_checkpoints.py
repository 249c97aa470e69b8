"""The geometry service's checkpoints, its logic called directly (no Zenoh session): the newest
checkpoint falls back to the previous one on start, the last integrated frame id round-trips,
and a full or read-only disk leaves the service mapping in memory with the failure counted and
``control/save`` answered with an error naming the path.

A stand-in runner (:class:`_Runner`: real :class:`ServiceStats`, no bus) lets the health
counters and the periodic checkpoint loop run as they do in the service. ``CheckpointFailed`` is
a ``RequestError``: a queryable answers it with ``reply_err`` (its code and reason)."""

from __future__ import annotations

import errno
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from openfusion.bus.stats import ServiceStats
from openfusion.mapping import load_map, mapfile, previous_map_path
from openfusion.mapping.mapfile import MAP_FILE_NAME
from openfusion.services.geometry.service import (
    CheckpointFailed,
    GeometryConfig,
    GeometrySection,
    GeometryService,
)
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.schemas import ControlRequest, RgbdFrame

pytestmark = pytest.mark.timeout(120)

FRAMES = list(SyntheticSource(SyntheticWorld(0), num_frames=5, width_px=80, height_px=60))


class _Runner:
    """What the geometry service uses of a ServiceRunner, without a bus: stats and wait()."""

    def __init__(self, iterations: int = 0) -> None:
        self.stats = ServiceStats()
        self._left = iterations

    def wait(self, timeout_s: float | None = None) -> bool:
        self._left -= 1
        if self._left < 0:
            return True
        time.sleep(timeout_s or 0.0)
        return False

    def publisher(self, *_args: object, **_kwargs: object) -> None:
        return None

    def subscriber(self, *_args: object, **_kwargs: object) -> None:
        return None

    def queryable(self, *_args: object, **_kwargs: object) -> None:
        return None

    def counter(self, name: str) -> float:
        return self.stats.counters.get(name, 0.0)


def _service(map_dir: Path, *, load: bool = False, period_s: float = 0.0) -> tuple[GeometryService, _Runner]:
    section = GeometrySection(
        map_dir=map_dir, load_on_start=load, checkpoint_period_s=period_s, voxel_size_m=0.08, initial_block_count=256
    )
    geo = GeometryService(GeometryConfig(map_id="ckpt", geometry=section))
    runner = _Runner()
    geo.setup(runner)  # type: ignore[arg-type]
    return geo, runner


def _integrate(geo: GeometryService, frames: list) -> None:  # noqa: ANN001
    for f in frames:
        geo.on_frame(RgbdFrame.from_frame(f))


def _save(geo: GeometryService) -> str:
    return geo.handle_control(ControlRequest(action="save"), action="save").message


@pytest.fixture
def map_dir(tmp_path: Path) -> Iterator[Path]:
    folder = tmp_path / "maps"
    yield folder
    for p in (folder, folder / "ckpt"):
        if p.exists():
            p.chmod(0o755)  # a read-only test folder must not stop tmp_path's clean-up


def test_last_frame_id_round_trips_and_a_corrupt_checkpoint_falls_back_on_start(map_dir: Path, caplog) -> None:  # noqa: ANN001
    """Each checkpoint records the id of the last frame integrated into it; a new service reads
    it back (attribute + health counter). With the newest checkpoint corrupted, the service
    starts from the previous one, says so in one line, and reports that one's frame id."""
    geo, runner = _service(map_dir)
    assert geo.checkpoint_last_frame_id is None and runner.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == -1
    _integrate(geo, FRAMES[:2])
    _save(geo)
    assert geo.checkpoint_last_frame_id == FRAMES[1].frame_id
    _integrate(geo, FRAMES[2:4])
    assert "saved to" in _save(geo)
    assert runner.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == FRAMES[3].frame_id
    assert runner.counter(GeometryCounter.CHECKPOINTS) == 2
    target = map_dir / "ckpt" / MAP_FILE_NAME
    assert load_map(target).meta["last_frame_id"] == FRAMES[3].frame_id
    assert load_map(target).meta["frames_integrated"] == 4

    restarted, runner2 = _service(map_dir, load=True)
    assert restarted.checkpoint_last_frame_id == restarted.last_frame_id == FRAMES[3].frame_id
    assert runner2.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == FRAMES[3].frame_id
    assert restarted.volume.num_blocks == geo.volume.num_blocks

    data = bytearray(target.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 16] = bytes(b ^ 0xFF for b in data[mid : mid + 16])
    target.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        fallback, runner3 = _service(map_dir, load=True)
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, warnings
    assert warnings[0].startswith(f"checkpoint {target} is corrupt (")
    assert warnings[0].endswith(f"); loading the previous one {previous_map_path(target)} "
                                "(the corrupt file is kept as map.ofz.corrupt.npz)")
    assert fallback.checkpoint_last_frame_id == FRAMES[1].frame_id
    assert runner3.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == FRAMES[1].frame_id
    assert load_map(previous_map_path(target)).volume.num_blocks == fallback.volume.num_blocks


def _read_only(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ``folder`` read-only. As root (how these tests run in CI containers) chmod 0o555 does
    not stop writes; then the read-only file system is simulated: creating the temporary file
    raises ``OSError(EROFS)``, what a read-only mount answers."""
    folder.chmod(0o555)
    probe = folder / ".probe"
    try:
        probe.write_bytes(b"")
    except PermissionError:
        return  # not root: the chmod does it
    probe.unlink()

    def refuse(*_args: object, **_kwargs: object) -> None:
        raise OSError(errno.EROFS, "Read-only file system", str(folder))

    monkeypatch.setattr(mapfile.tempfile, "mkstemp", refuse)


def _assert_failed_save(geo: GeometryService, folder: Path, reason: str) -> None:
    with pytest.raises(CheckpointFailed) as info:
        _save(geo)
    assert info.value.code == "checkpoint_failed"
    assert str(folder / MAP_FILE_NAME) in info.value.reason and reason in info.value.reason


def test_read_only_folder_keeps_mapping_in_memory(map_dir: Path, monkeypatch: pytest.MonkeyPatch, caplog) -> None:  # noqa: ANN001
    """A checkpoint into a read-only folder: control/save is refused naming the path and the
    reason, one error line is logged, ``checkpoint_failures`` counts it (the periodic loop's try
    too), the in-memory map is untouched, frames keep being integrated, the last good checkpoint
    stays loadable, and saving works again once the folder is writable."""
    geo, runner = _service(map_dir, period_s=0.001)
    _integrate(geo, FRAMES[:2])
    _save(geo)
    _integrate(geo, FRAMES[2:3])
    folder = map_dir / "ckpt"
    arrays, version = geo.volume.to_arrays(), geo.map_version

    _read_only(folder, monkeypatch)
    with caplog.at_level(logging.ERROR):
        _assert_failed_save(geo, folder, "Read-only file system" if os.geteuid() == 0 else "Permission denied")
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].startswith(f"geometry: checkpoint to {folder / MAP_FILE_NAME} failed: ")
    assert runner.counter(GeometryCounter.CHECKPOINT_FAILURES) == 1
    loop_runner = _Runner(iterations=1)
    loop_runner.stats = runner.stats
    geo.loop(loop_runner)  # type: ignore[arg-type]
    assert runner.counter(GeometryCounter.CHECKPOINT_FAILURES) == 2 and runner.stats.errors == 1
    assert geo.checkpoint_failures == 2

    assert geo.map_version == version
    for name, arr in geo.volume.to_arrays().items():
        np.testing.assert_array_equal(arr, arrays[name])
    _integrate(geo, FRAMES[3:4])
    assert geo.frames_integrated == 4 and geo.last_frame_id == FRAMES[3].frame_id
    assert sorted(os.listdir(folder)) == [MAP_FILE_NAME]
    assert load_map(folder).meta["last_frame_id"] == FRAMES[1].frame_id

    monkeypatch.undo()
    folder.chmod(0o755)
    _save(geo)
    assert load_map(folder).meta["last_frame_id"] == FRAMES[3].frame_id
    assert runner.counter(GeometryCounter.CHECKPOINTS) == 2


def test_disk_full_mid_write_leaves_no_temp_file(map_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk fills half-way through writing a checkpoint (simulated: the write stops at half the
    file and raises ENOSPC): refused with the reason, no temporary file left, both earlier
    checkpoints intact."""
    geo, runner = _service(map_dir)
    _integrate(geo, FRAMES[:1])
    _save(geo)
    _integrate(geo, FRAMES[1:2])
    _save(geo)
    folder = map_dir / "ckpt"
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    real_savez = np.savez

    def half_then_full(fh, **arrays) -> None:  # noqa: ANN001
        real_savez(fh, **arrays)
        fh.truncate(fh.tell() // 2)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez", half_then_full)
    _integrate(geo, FRAMES[2:3])
    _assert_failed_save(geo, folder, "No space left on device")
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    assert runner.counter(GeometryCounter.CHECKPOINT_FAILURES) == 1
    assert runner.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == FRAMES[1].frame_id
    assert load_map(folder).meta["last_frame_id"] == FRAMES[1].frame_id
    assert load_map(previous_map_path(folder)).meta["last_frame_id"] == FRAMES[0].frame_id
