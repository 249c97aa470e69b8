"""Record/replay: bit-identical playback, truncated and corrupt files, foreign payloads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.sources import open_source
from openfusion.sources.record import FrameRecorder, RecordingError, ReplaySource, record_source
from openfusion.wire.codec import encode
from openfusion.wire.schemas import RgbdFrame, TextQuery


def _frame(i: int, *, with_instances: bool = True) -> Frame:
    rng = np.random.default_rng(i)
    T = np.eye(4)
    T[:3, 3] = [0.1 * i, np.pi, -1.0 / 3.0]  # values that a text format would round
    inst = rng.integers(0, 5, size=(12, 16), dtype=np.int32) if with_instances else None
    return Frame(
        frame_id=i,
        stamp_ns=1_700_000_000_000_000_000 + i * 33_333_333,
        color=rng.integers(0, 255, size=(12, 16, 3), dtype=np.uint8),
        depth=rng.random((12, 16), dtype=np.float32) * 4 if i % 2 else rng.integers(0, 65535, (12, 16), dtype=np.uint16),
        depth_scale=1.0 if i % 2 else 1000.0,
        intrinsics=CameraIntrinsics(16, 12, 10.1, 10.2, 7.3, 5.4),
        T_world_cam=T,
        instance=inst,
        instance_categories={1: "chair", 2: "office chair"} if with_instances else {},
        source="test",
    )


def _assert_same(a: Frame, b: Frame) -> None:
    assert (a.frame_id, a.stamp_ns, a.depth_scale, a.intrinsics, a.source) == (
        b.frame_id, b.stamp_ns, b.depth_scale, b.intrinsics, b.source,
    )  # fmt: skip
    for name in ("color", "depth", "T_world_cam"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), name
    assert (a.instance is None) == (b.instance is None)
    if a.instance is not None:
        assert a.instance.tobytes() == b.instance.tobytes()
    assert a.instance_categories == b.instance_categories


def test_replay_is_bit_identical(tmp_path: Path) -> None:
    """uint16 and float32 depth, instances, awkward floats: everything comes back byte for byte,
    including frames written as already-encoded bus payloads."""
    frames = [_frame(i, with_instances=i != 2) for i in range(5)]
    path = tmp_path / "run.ofrec"
    with FrameRecorder(path) as rec:
        for f in frames[:3]:
            rec.write(f)
        for f in frames[3:]:
            rec.write(encode(RgbdFrame.from_frame(f)))  # as the bridge records from the bus
    src = open_source(f"replay:{path}")
    assert len(src) == 5
    out = list(src)
    assert src.stats.yielded == 5 and src.stats.skipped == {}
    for a, b in zip(frames, out, strict=True):
        _assert_same(a, b)


def test_record_source_and_synthetic_round_trip(tmp_path: Path) -> None:
    """A synthetic stream recorded with record_source replays identically."""
    src = open_source("synthetic:seed=1,frames=3,width=32,height=24")
    n = record_source(src, tmp_path / "syn.ofrec")
    assert n == 3
    for a, b in zip(src, ReplaySource(tmp_path / "syn.ofrec"), strict=True):
        _assert_same(a, b)


@pytest.mark.parametrize("cut", [3, 40, -1])
def test_truncated_recording_stops_with_a_count(tmp_path: Path, cut: int) -> None:
    """Bad input: a file cut inside the last record's length prefix (3 bytes left), inside its
    payload, or missing its final byte: every complete record replays, then one
    truncated_record is counted and iteration ends without raising."""
    path = tmp_path / "cut.ofrec"
    with FrameRecorder(path) as rec:
        for i in range(3):
            rec.write(_frame(i))
        last_start = rec.bytes_written
    data = path.read_bytes()
    end = last_start - 4 - len(encode(RgbdFrame.from_frame(_frame(2))))  # start of record 2
    keep = {3: end + 3, 40: end + 40, -1: len(data) - 1}[cut]
    path.write_bytes(data[:keep])
    src = ReplaySource(path)
    assert len(src) == 2
    out = list(src)
    assert [f.frame_id for f in out] == [0, 1]
    assert src.stats.skipped == {"truncated_record": 1}


def _as_version_2(payload: bytes) -> bytes:
    """The frame as a build from before robots wrote it: schema version 2, no ``robot`` field."""
    import msgpack

    from openfusion.wire.codec import _unpack

    schema, _version, body, arraydata = _unpack(payload)
    del body["robot"]
    assert arraydata is not None
    return msgpack.packb({"arraydata": bytes(arraydata), "schema": schema, "version": 2, "body": body},
                         use_bin_type=True)


def test_a_recording_from_before_robots_still_replays(tmp_path: Path) -> None:
    """Recordings of v2 frames replay (their robot is the default one); on the bus a v2 frame is
    still refused as another version (bad input tried: a v2 payload decoded without accept_older)."""
    from openfusion.wire.codec import DecodeError, decode

    frames = [_frame(i) for i in range(3)]
    old = [_as_version_2(encode(RgbdFrame.from_frame(f))) for f in frames]
    from openfusion.sources.record import _HEADER, _LENGTH, FORMAT_VERSION, MAGIC

    path = tmp_path / "old.ofrec"  # written as that build's recorder did (this one records v3 only)
    path.write_bytes(_HEADER.pack(MAGIC, FORMAT_VERSION, 0) + b"".join(_LENGTH.pack(len(p)) + p for p in old))
    out = list(ReplaySource(path))
    assert len(out) == 3
    for a, b in zip(frames, out, strict=True):
        _assert_same(a, b)
    with pytest.raises(DecodeError, match="got version 2"):
        decode(old[0], expected=RgbdFrame)
    assert decode(old[0], expected=RgbdFrame, accept_older=True).robot == "robot0"


def test_corrupt_record_is_skipped_and_replay_continues(tmp_path: Path) -> None:
    """Bad input: garbage bytes inside record 1 (length intact) -> decode_error, records 0 and 2
    still replay; an absurd length prefix stops replay with corrupt_length."""
    path = tmp_path / "bad.ofrec"
    with FrameRecorder(path) as rec:
        sizes = [rec.write(_frame(i)) for i in range(3)]
    data = bytearray(path.read_bytes())
    start1 = 16 + 4 + sizes[0] + 4
    data[start1 : start1 + 20] = b"\xc1" * 20  # 0xc1 is never valid msgpack
    path.write_bytes(bytes(data))
    src = ReplaySource(path)
    assert [f.frame_id for f in src] == [0, 2]
    assert src.stats.skipped == {"decode_error": 1}
    data[16:20] = (2**31).to_bytes(4, "little")
    path.write_bytes(bytes(data))
    src = ReplaySource(path)
    assert list(src) == [] and src.stats.skipped == {"corrupt_length": 1}


def test_not_a_recording(tmp_path: Path) -> None:
    """Bad input: a file with the wrong magic, one from a future format version, an empty file."""
    p = tmp_path / "x.ofrec"
    p.write_bytes(b"PNG not a recording at all")
    with pytest.raises(RecordingError, match="magic"):
        ReplaySource(p)
    p.write_bytes(b"OFZRGBD\n" + (99).to_bytes(4, "little") + bytes(4))
    with pytest.raises(RecordingError, match="version 99"):
        ReplaySource(p)
    p.write_bytes(b"")
    with pytest.raises(RecordingError, match="shorter"):
        ReplaySource(p)


def test_recorder_refuses_foreign_payloads_and_overwrites(tmp_path: Path) -> None:
    """Bad input: a query message and random bytes offered as frames; an existing file."""
    path = tmp_path / "r.ofrec"
    with FrameRecorder(path) as rec:
        with pytest.raises(ValueError, match="sensor.rgbd"):
            rec.write(encode(TextQuery(text="chair")))
        with pytest.raises(ValueError, match="not a message"):
            rec.write(b"\x00\x01garbage")
        rec.write(_frame(0))
    with pytest.raises(FileExistsError, match="overwrite=True"):
        FrameRecorder(path)
    assert len(ReplaySource(path)) == 1
    with pytest.raises(ValueError, match="closed"):
        rec.write(_frame(1))
