"""Keep the libraries' own output off a command's stderr (progress bars, advisory warnings, log
lines of transformers / huggingface_hub / tqdm / onnxruntime), so a command prints its answer and
nothing else; ``--verbose`` leaves them as they are.

Done for the command only, never in the library code the services share: :func:`quiet_libraries`
sets the environment variables these libraries read when they are imported (the commands import
them lazily, after it is entered), calls their own switches on the ones already imported, ignores
Python warnings, and puts everything back on exit. :func:`quiet_onnxruntime`, called just before a
command builds an onnxruntime encoder, lowers onnxruntime's default logger to errors while such a
block is active (and does nothing outside one, so the command need not know whether it is quiet).
A library first imported inside the block keeps what it read then (no progress bars) for the rest of
the process, which for a command is the command itself. OpenFusion-Z's own log lines are not touched here: the command's log level decides (WARNING by
default, so a warning the user should act on still shows).
"""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from collections.abc import Callable, Iterator

#: Read by tqdm (every progress bar's ``disable``), huggingface_hub and transformers at import.
QUIET_ENV: dict[str, str] = {
    "TQDM_DISABLE": "1",
    "HF_HUB_DISABLE_PROGRESS_BARS": "1",
    "TRANSFORMERS_VERBOSITY": "error",
    "TRANSFORMERS_NO_ADVISORY_WARNINGS": "1",
}
#: onnxruntime's logging severities: 2 warning (its default), 3 error.
_ORT_WARNING, _ORT_ERROR = 2, 3
#: State of the active :func:`quiet_libraries` block (None outside one): whether onnxruntime was lowered.
_active: dict[str, bool] | None = None


def _quiet_imported() -> list[Callable[[], None]]:
    """Silence the libraries already imported through their own switches; the undo steps."""
    undo: list[Callable[[], None]] = []
    hf_logging = sys.modules.get("transformers.utils.logging")
    if hf_logging is not None:
        level, bars = hf_logging.get_verbosity(), hf_logging.is_progress_bar_enabled()
        hf_logging.set_verbosity_error()
        hf_logging.disable_progress_bar()
        undo.append(lambda: hf_logging.set_verbosity(level))
        if bars:
            undo.append(hf_logging.enable_progress_bar)
    hub = sys.modules.get("huggingface_hub.utils")
    if hub is not None and hasattr(hub, "are_progress_bars_disabled"):
        if not hub.are_progress_bars_disabled():
            hub.disable_progress_bars()
            undo.append(hub.enable_progress_bars)
    return undo


@contextlib.contextmanager
def quiet_libraries(quiet: bool = True) -> Iterator[None]:
    """Inside: no library progress bars, advisory messages or Python warnings (``quiet``);
    with ``quiet=False`` nothing changes (``--verbose``)."""
    global _active
    if not quiet or _active is not None:  # verbose, or already inside a quiet block
        yield
        return
    saved = {name: os.environ.get(name) for name in QUIET_ENV}
    os.environ.update(QUIET_ENV)
    undo = _quiet_imported()
    _active = {"onnxruntime": False}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        lowered, _active = _active["onnxruntime"], None
        ort = sys.modules.get("onnxruntime")
        if lowered and ort is not None:
            ort.set_default_logger_severity(_ORT_WARNING)
        for step in reversed(undo):
            step()
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def quiet_onnxruntime() -> None:
    """Inside a quiet :func:`quiet_libraries` block: onnxruntime's default logger (sessions
    without their own severity, provider set-up) to errors only, until the block ends. Outside
    one, or without onnxruntime: nothing."""
    if _active is None:
        return
    try:
        import onnxruntime as ort
    except ImportError:
        return
    ort.set_default_logger_severity(_ORT_ERROR)
    _active["onnxruntime"] = True
