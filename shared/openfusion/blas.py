"""One switch for numpy's BLAS threads, shared by the map core and the encoders.

Small matrix products (ranking a query against the dictionary, pooling patch features under
masks) run faster on one BLAS thread on a small machine: OpenBLAS wakes its worker threads for
them, and they then busy-wait for a while, competing with a model's own threads (a 10,000 x 512
gemv: 8-16 ms p50 threaded on a loaded 2-core box against about 1 ms on one thread,
bench/bench_mapping.py; clip-dense's tower pass ran at half speed after pooling woke them,
docs/ENCODERS.md).
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any

logger = logging.getLogger(__name__)

_controller: Any = None
_controller_failed = False


def single_thread_blas() -> contextlib.AbstractContextManager[Any]:
    """A context in which numpy's BLAS uses one thread (``threadpoolctl``; a no-op without it)."""
    global _controller, _controller_failed
    if _controller is None and not _controller_failed:
        try:
            from threadpoolctl import ThreadpoolController

            _controller = ThreadpoolController()
        except ImportError:
            _controller_failed = True
            logger.debug("threadpoolctl not installed; BLAS keeps its default threads")
    if _controller is None:
        return contextlib.nullcontext()
    return _controller.limit(limits=1, user_api="blas")
