"""A kill -9 of the geometry *service* while it writes a periodic checkpoint, then a restart: nothing
the last completed checkpoint held is lost.

Geometry runs as its own process with a checkpoint every 0.3 s, a memory budget smaller than the
map (tiles are paged out into the store's generation being built while checkpoints write), and a
bridge playing a walk through two rooms of the synthetic building at full speed. The test waits for the event, not for a time: geometry's
health says a checkpoint is being written (``saving`` 1) after at least two completed ones; it
then sends SIGKILL at once. The map folder must then hold exactly the map of the frames its last
committed checkpoint names (voxel for voxel against the same frames integrated here), at least the
checkpoint the health named as the last completed one; a restarted geometry loads it and says so
(``checkpoint_last_frame_id``, ``frames_integrated``, the same blocks).
"""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest
from e2e_support import Env

from openfusion.mapping import CapacityError, SemanticVolume, load_map
from openfusion.services.geometry.section import GeometrySection
from openfusion.sources import open_source
from openfusion.testing.bus import subprocess_env, wait_until
from openfusion.wire.counters import GeometryCounter

pytestmark = pytest.mark.timeout(600)

# Two rooms of the synthetic building and the corridor, walked through and the first room revisited.
SOURCE = "synthetic:building,rooms=2,frames=90,width=160,height=120"
SETTINGS = {"checkpoint_period_s": 0.3, "memory_budget_mb": 40.0}


def _sorted(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    order = np.lexsort(arrays["block_coords"].T)
    return {k: v[order] for k, v in arrays.items()}


def _reference(last_frame_id: int) -> tuple[dict[str, np.ndarray], int]:
    """The frames 0..last_frame_id integrated here with geometry's volume parameters, its budget
    included, and the frames of them that budget refused: a frame that needs more blocks at once
    than the budget holds is refused whole (``CapacityError``, counted, nothing written), the same
    frames here as in the service (paging follows the frames alone; paging changes no voxel)."""
    volume = SemanticVolume(GeometrySection(**SETTINGS).volume_params())
    refused = 0
    for f in open_source(SOURCE):
        if f.frame_id > last_frame_id:
            break
        try:
            volume.integrate(f)
        except CapacityError:
            refused += 1
    arrays = volume.to_arrays()
    volume.close()
    return arrays, refused


def test_sigkill_of_geometry_during_a_periodic_checkpoint_loses_nothing_committed(tmp_path: Path) -> None:
    env = Env(tmp_path)
    flags = ("--checkpoint-period-s", str(SETTINGS["checkpoint_period_s"]),
             "--memory-budget-mb", str(SETTINGS["memory_budget_mb"]))
    try:
        env.start("geometry", *flags)
        env.wait_alive("geometry")
        env.cluster.start("bridge", ["--source", SOURCE, "--rate-hz", "0"], env=subprocess_env(HF_HUB_OFFLINE="1"))

        def writing_a_checkpoint() -> object:
            stats = env.health().get("geometry")
            if stats is None:
                return None
            c = stats.counters
            if c.get(GeometryCounter.CHECKPOINTS, 0) >= 2 and c.get(GeometryCounter.SAVING, 0) == 1:
                return stats
            return None

        seen = wait_until(writing_a_checkpoint, timeout_s=300, interval_s=0.01,
                          describe=lambda: str(env.health().get("geometry")))
        geometry = env.cluster.processes.pop("geometry")
        geometry.proc.send_signal(signal.SIGKILL)
        geometry.proc.wait(30)
        assert geometry.proc.returncode == -signal.SIGKILL
        env.cluster.stop("bridge")
        env.cluster.processes.pop("bridge")
        completed = int(seen.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID))
        assert seen.counter(GeometryCounter.TILES_PAGED_OUT) > 0  # the budget was in play

        folder = env.map_dir / env.map_id
        loaded = load_map(folder)
        held = int(loaded.meta["last_frame_id"])
        # The checkpoint being written when the signal landed is either absent or complete (its
        # last transaction may have committed in the instant between the health reply and the kill).
        assert held >= completed >= 0
        print(f"killed while a checkpoint was written: the last completed one held frame {completed}, "
              f"the store holds frame {held}")
        reference, refused = _reference(held)
        # A playback: every frame up to it, once (but the frames too large for the budget; before
        # they were counted here, a kill that came after the first of them failed this test).
        assert loaded.meta["frames_integrated"] == held + 1 - refused
        got, expected = _sorted(loaded.volume.to_arrays()), _sorted(reference)
        assert len(got["block_coords"]) == len(expected["block_coords"]) > 0
        for name in expected:
            np.testing.assert_array_equal(got[name], expected[name], err_msg=name)
        loaded.volume.close()

        env.start("geometry", *flags)  # a restart loads the checkpoint and says what it holds
        env.wait_alive("geometry")
        restarted = env.health()["geometry"]
        assert restarted.counter(GeometryCounter.CHECKPOINT_LAST_FRAME_ID) == held
        assert restarted.counter(GeometryCounter.FRAMES_INTEGRATED) == held + 1 - refused
        assert restarted.counter(GeometryCounter.NUM_BLOCKS) == len(expected["block_coords"])
    finally:
        env.close()
