"""What a replica holds while it copies its peer's checkpoint (services/geometry/start_buffer.py)
and how it takes it after the copy, with geometry's service code called directly (no bus).

Bad input tried: more frames than the buffer holds (the oldest are kept, the rest counted lost);
a live frame the copy already holds (a duplicate: counted, not integrated twice); a held update
geometry refuses (confidences outside [0, 1]: logged, the items after it still taken); a live
bridge restarted during the copy (its ids from 0 again: new frames, not duplicates).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from openfusion.bus.stats import ServiceStats
from openfusion.services.geometry.service import GeometryConfig, GeometrySection, GeometryService
from openfusion.services.geometry.start_buffer import FRAME, UPDATE, StartBuffer
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.schemas import RgbdFrame, SemanticUpdate

FRAMES = [RgbdFrame.from_frame(f, with_instance=False)  # live: no playback, no predecessor
          for f in SyntheticSource(SyntheticWorld(0), num_frames=5, width_px=64, height_px=48)]


def test_the_buffer_keeps_the_oldest_in_order_and_counts_the_rest() -> None:
    held = StartBuffer(max_frames=2)
    assert held.offer(FRAME, "f0") and held.offer(UPDATE, "u0") and held.offer(FRAME, "f1")
    assert held.offer(FRAME, "f2")  # over the limit: counted, not kept
    assert held.frames == 2 and held.frames_lost == 1 and held.updates == 1
    seen: list[tuple[str, str]] = []

    def handle(kind: str, msg: str) -> None:
        if msg == "u0":
            raise ValueError("a bad update")  # logged; the next item is still handled
        seen.append((kind, msg))

    held.release(handle)
    assert seen == [(FRAME, "f0"), (FRAME, "f1")]
    assert not held.offer(FRAME, "f3")  # released: the caller handles what comes now


def _geometry_after_copy() -> tuple[GeometryService, SimpleNamespace]:
    """A geometry (counters without a bus) whose copy held frames 0-2 of ``FRAMES``."""
    geo = GeometryService(GeometryConfig(map_id="unit", geometry=GeometrySection(load_on_start=False)))
    runner = SimpleNamespace(stats=ServiceStats())
    geo._runner = runner  # noqa: SLF001
    for msg in FRAMES[:3]:
        geo.on_frame(msg)
    return geo, runner


def test_after_the_copy_a_live_frame_it_holds_is_a_duplicate_and_the_rest_are_taken_once() -> None:
    geo, runner = _geometry_after_copy()
    held = StartBuffer(max_frames=8)
    bad = SemanticUpdate(frame_id=2, T_world_cam=FRAMES[2].T_world_cam, **SemanticUpdate.intrinsics_fields(
        FRAMES[2].to_frame().intrinsics), key_map=np.zeros((48, 64), np.int32),
        conf_map=np.full((48, 64), 1.5, np.float32), new_keys=np.zeros(0, np.int32))
    for kind, msg in ((FRAME, FRAMES[2]), (UPDATE, bad), (FRAME, FRAMES[3]), (FRAME, FRAMES[4])):
        held.offer(kind, msg)
    geo.release_held(runner, held)
    assert geo.frames_integrated == 5  # frames 3 and 4 once; frame 2 not again
    assert runner.stats.counters[GeometryCounter.FRAMES_DUPLICATE] == 1
    assert runner.stats.counters[GeometryCounter.PEER_COPY_FRAMES_HELD] == 3
    assert runner.stats.counters[GeometryCounter.PEER_COPY_FRAMES_LOST] == 0
    assert geo.updates_applied == 0  # the refused update wrote nothing
    geo.close()


def test_a_live_bridge_restarted_during_the_copy_has_its_new_frames_taken() -> None:
    """The copy holds frames 0-2; frame 2 comes again, then the bridge restarts and counts from 0:
    frames 0 and 1 of the new run are new (ids below the copy's last, after the ids went back)."""
    geo, runner = _geometry_after_copy()
    held = StartBuffer(max_frames=8)
    again = [msg.model_copy(update={"frame_id": i}) for i, msg in enumerate(FRAMES[3:5])]  # ids 0, 1
    for msg in (FRAMES[2], *again):
        held.offer(FRAME, msg)
    geo.release_held(runner, held)
    assert runner.stats.counters[GeometryCounter.FRAMES_DUPLICATE] == 1  # frame 2 of the old run only
    assert geo.frames_integrated == 5
    geo.close()


def test_a_bridge_restarted_before_the_first_held_frame_is_told_by_its_later_stamps() -> None:
    """The copy holds frames 0-2; the bridge restarted before anything was held: ids 0 and 1
    again, stamped after the copy's last frame. They are new, not duplicates."""
    geo, runner = _geometry_after_copy()
    assert geo.robots.get(FRAMES[0].robot, map_empty=False).last_stamp_ns == FRAMES[2].stamp_ns
    held = StartBuffer(max_frames=8)
    again = [msg.model_copy(update={"frame_id": i}) for i, msg in enumerate(FRAMES[3:5])]  # ids 0, 1
    assert all(msg.stamp_ns > FRAMES[2].stamp_ns for msg in again)
    for msg in again:
        held.offer(FRAME, msg)
    geo.release_held(runner, held)
    assert runner.stats.counters.get(GeometryCounter.FRAMES_DUPLICATE, 0) == 0
    assert geo.frames_integrated == 5
    geo.close()


def test_a_copy_without_recorded_stamps_tells_duplicates_by_id() -> None:
    """A checkpoint from before stamps were recorded: the restarted bridge's frames 0 and 1 look
    like the copy's (the id rule alone), as before; a checkpoint round trip keeps the stamp."""
    geo, runner = _geometry_after_copy()
    meta = geo.robots.to_meta()
    name, = meta["robots"]
    assert meta["robots"][name]["last_stamp_ns"] == FRAMES[2].stamp_ns
    del meta["robots"][name]["last_stamp_ns"]
    geo.robots.restore(meta, default_robot=name)
    held = StartBuffer(max_frames=8)
    for i, msg in enumerate(FRAMES[3:5]):
        held.offer(FRAME, msg.model_copy(update={"frame_id": i}))
    geo.release_held(runner, held)
    assert runner.stats.counters[GeometryCounter.FRAMES_DUPLICATE] == 2
    assert geo.frames_integrated == 3
    geo.close()
