"""The end of ``openfusion run`` at any map size: a save that is waited for, and a mesh however large.

Save (:func:`save_and_wait`)
    ``control/save`` is asked with the client's usual timeout. A large map may take longer (the
    surface read-out of the region summaries, the merge pass before it): when the request times
    out, the run keeps waiting while geometry is alive and its health says ``saving`` 1, printing
    how long it has waited every :data:`PROGRESS_EVERY_S`, and takes the save as done when
    ``saves`` (control saves completed) goes up, as failed when ``save_failures`` does (a periodic
    checkpoint meanwhile is not the save). With geometry shards the counters are the shards'
    combined view (:func:`openfusion.app.shard_run.combined_geometry`: saved when every shard
    saved). It never gives up on a fixed timeout; it stops waiting only when geometry dies or the
    save failed (:class:`~openfusion.app.launcher.RunError`), or a second signal aborts the run.

Mesh (:func:`fetch_mesh`)
    ``geometry/mesh`` answers in one reply up to ``max_points_reply`` vertices. A larger mesh is
    refused (``too_large``), a building's read-out can outlast the request (``timeout``), and a map
    larger than geometry's memory budget (``tiles_paged_out`` > 0) is not asked for at all; the run
    then builds the mesh from the map it just saved (``OUT/map``),
    part by part (:func:`openfusion.mapping.wholemap.iter_mesh_parts`, with the map's memory
    budget when it has one), so ``mesh.ply`` is written whatever the size of the map.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from openfusion.bus.query import QueryError
from openfusion.wire.counters import GeometryCounter

logger = logging.getLogger(__name__)

PROGRESS_EVERY_S = 10.0
_POLL_S = 1.0


def _timed_out(exc: QueryError) -> bool:
    """Nobody answered in time, or the queryable did not (Zenoh answers the latter itself, with an
    error reply whose payload is ``Timeout``)."""
    return exc.timed_out


def _geometry_counters(client: Any) -> dict[str, float] | None:
    """Geometry's counters: one service's, or the shards' combined view."""
    from openfusion.app.shard_run import combined_geometry

    health = client.health(timeout_s=2.0)
    stats = combined_geometry(health).get("geometry") or health.get("geometry")
    return None if stats is None else dict(stats.counters)


def save_and_wait(
    client: Any, map_dir: Path, *, say: Callable[[str], None], alive: Callable[[], bool],
    should_stop: Callable[[], bool] = lambda: False,
) -> None:
    """Save the map to ``map_dir`` through geometry and wait for it (module docstring)."""
    before = _geometry_counters(client) or {}
    started = time.monotonic()
    try:
        client.control("save", str(map_dir.resolve()))
        return
    except QueryError as exc:
        if not _timed_out(exc):
            raise
    from openfusion.app.launcher import RunError

    saves = before.get(GeometryCounter.SAVES, 0.0)
    failures = before.get(GeometryCounter.SAVE_FAILURES, 0.0)
    last_said = time.monotonic()
    while True:
        if not alive():
            raise RunError(f"geometry died while saving the map to {map_dir}")
        if should_stop():
            raise RunError(f"stopped while geometry was saving the map to {map_dir}")
        counters = _geometry_counters(client)
        if counters is not None and counters.get(GeometryCounter.SAVE_FAILURES, 0.0) > failures:
            raise RunError(f"geometry could not save the map to {map_dir} (its log says why)")
        if counters is not None and counters.get(GeometryCounter.SAVES, 0.0) > saves:
            say(f"saved the map ({time.monotonic() - started:.0f} s)")
            return
        if time.monotonic() - last_said >= PROGRESS_EVERY_S:
            last_said = time.monotonic()
            say(f"saving the map: {last_said - started:.0f} s so far, geometry is still writing it")
        time.sleep(_POLL_S)  # polling a remote service's health: there is no event to wait on


def fetch_mesh(client: Any, map_dir: Path, *, say: Callable[[str], None]) -> Any:
    """The map's mesh: over the bus in one reply, or built from the saved map when the map is
    larger than geometry's memory budget (tiles were paged out), the mesh too large for one reply,
    or its read-out slower than the request's timeout."""
    counters = _geometry_counters(client) or {}
    if counters.get(GeometryCounter.TILES_PAGED_OUT, 0.0) > 0:
        say("the map is larger than geometry's memory budget; building the mesh from the saved map")
        return mesh_from_map(map_dir)
    try:
        reply = client.mesh()
        return reply.vertices, reply.triangles, reply.vertex_colors, reply.vertex_keys
    except QueryError as exc:
        if exc.code != "too_large" and not _timed_out(exc):
            raise
        why = "too large for one reply" if exc.code == "too_large" else "not read out within the request's timeout"
        say(f"the mesh is {why} ({exc.reason}); building it from the saved map")
    return mesh_from_map(map_dir)


def mesh_from_map(map_dir: Path) -> Any:
    """The mesh of a saved map, read part by part (the map's memory budget, if any, holds)."""
    from openfusion.mapping import load_map

    loaded = load_map(map_dir)
    try:
        return loaded.volume.extract_mesh()
    finally:
        loaded.volume.close()
