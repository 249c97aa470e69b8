"""Progress of a run or a playback: a tqdm bar on a terminal, a plain line now and then in a log.

tqdm redraws its bar in place with carriage returns. Written to a file or a pipe (a service's log
under the launcher, ``docker compose logs``, CI) that is one line of thousands of redraws that a
reader cannot follow and ``grep`` cannot split. tqdm has no line mode, so off a terminal
:func:`progress_bar` returns :class:`LineProgress` instead: the same few calls the commands make
(``update``, ``n``, ``set_postfix``, ``refresh``, ``write``, ``close``), written to the same
stream as one line every :data:`LINE_INTERVAL_S` seconds, every tenth of a known total (a short run
still shows where it is: a user or a script waiting for a frame count sees it come) and once at
the end. Written, not logged:
progress is what a bar shows, whatever the log level (``openfusion run`` logs warnings only).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, TextIO

#: Seconds between two progress lines off a terminal.
LINE_INTERVAL_S = 10.0
#: With a known total, a line also at every this share of it.
LINE_SHARE = 0.1


class LineProgress:
    """tqdm's calls used here, as a progress line written every ``interval_s`` and at ``close``."""

    def __init__(self, total: int | None, desc: str, unit: str, *, stream: TextIO | None = None,
                 interval_s: float = LINE_INTERVAL_S, clock: Any = time.monotonic) -> None:
        self.stream = stream or sys.stderr
        self.total = total
        self.desc = desc
        self.unit = unit
        self.n = 0
        self.interval_s = interval_s
        self._clock = clock
        self._postfix = ""
        self._last_line_s = clock()
        self._last_line = ""
        self._step = max(1, math.ceil(total * LINE_SHARE)) if total else None
        self._next_n = self._step
        self._closed = False

    def update(self, n: int = 1) -> None:
        self.n += n
        self.refresh()

    def set_postfix(self, **counts: Any) -> None:
        self._postfix = ", ".join(f"{name}={value}" for name, value in counts.items())

    def refresh(self) -> None:
        share_reached = self._next_n is not None and self.n >= self._next_n
        if share_reached or self._clock() - self._last_line_s >= self.interval_s:
            self._line()

    def write(self, text: str, file: TextIO | None = None) -> None:
        print(text, file=file or self.stream, flush=True)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if self.line() != self._last_line:  # the count or the counts after it moved since
                self._line()

    def line(self) -> str:
        """What the next progress line says."""
        done = f"{self.n}/{self.total}" if self.total else str(self.n)
        return f"{self.desc}: {done} {self.unit}s" + (f" ({self._postfix})" if self._postfix else "")

    def _line(self) -> None:
        if self._step is not None:
            self._next_n = (self.n // self._step + 1) * self._step
        self._last_line_s = self._clock()
        self._last_line = self.line()
        print(self._last_line, file=self.stream, flush=True)


def progress_bar(total: int | None, desc: str, *, unit: str = "frame", disable: bool = False,
                 stream: TextIO | None = None) -> Any:
    """A tqdm bar when ``stream`` (stderr by default) is a terminal, else a :class:`LineProgress`;
    ``disable`` (``--quiet``): a bar that shows nothing."""
    stream = stream or sys.stderr
    if not (disable or _is_terminal(stream)):
        return LineProgress(total, desc, unit, stream=stream)
    from tqdm import tqdm  # only where a bar is drawn (or stands in for --quiet)

    return tqdm(total=total, desc=desc, unit=unit, disable=disable, file=stream)


def _is_terminal(stream: TextIO) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty()) if callable(isatty) else False
    except ValueError:  # a closed stream
        return False
