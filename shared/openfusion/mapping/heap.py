"""Returning freed heap memory to the operating system (glibc's ``malloc_trim``).

A process under a memory budget frees large temporary arrays all the time (tile copies and blobs of
page-outs and checkpoints); glibc keeps freed heap in its arenas, and the process's resident memory
crept upwards by fragmentation. Plain ctypes, no Open3D: map-file readers may import it.
"""

from __future__ import annotations

import ctypes
import ctypes.util


def release_freed_memory() -> None:
    """Give memory freed by a burst of page-outs or a checkpoint (tile copies, blobs) back to the
    OS. glibc keeps freed heap in its arenas, and without this a process under a memory budget
    creeps upwards by fragmentation (before this: +106 MiB of RssAnon over a 300-frame walk). A no-op
    where there is no glibc."""
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _load_libc() -> object:
    try:
        name = ctypes.util.find_library("c")
        libc = ctypes.CDLL(name) if name else None
        return libc if libc is not None and hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


_LIBC: object = _load_libc()


