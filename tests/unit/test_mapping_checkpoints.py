"""Checkpoints: save_map keeps the previous file, load_latest_map falls back to it, torn writes
leave both files loadable and no temporary file behind."""

from __future__ import annotations

import errno
import logging
import os
import time
from pathlib import Path

import numpy as np
import pytest

from openfusion.frame import CameraIntrinsics
from openfusion.mapping import (
    MapFormatError,
    RegionDictionary,
    SemanticVolume,
    VolumeParams,
    load_latest_map,
    load_map,
    mapfile,
    previous_map_path,
    save_map,
)
from openfusion.mapping.mapfile import MAP_FILE_NAME
from openfusion.poses import look_at
from openfusion.testing.analytic_scene import AnalyticScene, Box, Room, category_embedding

K = CameraIntrinsics(80, 60, 65.6, 65.6, 39.5, 29.5)
DIM = 8
LOGGER = "openfusion.mapping.mapfile"


@pytest.fixture(scope="module")
def maps() -> tuple[tuple[SemanticVolume, RegionDictionary], tuple[SemanticVolume, RegionDictionary]]:
    """Two states of one small map: after one frame, and after a second one plus a region."""
    scene = AnalyticScene(room=Room(size_m=(3.0, 3.0, 2.5)), boxes=[Box((0.8, 1.8, 0.0), (1.4, 2.3, 0.8), 10, "chair")])
    params = VolumeParams(voxel_size_m=0.08, initial_block_count=64)
    first = SemanticVolume(params)
    first.integrate(scene.make_frame(look_at((1.5, 0.3, 1.4), (1.5, 2.0, 0.4)), K, frame_id=0))
    d1 = RegionDictionary("analytic-test", DIM)
    d1.add(category_embedding("wall", DIM), label="wall")
    second = SemanticVolume.from_arrays(params, first.to_arrays())
    second.integrate(scene.make_frame(look_at((0.5, 0.5, 1.3), (1.5, 2.0, 0.4)), K, frame_id=1))
    d2 = RegionDictionary.from_snapshot(d1.snapshot())
    d2.add(category_embedding("chair", DIM), label="chair")
    return (first, d1), (second, d2)


def _same_volume(a: SemanticVolume, b: SemanticVolume) -> None:
    xa, xb = a.to_arrays(), b.to_arrays()
    oa, ob = np.lexsort(xa["block_coords"].T), np.lexsort(xb["block_coords"].T)
    for name in xa:
        np.testing.assert_array_equal(xa[name][oa], xb[name][ob])


def _two_checkpoints(maps, path: Path) -> Path:  # noqa: ANN001
    (v1, d1), (v2, d2) = maps
    save_map(path, v1, d1, {"v": 1, "last_frame_id": 0})
    return save_map(path, v2, d2, {"v": 2, "last_frame_id": 1})


def _flip_middle(path: Path) -> None:
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 16] = bytes(b ^ 0xFF for b in data[mid : mid + 16])
    path.write_bytes(bytes(data))


def _temps(folder: Path) -> list[str]:
    return sorted(n for n in os.listdir(folder) if n.endswith(".tmp"))


def test_save_keeps_the_previous_checkpoint(maps, tmp_path: Path) -> None:  # noqa: ANN001
    """Version-1 files (an ``.npz`` path): the first save makes one file; each later one moves the
    file it replaces to ``.prev``. (Version-2 stores keep no ``.prev``: mapfile's docstring.)"""
    (v1, d1), _ = maps
    folder = tmp_path / "site"
    target = save_map(folder / MAP_FILE_NAME, v1, d1, {"v": 1})
    assert os.listdir(folder) == [MAP_FILE_NAME]
    _two_checkpoints(maps, folder / MAP_FILE_NAME)
    assert previous_map_path(folder) == folder / "map.ofz.prev.npz"
    assert sorted(os.listdir(folder)) == ["map.ofz.npz", "map.ofz.prev.npz"]
    assert load_map(target).meta["v"] == 2 and load_map(previous_map_path(target)).meta["v"] == 1
    save_map(tmp_path / "one.npz", v1, d1, keep_previous=False)
    save_map(tmp_path / "one.npz", v1, d1, keep_previous=False)
    assert not previous_map_path(tmp_path / "one.npz").exists()


def test_corrupt_newest_checkpoint_falls_back_to_the_previous(maps, tmp_path: Path, caplog) -> None:  # noqa: ANN001
    """Flipped bytes in the middle of the newest file: a strict load refuses it, load_latest_map
    says so in one line and returns the previous map, equal to what was saved before."""
    (v1, d1), _ = maps
    target = _two_checkpoints(maps, tmp_path / "m.npz")
    _flip_middle(target)
    with pytest.raises(MapFormatError):
        load_map(target)
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        loaded = load_latest_map(target)
    lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"checkpoint {target} is corrupt (")
    assert lines[0].endswith(f"; loading the previous one {previous_map_path(target)} "
                             "(the corrupt file is kept as m.corrupt.npz)")
    aside = tmp_path / "m.corrupt.npz"
    assert loaded.path == previous_map_path(target)
    assert loaded.meta["v"] == 1 and loaded.meta["last_frame_id"] == 0
    _same_volume(loaded.volume, v1)
    assert loaded.dictionary.snapshot().labels == d1.snapshot().labels
    # The corrupt file is set aside, so the next checkpoint keeps the good one as .prev: two good.
    assert aside.exists() and not target.exists()
    save_map(target, loaded.volume, loaded.dictionary, meta={"v": 3})
    assert load_map(target).meta["v"] == 3 and load_map(previous_map_path(target)).meta["v"] == 1


def test_newest_missing_between_the_renames_loads_the_previous(maps, tmp_path: Path, caplog) -> None:  # noqa: ANN001
    """A crash between moving the newest file to ``.prev`` and renaming the new one in leaves
    only ``.prev``: it is loaded, with the line saying the newest is missing."""
    target = _two_checkpoints(maps, tmp_path / "m.npz")
    os.replace(target, previous_map_path(target))
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        assert load_latest_map(target).meta["v"] == 2
    assert f"checkpoint {target} is missing" in caplog.text


def test_both_checkpoints_corrupt_names_both_reasons(maps, tmp_path: Path) -> None:  # noqa: ANN001
    target = _two_checkpoints(maps, tmp_path / "m.npz")
    _flip_middle(target)
    previous_map_path(target).write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(MapFormatError) as info:
        load_latest_map(target)
    message = str(info.value)
    assert str(target) in message and str(previous_map_path(target)) in message
    assert message.count("corrupt (") == 2
    # Only a corrupt newest file and no previous one: the reason and that there is none.
    previous_map_path(target).unlink()
    with pytest.raises(MapFormatError, match="no previous checkpoint"):
        load_latest_map(target)
    with pytest.raises(MapFormatError, match="no map file"):
        load_latest_map(tmp_path / "nowhere")


def test_torn_write_leaves_both_checkpoints_and_no_temp_file(maps, tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """The disk fills half-way through writing a third checkpoint: the error propagates, the two
    checkpoints are untouched and the half-written temporary file is gone."""
    (v1, _), _ = maps
    target = _two_checkpoints(maps, tmp_path / "m.npz")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real_savez = np.savez

    def half_then_full(fh, **arrays) -> None:  # noqa: ANN001
        real_savez(fh, **arrays)
        fh.truncate(fh.tell() // 2)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez", half_then_full)
    with pytest.raises(OSError, match="No space left"):
        save_map(target, v1, RegionDictionary("analytic-test", DIM), {"v": 3})
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert load_map(target).meta["v"] == 2 and load_map(previous_map_path(target)).meta["v"] == 1


def test_failed_final_rename_puts_the_newest_back(maps, tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """Renaming the new file in fails after the newest was moved to ``.prev``: it is renamed back
    so a strict reader still finds the newest map at the target; no temporary file remains."""
    (v1, d1), _ = maps
    target = _two_checkpoints(maps, tmp_path / "m.npz")
    real_replace = os.replace

    def refuse_temp(src, dst) -> None:  # noqa: ANN001
        if str(src).endswith(".tmp"):
            raise OSError(errno.EROFS, "Read-only file system", str(dst))
        real_replace(src, dst)

    monkeypatch.setattr(mapfile.os, "replace", refuse_temp)
    with pytest.raises(OSError, match="Read-only"):
        save_map(target, v1, d1, {"v": 3})
    monkeypatch.undo()
    assert load_map(target).meta["v"] == 2
    assert _temps(tmp_path) == []


def test_leftover_temp_file_of_a_killed_writer_is_ignored_then_removed(maps, tmp_path: Path) -> None:  # noqa: ANN001
    """A process killed mid-write leaves ``.m.npz.*.tmp`` (half a map): loading never looks at it,
    and the next save removes it once it is STALE_TEMP_S old (a younger one may be a save still
    writing, in another process, and is left alone)."""
    (v1, d1), _ = maps
    target = _two_checkpoints(maps, tmp_path / "m.npz")
    half = target.read_bytes()[: target.stat().st_size // 2]
    stale, young = tmp_path / ".m.npz.killed01.tmp", tmp_path / ".m.npz.writing1.tmp"
    stale.write_bytes(half)
    young.write_bytes(half)
    old = time.time() - mapfile.STALE_TEMP_S - 10
    os.utime(stale, (old, old))
    assert load_latest_map(target).meta["v"] == 2
    save_map(target, v1, d1, {"v": 3})
    assert _temps(tmp_path) == [young.name]
    assert load_map(target).meta["v"] == 3 and load_map(previous_map_path(target)).meta["v"] == 2
