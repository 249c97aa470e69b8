"""The source contract: ``FrameSource`` (an iterable of ``Frame``) and its ``SourceStats``.

A reader never crashes mid-stream on bad data: a frame it cannot use (missing or corrupt
file, invalid pose, wrong depth format) is *skipped*, counted in ``stats.skipped`` under a
short reason, and logged once per reason with enough context (file, frame index) to find it.
Errors that make the whole source unusable (missing folder, unreadable intrinsics) are
raised when the source is opened, before the first frame.

Subclasses implement ``_produce()``: a generator of ``Frame`` or ``Skip`` items. Dataset
readers with random access implement ``IndexedFrameSource`` (``_num_items`` + ``_load``). In
playback (``replay_from``, what the bridge reads) any exception while loading one item (not only
``SkipFrame``: a reader's bug on one odd file) skips that item as ``read_failed``, logged with its
traceback at debug level, so one item never ends a playback and a replay skips it again instead of
failing on it again; a plain pass (``iter``: writers, evaluation) still raises it.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field

from openfusion.errors import OpenFusionError, UserError
from openfusion.frame import Frame

logger = logging.getLogger(__name__)

NOMINAL_FPS = 30.0
"""Frame rate assumed for datasets without timestamps (ScanNet, Replica, Redwood)."""


@dataclass
class SourceStats:
    """Counters of one pass over a source.

    ``read``: items the source looked at (frames attempted); ``yielded``: frames handed out;
    ``skipped``: reason -> count for items that were dropped.
    """

    read: int = 0
    yielded: int = 0
    skipped: dict[str, int] = field(default_factory=dict)

    def count_skip(self, reason: str, count: int = 1) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + count


@dataclass(frozen=True)
class Skip:
    """An item a source could not turn into a frame: ``reason`` is the counter key."""

    reason: str
    detail: str


class SourceError(UserError, ValueError):
    """A source that cannot be opened: unknown scheme, bad options, a missing path or a folder
    that is not the layout its scheme reads (the message names the spec and what would be valid)."""


class SkipFrame(OpenFusionError):  # noqa: N818 - control flow, not an error for the caller
    """Raised inside ``IndexedFrameSource._load`` to skip one item with a reason."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


class FrameSource(ABC):
    """An iterable of canonical ``Frame`` objects (docs/ARCHITECTURE.md, "Sources").

    Each ``iter()`` starts a new pass and resets ``stats``. ``max_frames`` stops after that
    many yielded frames; ``stride`` keeps every n-th item (indexed sources only). ``live`` is True
    for sources whose frames come from sensors in real time (Kinect + T265, ROS 2 topics): the
    bridge then never blocks or waits for them (a stale frame is worth less than a fresh one).
    """

    live: bool = False

    def __init__(self, name: str, *, max_frames: int | None = None) -> None:
        if max_frames is not None and max_frames < 0:
            raise ValueError(f"max_frames must be >= 0, got {max_frames}")
        self.name = name
        self.max_frames = max_frames
        self.stats = SourceStats()
        self._logged_reasons: set[str] = set()

    @abstractmethod
    def _produce(self) -> Iterator[Frame | Skip]:
        """Yield frames, or ``Skip`` markers for items that could not be used."""

    def _length(self) -> int | None:
        """Number of items one pass looks at, when known before iterating."""
        return None

    def __len__(self) -> int:
        n = self._length()
        if n is None:
            raise TypeError(f"source {self.name!r} has no length known in advance (a live or streamed source)")
        if self.max_frames is not None:
            n = min(n, self.max_frames)
        return n

    def __iter__(self) -> Iterator[Frame]:
        self.stats = SourceStats()
        self._logged_reasons = set()
        if self.max_frames == 0:
            return
        for item in self._produce():
            self.stats.read += 1
            if isinstance(item, Skip):
                self._record_skip(item.reason, item.detail)
                continue
            self.stats.yielded += 1
            yield item
            if self.max_frames is not None and self.stats.yielded >= self.max_frames:
                return

    def _record_skip(self, reason: str, detail: str) -> None:
        self.stats.count_skip(reason)
        if reason not in self._logged_reasons:
            self._logged_reasons.add(reason)
            logger.warning(
                "source %s: skipping frame (%s): %s (further skips for this reason are logged at debug level)",
                self.name,
                reason,
                detail,
            )
        else:
            logger.debug("source %s: skipping frame (%s): %s", self.name, reason, detail)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


#: The skip reason of an item whose loading raised something other than ``SkipFrame``.
READ_FAILED = "read_failed"


class IndexedFrameSource(FrameSource):
    """A source whose items are numbered 0..n-1 and loaded independently (datasets)."""

    def _load_or_skip(self, index: int) -> Frame | Skip:
        """Item ``index`` as a frame, or the ``Skip`` saying why it cannot be one."""
        try:
            return self._load(index)
        except SkipFrame as skip:
            return Skip(skip.reason, skip.detail)
        except Exception as exc:  # one odd item must not end the playback: logged with its traceback, skipped
            logger.debug("source %s: item %d failed", self.name, index, exc_info=True)
            return Skip(READ_FAILED, f"item {index}: {type(exc).__name__}: {exc}")

    def __init__(self, name: str, *, stride: int = 1, max_frames: int | None = None) -> None:
        super().__init__(name, max_frames=max_frames)
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        self.stride = int(stride)
        self._furthest = -1  # the furthest position a replayable pass reached (replay_from)

    @abstractmethod
    def _num_items(self) -> int:
        """Number of items (candidate frames) before striding."""

    @abstractmethod
    def _load(self, index: int) -> Frame:
        """Load item ``index`` or raise ``SkipFrame(reason, detail)``."""

    def _length(self) -> int | None:
        return len(range(0, self._num_items(), self.stride))

    def _produce(self) -> Iterator[Frame | Skip]:
        for index in range(0, self._num_items(), self.stride):
            try:
                frame = self._load(index)
            except SkipFrame as skip:
                yield Skip(skip.reason, skip.detail)
                continue
            yield frame

    def positions(self) -> int:
        """Number of positions one pass looks at (items after striding; before ``max_frames``)."""
        return len(range(0, self._num_items(), self.stride))

    def start_replayable_pass(self) -> None:
        """Begin a pass read with :meth:`replay_from` (fresh ``stats``, nothing reached yet)."""
        self.stats = SourceStats()
        self._logged_reasons = set()
        self._furthest = -1

    def replay_from(self, position: int) -> Iterator[tuple[int, Frame]]:
        """The frames from ``position`` (an index into the strided items) on, each with its
        position: playback that can go back (the bridge replays the frames after a restarted
        geometry's checkpoint). Within one pass (:meth:`start_replayable_pass`) an item is counted
        in ``stats`` (read, skipped, yielded) only the first time any call reaches it, so going
        back counts nothing twice; ``max_frames`` bounds the distinct frames of the pass. Frames
        are re-read from the source (a reader's frames are pure functions of the item), never kept."""
        for pos in range(max(0, position), self.positions()):
            new = pos > self._furthest
            if new and self.max_frames is not None and self.stats.yielded >= self.max_frames:
                return
            frame = self._load_or_skip(pos * self.stride)
            if isinstance(frame, Skip):
                if new:
                    self._furthest = pos
                    self.stats.read += 1
                    self._record_skip(frame.reason, frame.detail)
                continue
            if new:
                self._furthest = pos
                self.stats.read += 1
                self.stats.yielded += 1
            yield pos, frame

    def frame_at(self, index: int) -> Frame:
        """Load one item directly (raises ``SkipFrame`` for an unusable one)."""
        if not 0 <= index < self._num_items():
            raise IndexError(f"source {self.name!r} has {self._num_items()} items, asked for {index}")
        return self._load(index)
