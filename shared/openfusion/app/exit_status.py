"""A process's exit status is what the program returned, not Open3D's leak check.

Open3D (0.19+, ``core/MemoryManagerStatistic.cpp``) prints its allocation statistics from a C++
static destructor at process end and calls ``std::exit(EXIT_FAILURE)`` when any tensor it
allocated is still alive then. Python does not free every object at interpreter teardown (a
daemon thread's volume, a module-level cache, a reference cycle the last collection missed), so a
command or a test run that finished cleanly could end with status 1 and a page of "Memory
Statistics" (seen: a test suite with every test passed, exit 1). Open3D offers no Python switch for
this, so :func:`keep_exit_status` registers an ``atexit`` handler (atexit runs before C++ static
destructors) that turns the end-of-program check off through the library's exported C++ API
(``MemoryManagerStatistic::GetInstance()``, ``SetPrintAtProgramEnd(false)``) with ctypes, only when
Open3D was loaded by then; a build without those symbols is left as it is (logged at debug level).
"""

from __future__ import annotations

import atexit
import ctypes
import logging
import os
import sys
from pathlib import Path

logger = logging.getLogger(__name__)

_GET_INSTANCE = "_ZN6open3d4core22MemoryManagerStatistic11GetInstanceEv"
_SET_PRINT_AT_END = "_ZN6open3d4core22MemoryManagerStatistic20SetPrintAtProgramEndEb"
_registered = False


def _loaded_open3d_libraries() -> list[ctypes.CDLL]:
    """The Open3D shared libraries this process has loaded (opened again without loading anything)."""
    module = sys.modules.get("open3d")
    if module is None or not getattr(module, "__file__", None):
        return []
    libs = []
    for path in sorted(Path(module.__file__).parent.rglob("libOpen3D.so*")):
        try:
            libs.append(ctypes.CDLL(str(path), mode=os.RTLD_NOLOAD | os.RTLD_GLOBAL))
        except OSError:  # not loaded in this process (another device's build)
            continue
    return libs


def disable_open3d_exit_check() -> bool:
    """Turn Open3D's end-of-program leak check off now; True when it was found and turned off."""
    done = False
    for lib in _loaded_open3d_libraries():
        try:
            get_instance = getattr(lib, _GET_INSTANCE)
            set_print = getattr(lib, _SET_PRINT_AT_END)
        except AttributeError:
            logger.debug("open3d: no MemoryManagerStatistic symbols in %s; its exit check is left on", lib._name)
            continue
        get_instance.restype = ctypes.c_void_p
        get_instance.argtypes = []
        set_print.restype = None
        set_print.argtypes = [ctypes.c_void_p, ctypes.c_bool]
        set_print(get_instance(), False)
        done = True
    return done


def keep_exit_status() -> None:
    """At interpreter exit, keep Open3D from overriding the exit status (module docstring). Idempotent."""
    global _registered
    if not _registered:
        atexit.register(disable_open3d_exit_check)
        _registered = True
