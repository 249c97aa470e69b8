"""Shared test setup: markers by folder, and fixtures every layer uses.

The folder a test lives in says what it needs, and gives it a marker of the same name:

- ``tests/unit``: library code only (no Zenoh session, no subprocess);
- ``tests/bus``: real Zenoh sessions in this process, on loopback with multicast off;
- ``tests/process``: real service processes (or the ``openfusion`` command) talking over loopback.

``scripts/dev.sh test -m unit`` runs one layer. Slow tests (``@pytest.mark.slow``) are left out by
default (``-m slow`` runs them). Tests wait for the state they need (a token, a counter, a reply),
never for a fixed time: helpers in :mod:`openfusion.testing.bus`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    import zenoh

from openfusion.app.exit_status import keep_exit_status
from openfusion.mapping import VolumeParams
from openfusion.testing.bus import open_pair, unique_map_id
from openfusion.wire.keys import KeySpace

TESTS = Path(__file__).resolve().parent
LAYERS = ("unit", "bus", "process")


def pytest_configure(config: pytest.Config) -> None:
    keep_exit_status()  # the run's status is pytest's verdict, not Open3D's end-of-process leak check


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        rel = Path(str(item.fspath)).resolve().relative_to(TESTS)
        layer = rel.parts[0] if len(rel.parts) > 1 else "unit"
        if layer not in LAYERS:
            raise pytest.UsageError(f"{rel}: tests live in tests/unit, tests/bus or tests/process (conftest.py)")
        item.add_marker(getattr(pytest.mark, layer))


@pytest.fixture
def map_id() -> str:
    """A map id no other test (or concurrent run on this machine) uses."""
    return unique_map_id("test")


@pytest.fixture(scope="session")
def minilm_onnx_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache folder (``OPENFUSION_CACHE``) holding the MiniLM ONNX export, made once per session."""
    from openfusion.encoders.text_minilm_onnx import cached_onnx_model

    cache = tmp_path_factory.mktemp("openfusion-cache")
    cached_onnx_model(cache_dir=cache)
    return cache


@pytest.fixture(scope="module")
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session, int]]:
    """Two Zenoh sessions of one test module, connected on a free loopback port (multicast off),
    and that port (tests/bus, tests/process)."""
    a, b, port = open_pair(unique_map_id("bus"))
    yield a, b, port
    a.close()
    b.close()


@pytest.fixture
def keys() -> KeySpace:
    """The key space of a map no other test uses."""
    return KeySpace("openfusion", unique_map_id("bus"))


@pytest.fixture
def small_volume_params() -> VolumeParams:
    """Volume parameters with a small initial grid (the default preallocates a room: 230 MiB)."""
    return VolumeParams(initial_block_count=1024)
