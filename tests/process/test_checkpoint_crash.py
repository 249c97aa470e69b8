"""A writer killed in the middle of a checkpoint (a real process, ``os._exit`` after half the new
file is on disk): the newest and the previous checkpoint both still load, the half-written
temporary file is never read, and the next save removes it once it is stale."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from openfusion.mapping import (
    RegionDictionary,
    SemanticVolume,
    VolumeParams,
    load_latest_map,
    load_map,
    mapfile,
    save_map,
)
from openfusion.mapping.mapfile import previous_map_path

pytestmark = pytest.mark.timeout(120)

_WRITER = textwrap.dedent(
    """
    import os, sys
    import numpy as np
    from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams, save_map

    target = sys.argv[1]
    volume = SemanticVolume(VolumeParams(voxel_size_m=0.1, initial_block_count=8))
    dictionary = RegionDictionary("none", 1)
    save_map(target, volume, dictionary, {"v": 1})
    save_map(target, volume, dictionary, {"v": 2})
    real_savez = np.savez

    def die_half_way(fh, **arrays):
        real_savez(fh, **arrays)
        fh.truncate(fh.tell() // 2)
        fh.flush()
        os._exit(17)  # killed: no exception handler, no clean-up runs

    np.savez = die_half_way
    save_map(target, volume, dictionary, {"v": 3})
    """
)


def test_killed_writer_leaves_both_checkpoints_loadable(tmp_path: Path) -> None:
    target = tmp_path / "m.npz"
    done = subprocess.run(
        [sys.executable, "-c", _WRITER, str(target)], capture_output=True, text=True, timeout=90, check=False
    )
    assert done.returncode == 17, done.stderr
    leftovers = sorted(tmp_path.glob(".m.npz.*.tmp"))
    assert len(leftovers) == 1 and leftovers[0].stat().st_size > 0
    assert load_map(target).meta["v"] == 2
    assert load_map(previous_map_path(target)).meta["v"] == 1
    assert load_latest_map(target).meta["v"] == 2

    old = time.time() - mapfile.STALE_TEMP_S - 1
    os.utime(leftovers[0], (old, old))
    save_map(target, SemanticVolume(VolumeParams(voxel_size_m=0.1, initial_block_count=8)),
             RegionDictionary("none", 1), {"v": 3})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz", "m.prev.npz"]
    assert load_map(target).meta["v"] == 3 and load_map(previous_map_path(target)).meta["v"] == 2
