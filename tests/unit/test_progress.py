"""Progress off a terminal (shared/openfusion/progress.py): lines a log can hold, not tqdm's
carriage-return redraws.

Bad input tried: a closed stream (taken as no terminal, no error); a total that is unknown (a live
source: the count alone).
"""

from __future__ import annotations

import io

from openfusion.progress import LineProgress, progress_bar


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class _Clock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def test_off_a_terminal_progress_is_a_line_now_and_then_and_one_at_the_end() -> None:
    log = io.StringIO()
    clock = _Clock()
    bar = LineProgress(1000, "frames integrated", "frame", stream=log, interval_s=10.0, clock=clock)
    for _ in range(30):
        bar.update(1)
    assert log.getvalue() == ""  # not yet ten seconds, nor a tenth of the frames
    clock.now_s = 10.5
    bar.set_postfix(semantic=12)
    bar.update(1)
    bar.n = 90
    bar.refresh()  # within ten seconds of the last line, under a tenth
    bar.n = 250
    bar.refresh()  # past a tenth: a line, and the next at 300
    bar.n = 299
    bar.refresh()
    bar.close()
    bar.close()
    assert log.getvalue().splitlines() == ["frames integrated: 31/1000 frames (semantic=12)",
                                           "frames integrated: 250/1000 frames (semantic=12)",
                                           "frames integrated: 299/1000 frames (semantic=12)"]
    # The count stands still while the counts after it move (the semantic service finishing):
    # the last line still shows where they ended.
    settled = io.StringIO()
    bar = LineProgress(2, "frames integrated", "frame", stream=settled, interval_s=10.0, clock=clock)
    bar.n = 2
    bar.set_postfix(semantic=1)
    bar.refresh()  # a tenth (and all) of the frames
    bar.set_postfix(semantic=2)
    bar.close()
    assert settled.getvalue().splitlines() == ["frames integrated: 2/2 frames (semantic=1)",
                                               "frames integrated: 2/2 frames (semantic=2)"]
    assert "\r" not in log.getvalue()


def test_progress_bar_is_tqdm_on_a_terminal_and_lines_elsewhere() -> None:
    terminal = _Terminal()
    bar = progress_bar(3, "bridge synthetic")
    assert isinstance(bar, LineProgress)  # pytest's captured stderr is no terminal
    bar = progress_bar(3, "bridge synthetic", stream=terminal)
    bar.update(3)
    bar.close()
    assert not isinstance(bar, LineProgress) and "\r" in terminal.getvalue()
    closed = io.StringIO()
    closed.close()
    assert isinstance(progress_bar(None, "bridge live", stream=closed), LineProgress)
    live = io.StringIO()
    bar = progress_bar(None, "bridge live", stream=live)
    bar.update(7)  # no total: the clock alone, then the end
    bar.close()
    assert live.getvalue() == "bridge live: 7 frames\n"
    short = io.StringIO()
    bar = progress_bar(400, "frames integrated", stream=short)  # a run shorter than ten seconds
    for _ in range(400):
        bar.update(1)
    bar.close()
    assert [line.split()[2] for line in short.getvalue().splitlines()] == [f"{n}/400" for n in range(40, 401, 40)]
    quiet_log = io.StringIO()
    bar = progress_bar(3, "quiet", disable=True, stream=quiet_log)  # --quiet: nothing, line or bar
    bar.update(3)
    bar.close()
    assert quiet_log.getvalue() == ""
