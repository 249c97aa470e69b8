"""The geometry service's checkpoints, its logic called directly (no Zenoh session): the last
integrated frame id and every block round-trip through the tile store, a corrupt tile stops the
start, an older checkpoint file still loads, and a full disk leaves the service mapping in memory
with the failure counted and ``control/save`` answered with an error naming the store.

A stand-in runner (:class:`_Runner`: real :class:`ServiceStats`, no bus) lets the health
counters and the periodic checkpoint loop run as they do in the service. ``CheckpointFailed`` is
a ``RequestError``: a queryable answers it with ``reply_err`` (its code and reason)."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path

import lmdb
import numpy as np
import pytest

from openfusion.bus.stats import ServiceStats
from openfusion.mapping import MapFormatError, RegionDictionary, load_map, save_map
from openfusion.mapping.mapfile import MAP_FILE_NAME
from openfusion.mapping.tilestore import TileStore
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


def test_last_frame_id_round_trips_and_a_corrupt_tile_stops_the_start(map_dir: Path) -> None:
    """Each checkpoint records the id of the last frame integrated into it; a new service reads
    it back (attribute + health counter) with every block. A tile whose bytes were flipped on disk
    is refused at start with a MapFormatError naming the store (the service does not map over a
    corrupt map)."""
    geo, runner = _service(map_dir)
    assert geo.checkpoint_last_frame_id is None and runner.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == -1
    _integrate(geo, FRAMES[:2])
    _save(geo)
    assert geo.checkpoint_last_frame_id == FRAMES[1].frame_id
    _integrate(geo, FRAMES[2:4])
    assert "saved to" in _save(geo)
    assert runner.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == FRAMES[3].frame_id
    assert runner.counter(GeometryCounter.CHECKPOINTS) == 2
    folder = map_dir / "ckpt"
    assert load_map(folder).meta["last_frame_id"] == FRAMES[3].frame_id
    assert load_map(folder).meta["frames_integrated"] == 4
    arrays = geo.volume.to_arrays()
    geo.close()

    restarted, runner2 = _service(map_dir, load=True)
    assert restarted.checkpoint_last_frame_id == restarted.last_frame_id == FRAMES[3].frame_id
    assert runner2.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == FRAMES[3].frame_id
    assert restarted.volume.num_blocks_total == len(arrays["block_coords"])
    restored = restarted.volume.to_arrays()
    o1, o2 = np.lexsort(arrays["block_coords"].T), np.lexsort(restored["block_coords"].T)
    for name, arr in arrays.items():
        np.testing.assert_array_equal(arr[o1], restored[name][o2])
    restarted.close()

    with TileStore(folder / "map.ofz") as store:  # flip bytes inside one committed tile
        tile, blob = next(store.iter_committed())
        bad = bytearray(blob)
        bad[len(bad) // 2] ^= 0xFF
        entry = store.committed_entry_key(tile)
        with store.env.begin(write=True, db=store._tiles) as txn:
            txn.put(entry, bytes(bad))
    with pytest.raises(MapFormatError, match="map.ofz tile"):
        _service(map_dir, load=True)


def test_a_version_1_checkpoint_still_loads_and_the_next_one_is_a_store(map_dir: Path) -> None:
    """A checkpoint written by an older build (``map.ofz.npz``) is loaded on start; the next
    checkpoint writes the tile store with every block, and a restart then reads the store."""
    geo, _ = _service(map_dir)
    _integrate(geo, FRAMES[:3])
    folder = map_dir / "ckpt"
    save_map(folder / MAP_FILE_NAME, geo.volume, RegionDictionary("none", 1),
             meta={"last_frame_id": FRAMES[2].frame_id, "frames_integrated": 3})
    n_blocks = geo.volume.num_blocks
    geo.volume.close()
    old, _ = _service(map_dir, load=True)
    assert old.last_frame_id == FRAMES[2].frame_id and old.volume.num_blocks == n_blocks
    _integrate(old, FRAMES[3:4])
    _save(old)
    assert (folder / "map.ofz" / "data.mdb").is_file()
    total = old.volume.num_blocks_total
    old.close()
    new, _ = _service(map_dir, load=True)
    assert new.last_frame_id == FRAMES[3].frame_id and new.volume.num_blocks_total == total
    new.close()


def _assert_failed_save(geo: GeometryService, folder: Path, reason: str) -> None:
    with pytest.raises(CheckpointFailed) as info:
        _save(geo)
    assert info.value.code == "checkpoint_failed"
    assert str(folder / "map.ofz") in info.value.reason and reason in info.value.reason


def test_a_failed_commit_keeps_mapping_in_memory(map_dir: Path, monkeypatch: pytest.MonkeyPatch, caplog) -> None:  # noqa: ANN001
    """The store cannot be written (disk full, simulated inside LMDB's transaction): control/save is
    refused naming the store and the reason, one error line is logged, ``checkpoint_failures``
    counts it (the periodic loop's try too), the in-memory map is untouched, frames keep being
    integrated, the last good checkpoint stays loadable, and the next checkpoint after the disk
    has room writes every tile the failed ones did not."""
    geo, runner = _service(map_dir, period_s=0.001)
    _integrate(geo, FRAMES[:2])
    _save(geo)
    _integrate(geo, FRAMES[2:3])
    folder = map_dir / "ckpt"
    arrays, version = geo.volume.to_arrays(), geo.map_version

    def disk_full(*_args: object, **_kwargs: object) -> None:
        raise lmdb.DiskError("mdb_txn_commit: No space left on device")

    monkeypatch.setattr(TileStore, "_commit", disk_full)
    with caplog.at_level(logging.ERROR):
        _assert_failed_save(geo, folder, "No space left on device")
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].startswith(f"geometry: checkpoint to {folder / 'map.ofz'} failed: ")
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
    assert load_map(folder).meta["last_frame_id"] == FRAMES[1].frame_id

    monkeypatch.undo()
    _save(geo)
    assert runner.counter(GeometryCounter.CHECKPOINTS) == 2
    final = geo.volume.to_arrays()
    geo.close()
    loaded = load_map(folder)
    assert loaded.meta["last_frame_id"] == FRAMES[3].frame_id
    restored = loaded.volume.to_arrays()
    o1, o2 = np.lexsort(final["block_coords"].T), np.lexsort(restored["block_coords"].T)
    for name, arr in final.items():
        np.testing.assert_array_equal(arr[o1], restored[name][o2])
