"""A mapping process killed with SIGKILL in the middle of an incremental checkpoint into its tile
store (tiles paged out under a memory budget, checkpoints every two frames): the store loads, and
it holds exactly the map of the frames its last committed checkpoint says it holds (compared
with a fresh map of those frames, voxel for voxel). Then a second process goes on from it."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from openfusion.mapping import SemanticVolume, VolumeParams, load_map
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld

pytestmark = pytest.mark.timeout(180)

PARAMS = {"voxel_size_m": 0.04, "tile_blocks": 2, "memory_budget_mb": 9.0}
N_FRAMES = 14

_WRITER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from openfusion.mapping import RegionDictionary, SemanticVolume, VolumeParams, load_map
    from openfusion.mapping.mapstore import checkpoint
    from openfusion.mapping.tilestore import TileStore
    from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld

    folder, start, stop = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    frames = list(SyntheticSource(SyntheticWorld(0), num_frames=%(n)d, width_px=160, height_px=120))
    params = VolumeParams(**%(params)r)
    if start:
        volume = load_map(folder, writable=True).volume
    else:
        volume = SemanticVolume(params, store=TileStore(folder / "map.ofz"))
    dictionary = RegionDictionary("none", 1)
    for i in range(start, stop):
        volume.integrate(frames[i])
        if i %% 2 == 1:
            print(f"checkpoint {i + 1} started", flush=True)
            checkpoint(volume, dictionary, {"frames": i + 1})
            print(f"checkpoint {i + 1} committed", flush=True)
    print(f"paged in {volume.pager.stats.tiles_paged_in} out {volume.pager.stats.tiles_paged_out}", flush=True)
    """
) % {"n": N_FRAMES, "params": PARAMS}


def _reference(n: int) -> dict[str, np.ndarray]:
    volume = SemanticVolume(VolumeParams(**{**PARAMS, "memory_budget_mb": None}))
    for f in list(SyntheticSource(SyntheticWorld(0), num_frames=N_FRAMES, width_px=160, height_px=120))[:n]:
        volume.integrate(f)
    return volume.to_arrays()


def _assert_same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    oa, ob = np.lexsort(a["block_coords"].T), np.lexsort(b["block_coords"].T)
    assert len(oa) == len(ob)
    for name in a:
        np.testing.assert_array_equal(a[name][oa], b[name][ob], err_msg=name)


def test_sigkill_during_a_checkpoint_leaves_the_last_committed_one(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp_path), "0", str(N_FRAMES)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:  # kill as checkpoint 8 begins: 6 is committed, 8 is being written
        if line.startswith("checkpoint 8 started"):
            proc.send_signal(signal.SIGKILL)
            break
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL, err
    loaded = load_map(tmp_path)
    held = int(loaded.meta["frames"])
    assert held in (6, 8)  # 8 only if its commit finished before the signal landed
    _assert_same(loaded.volume.to_arrays(), _reference(held))
    loaded.volume.close()

    # A new process goes on from the store (its paged area discarded) and maps the rest.
    done = subprocess.run([sys.executable, "-c", _WRITER, str(tmp_path), str(held), str(N_FRAMES)],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    paged_in = int(done.stdout.split("paged in ")[1].split()[0])
    assert paged_in > 0  # the lazily loaded map's tiles came back as frames reached them
    final = load_map(tmp_path)
    assert final.meta["frames"] == N_FRAMES
    _assert_same(final.volume.to_arrays(), _reference(N_FRAMES))
