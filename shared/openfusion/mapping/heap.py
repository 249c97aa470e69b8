"""Returning freed heap memory to the operating system (glibc's ``malloc_trim``).

A process under a memory budget frees large temporary arrays all the time (tile copies and blobs of
page-outs and checkpoints); glibc keeps freed heap in its arenas, and the process's resident memory
crept upwards by fragmentation. Plain ctypes, no Open3D: map-file readers may import it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from typing import Any


def release_freed_memory() -> None:
    """Give memory freed by a burst of page-outs or a checkpoint (tile copies, blobs) back to the
    OS. glibc keeps freed heap in its arenas, and without this a process under a memory budget
    creeps upwards by fragmentation (before this: +106 MiB of RssAnon over a 300-frame walk). A no-op
    where there is no glibc."""
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


@functools.cache
def _libc() -> Any:
    """The C library, looked up on first use (``find_library`` may run ``ldconfig``: not at import,
    so a command that never trims starts no process)."""
    try:
        name = ctypes.util.find_library("c")
        libc = ctypes.CDLL(name) if name else None
        return libc if libc is not None and hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


#: glibc's ``mallopt`` parameter number of ``M_ARENA_MAX`` (malloc.h).
_M_ARENA_MAX = -8


def limit_malloc_arenas(arenas: int) -> bool:
    """Let glibc make at most ``arenas`` malloc arenas in this process (``MALLOC_ARENA_MAX``), so the
    memory a thread frees is reused by the others instead of kept in that thread's own arena (a
    service answering on many threads: each kept its last read-out's worth). Call before threads
    start; arenas made already stay. Returns whether it was applied (False without glibc)."""
    if arenas < 1:
        raise ValueError(f"arenas must be >= 1, got {arenas}")
    libc = _libc()
    if libc is None or not hasattr(libc, "mallopt"):
        return False
    return bool(libc.mallopt(_M_ARENA_MAX, int(arenas)))
