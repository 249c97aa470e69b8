"""A render asked for after a semantic update waits for geometry to apply that update
(openfusion.services.geometry.applied_updates), with geometry's service code called directly
(no bus).

What a user would notice: with a fast encoder, frame N+1 was rendered before geometry had written
frame N's labels, so its regions were made again as new keys (duplicates until the next merge
pass). Bad input tried: an update geometry refuses (confidences outside [0, 1]) still releases a
render waiting for its number; a render waiting for an update that never comes renders without it
after ``render_update_wait_s`` and is counted; numbered messages without their source are refused
(tests/unit/test_messages.py).
"""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from openfusion.bus.stats import ServiceStats
from openfusion.services.geometry.applied_updates import AppliedUpdates
from openfusion.services.geometry.service import GeometryConfig, GeometrySection, GeometryService
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld
from openfusion.testing.bus import wait_until
from openfusion.wire.counters import GeometryCounter
from openfusion.wire.schemas import RenderRequest, RgbdFrame, SemanticUpdate

FRAME = next(iter(SyntheticSource(SyntheticWorld(0), num_frames=1, width_px=80, height_px=60)))
SOURCE = "semantic-test"


def _geometry(wait_s: float) -> GeometryService:
    geo = GeometryService(GeometryConfig(map_id="unit", geometry=GeometrySection(
        load_on_start=False, render_update_wait_s=wait_s)))
    geo._runner = SimpleNamespace(stats=ServiceStats())  # noqa: SLF001 (counters without a bus)
    geo.on_frame(RgbdFrame.from_frame(FRAME))
    return geo


def _update(seq: int, *, conf: float = 0.9) -> SemanticUpdate:
    keys = (FRAME.instance.astype(np.int32) - 1).clip(-1, 5)
    return SemanticUpdate(frame_id=FRAME.frame_id, T_world_cam=FRAME.T_world_cam,
                          **SemanticUpdate.intrinsics_fields(FRAME.intrinsics), key_map=keys,
                          conf_map=np.where(keys >= 0, conf, 0.0).astype(np.float32),
                          new_keys=np.arange(6, dtype=np.int32), source=SOURCE, seq=seq)


def _render_request(after_seq: int) -> RenderRequest:
    return RenderRequest(frame_id=1, T_world_cam=FRAME.T_world_cam, after_update_source=SOURCE,
                         after_update_seq=after_seq, **RenderRequest.intrinsics_fields(FRAME.intrinsics))


def test_a_render_after_an_update_waits_for_it_and_shows_its_labels() -> None:
    geo = _geometry(wait_s=5.0)
    assert (geo.handle_render(_render_request(0)).key_map < 0).all()  # no update asked for: at once, unlabelled
    replies = []
    render = threading.Thread(target=lambda: replies.append(geo.handle_render(_render_request(1))), daemon=True)
    render.start()
    wait_until(lambda: geo._updates.waiting == 1, timeout_s=10, describe=lambda: "the render never waited")  # noqa: SLF001
    geo.on_update(_update(1))  # the update the render asked for
    render.join(10)
    assert replies and (replies[0].key_map >= 0).mean() > 0.3  # rendered after it: the frame's labels
    assert geo._runner.stats.counters.get(GeometryCounter.RENDER_UPDATE_WAIT_TIMEOUTS, 0) == 0  # noqa: SLF001


def test_an_update_that_never_comes_delays_the_render_once_and_is_counted() -> None:
    geo = _geometry(wait_s=0.05)
    reply = geo.handle_render(_render_request(3))
    assert (reply.key_map < 0).all()
    assert geo._runner.stats.counters[GeometryCounter.RENDER_UPDATE_WAIT_TIMEOUTS] == 1  # noqa: SLF001


def test_a_refused_update_still_releases_the_render_waiting_for_it() -> None:
    geo = _geometry(wait_s=5.0)
    with pytest.raises(ValueError, match="conf_map"):
        geo.on_update(_update(1, conf=1.5))  # refused: the subscription logs and counts it
    assert geo._updates.wait(SOURCE, 1, timeout_s=0.0)  # noqa: SLF001 (taken: no render waits for it)
    assert (geo.handle_render(_render_request(1)).key_map < 0).all()  # and the map was not written


def test_applied_updates_per_source() -> None:
    marks = AppliedUpdates()
    assert marks.wait("a", 0, timeout_s=0.0)  # unnumbered: never waited for
    marks.applied("a", 2)
    assert marks.wait("a", 1, timeout_s=0.0) and marks.wait("a", 2, timeout_s=0.0)
    assert not marks.wait("a", 3, timeout_s=0.0) and not marks.wait("b", 1, timeout_s=0.0)
    marks.applied("a", 1)  # an older number never moves the mark back
    assert marks.wait("a", 2, timeout_s=0.0)
    marks.applied("", 5)  # no source: counts for nothing
    assert not marks.wait("", 5, timeout_s=0.0)
