"""Record a frame stream to a file and play it back bit-identically (``replay:FILE``).

File format (little-endian)::

    header   8 bytes magic b"OFZRGBD\\n", uint32 format version (1), uint32 reserved (0)
    records  uint32 payload length, then the payload: one ``openfusion.wire.schemas.RgbdFrame``
             encoded by ``openfusion.wire.codec.encode`` (the same bytes that travel on
             ``.../sensor/rgbd``), repeated until the end of the file

Nothing is converted: frames are already canonical, and replay returns exactly the arrays,
pose and metadata that were recorded. A recording cut off mid-record (a crash, a full disk)
replays every complete record and then stops, counting ``truncated_record``; a record that
does not decode is skipped (``decode_error``) and replay continues with the next one, since
the length prefix says where it starts. A length larger than ``max_record_bytes`` cannot be
trusted to resync on, so replay stops there (``corrupt_length``).
"""

from __future__ import annotations

import io
import logging
import struct
import time
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType

from openfusion.errors import UserError
from openfusion.frame import Frame
from openfusion.sources.base import FrameSource, Skip
from openfusion.wire.codec import DEFAULT_MAX_MESSAGE_BYTES, DecodeError, decode, encode, unpack_envelope
from openfusion.wire.schemas import RgbdFrame

logger = logging.getLogger(__name__)

MAGIC = b"OFZRGBD\n"
FORMAT_VERSION = 1
_HEADER = struct.Struct("<8sII")
_LENGTH = struct.Struct("<I")


class RecordingError(UserError, ValueError):
    """A file that is not a recording this build can read (message names the file and why)."""


def read_header(fh: io.BufferedIOBase, path: Path) -> int:
    """Check the header; returns the format version. Raises RecordingError."""
    raw = fh.read(_HEADER.size)
    if len(raw) < _HEADER.size:
        raise RecordingError(f"{path}: not an OpenFusion recording (file shorter than the {_HEADER.size}-byte header)")
    magic, version, _reserved = _HEADER.unpack(raw)
    if magic != MAGIC:
        raise RecordingError(f"{path}: not an OpenFusion recording (magic {magic!r}, expected {MAGIC!r})")
    if version != FORMAT_VERSION:
        raise RecordingError(f"{path}: recording format version {version}, this build reads version {FORMAT_VERSION}")
    return version


class FrameRecorder:
    """Appends frames (``Frame`` or encoded ``RgbdFrame`` bytes) to a new recording file.

    Refuses to overwrite an existing file unless ``overwrite=True``. Encoded bytes (e.g. a
    sample taken from the bus) are checked to be an ``RgbdFrame`` envelope of this build's
    version before they are written, so a recording never holds foreign messages.
    """

    def __init__(
        self, path: str | Path, *, overwrite: bool = False, max_record_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    ) -> None:
        self.path = Path(path)
        self.max_record_bytes = int(max_record_bytes)
        mode = "wb" if overwrite else "xb"
        try:
            self._fh: io.BufferedWriter | None = open(self.path, mode)  # noqa: SIM115 - closed in close()
        except FileExistsError:
            raise FileExistsError(f"recording {self.path} exists; pass overwrite=True to replace it") from None
        self._fh.write(_HEADER.pack(MAGIC, FORMAT_VERSION, 0))
        self.frames_written = 0
        self.bytes_written = _HEADER.size

    def write(self, frame_or_encoded: Frame | bytes | bytearray | memoryview) -> int:
        """Append one frame; returns the payload size in bytes. ValueError for a non-frame payload."""
        if self._fh is None:
            raise ValueError(f"recorder for {self.path} is closed")
        if isinstance(frame_or_encoded, Frame):
            payload = encode(RgbdFrame.from_frame(frame_or_encoded), max_bytes=self.max_record_bytes)
        else:
            payload = bytes(frame_or_encoded)
            try:
                schema, version, _ = unpack_envelope(payload, max_bytes=self.max_record_bytes)
            except DecodeError as exc:
                raise ValueError(f"refusing to record a payload that is not a message: {exc}") from exc
            if (schema, version) != (RgbdFrame.schema_name, RgbdFrame.schema_version):
                raise ValueError(
                    f"refusing to record {schema} v{version}: recordings hold "
                    f"{RgbdFrame.schema_name} v{RgbdFrame.schema_version} frames only"
                )
        self._fh.write(_LENGTH.pack(len(payload)))
        self._fh.write(payload)
        self.frames_written += 1
        self.bytes_written += _LENGTH.size + len(payload)
        return len(payload)

    def flush(self) -> None:
        if self._fh is not None:
            self._fh.flush()

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None
            logger.info("recorded %d frames (%d bytes) to %s", self.frames_written, self.bytes_written, self.path)

    def __enter__(self) -> FrameRecorder:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def record_source(source: FrameSource, path: str | Path, *, overwrite: bool = False) -> int:
    """Record every frame of ``source`` to ``path``; returns the number of frames written."""
    with FrameRecorder(path, overwrite=overwrite) as rec:
        for frame in source:
            rec.write(frame)
        return rec.frames_written


class ReplaySource(FrameSource):
    """Frames of a recording, bit-identical to what was recorded.

    ``realtime=True`` paces frames by their ``stamp_ns`` differences (scaled by ``speed``).
    Decoded arrays are read-only views on the file's bytes; copy before writing into them.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        realtime: bool = False,
        speed: float = 1.0,
        max_record_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        max_frames: int | None = None,
    ) -> None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"recording {path} does not exist")
        if speed <= 0:
            raise ValueError(f"speed must be positive, got {speed}")
        with path.open("rb") as fh:
            read_header(fh, path)
        super().__init__(f"replay:{path.name}", max_frames=max_frames)
        self.path = path
        self.realtime = realtime
        self.speed = float(speed)
        self.max_record_bytes = int(max_record_bytes)
        self._count: int | None = None

    def _length(self) -> int | None:
        """Number of complete records (scans the length prefixes once, no decoding)."""
        if self._count is None:
            n = 0
            size = self.path.stat().st_size
            with self.path.open("rb") as fh:
                fh.seek(_HEADER.size)
                while True:
                    raw = fh.read(_LENGTH.size)
                    if len(raw) < _LENGTH.size:
                        break
                    (length,) = _LENGTH.unpack(raw)
                    if length > self.max_record_bytes or fh.tell() + length > size:
                        break
                    fh.seek(length, io.SEEK_CUR)
                    n += 1
            self._count = n
        return self._count

    def _produce(self) -> Iterator[Frame | Skip]:
        t0_wall: float | None = None
        t0_stamp = 0
        with self.path.open("rb") as fh:
            read_header(fh, self.path)
            index = 0
            while True:
                offset = fh.tell()
                raw = fh.read(_LENGTH.size)
                if not raw:
                    return
                if len(raw) < _LENGTH.size:
                    yield Skip("truncated_record", f"{self.path}: file ends inside the length of record {index} at byte {offset}")
                    return
                (length,) = _LENGTH.unpack(raw)
                if length > self.max_record_bytes:
                    yield Skip(
                        "corrupt_length",
                        f"{self.path}: record {index} at byte {offset} claims {length} bytes (limit {self.max_record_bytes}); "
                        "stopping, the rest of the file cannot be trusted",
                    )
                    return
                payload = fh.read(length)
                if len(payload) < length:
                    yield Skip(
                        "truncated_record",
                        f"{self.path}: record {index} at byte {offset} is cut off ({len(payload)} of {length} bytes)",
                    )
                    return
                index += 1
                try:
                    msg = decode(payload, expected=RgbdFrame, max_bytes=self.max_record_bytes, accept_older=True)
                except DecodeError as exc:
                    yield Skip("decode_error", f"{self.path}: record {index - 1} at byte {offset}: {exc}")
                    continue
                frame = msg.to_frame()
                if self.realtime:
                    now = time.monotonic()
                    if t0_wall is None:
                        t0_wall, t0_stamp = now, frame.stamp_ns
                    else:
                        due = t0_wall + (frame.stamp_ns - t0_stamp) / 1e9 / self.speed
                        if due > now:
                            time.sleep(due - now)
                yield frame
