"""The two ways a :class:`~openfusion.mapping.volume.SemanticVolume` method holds the volume's lock
(split from ``volume.py``, whose parts use them): :func:`locked` serialises a method on the lock
(Open3D's grid is not thread-safe); :func:`read_out` runs a whole-map read-out as one job of the
read-out worker (:mod:`.readout_worker`), holding the lock there."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

from openfusion.mapping import readout_worker

_F = TypeVar("_F", bound=Callable[..., Any])


def locked(method: _F) -> _F:
    """Serialise a public method on the volume's lock (Open3D's grid is not thread-safe)."""

    @functools.wraps(method)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            return method(self, *args, **kwargs)

    return wrapper  # type: ignore[return-value]


def read_out(method: _F) -> _F:
    """A whole-map read-out: one job on the read-out worker (:mod:`.readout_worker`: one at a time
    in the process, so its chunks never overlap another read-out's), holding the volume's lock there."""

    @functools.wraps(method)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        def job() -> Any:
            with self._lock:
                return method(self, *args, **kwargs)

        return readout_worker.run(method.__name__, job)

    return wrapper  # type: ignore[return-value]
