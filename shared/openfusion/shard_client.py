"""Reading one map from its geometry shards: the one client-side helper (docs/SHARDS.md).

Every reader of geometry (the semantic service's renders, dictionary and contacts; the query
service's points and region summaries; :class:`openfusion.client.OpenFusionClient`'s points,
regions, meshes and control calls) asks through :class:`GeometryReader`, which

- learns how many shards serve the map from the geometry services' liveliness tokens
  (``geometry`` for an unsharded map, ``geometry-{I}of{N}`` for shard I of N;
  :class:`~openfusion.wire.keys.ShardId`), refreshed every ``refresh_s`` or given (``shards=N``);
- for an unsharded map asks the plain key, exactly as before (one ``get``);
- for ``N`` shards asks every shard's key at once (one ``get`` per shard, in parallel) and merges
  the answers with :mod:`openfusion.mapping.shards`: renders composited by nearest depth, points
  and meshes concatenated (points capped again), region summaries and contacts merged, the
  dictionary taken from the first shard that answers (every shard follows the same deltas), and
  control calls (save, load, reset) done by every shard (ok only when every shard says ok).
- a shard run twice (replicas, ``geometry-0of2`` and ``geometry-0of2-r1``) answers on one key:
  Zenoh gives each query to one of them (the first good answer); a query left unanswered by a
  replica that went away is asked again for a moment and goes to the other.

A shard that does not answer makes the whole call fail (:class:`~openfusion.bus.QueryError`
naming the shard): a reader never takes a part of the map for the whole.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import numpy as np
import zenoh

from openfusion.bus.health import live_services
from openfusion.bus.query import RETRY_UNANSWERED_S, QueryError, get
from openfusion.mapping import shards as merge
from openfusion.wire.endpoints import (
    CONTROL,
    GEOMETRY_CONTACTS,
    GEOMETRY_DICTIONARY,
    GEOMETRY_MESH,
    GEOMETRY_POINTS,
    GEOMETRY_REGIONS,
    GEOMETRY_RENDER,
    Endpoint,
)
from openfusion.wire.keys import KeySpace, ShardId
from openfusion.wire.schemas import (
    ControlReply,
    ControlRequest,
    DictionaryRequest,
    DictionarySnapshot,
    MeshReply,
    MeshRequest,
    PointsReply,
    PointsRequest,
    RegionContactsReply,
    RegionContactsRequest,
    RegionSummaryReply,
    RegionSummaryRequest,
    RenderReply,
    RenderRequest,
)

R = TypeVar("R")

#: How often the reader asks who serves the map (a liveliness query, ~1 ms on loopback).
DEFAULT_REFRESH_S = 2.0


def shard_count_of(names: list[str]) -> int:
    """The shard count the live service ``names`` show (1 when no shard is live); ValueError when
    shards of two different splits are live at once."""
    counts = {s.count for s in (ShardId.of_service(n) for n in names) if s is not None and s.sharded}
    if len(counts) > 1:
        raise ValueError(f"geometry shards of {sorted(counts)} splits are live on one map")
    return counts.pop() if counts else 1


class GeometryReader:
    """One map's geometry, read from however many shards serve it (module docstring). Thread-safe."""

    def __init__(self, session: zenoh.Session | None, keys: KeySpace, *, shards: int | None = None,
                 refresh_s: float = DEFAULT_REFRESH_S, call: Callable[..., Any] | None = None) -> None:
        """``call``: how an unsharded map's endpoint is asked (a service's ``runner.call``: the
        service's own path, as before shards); without it, :func:`openfusion.bus.query.get` on
        ``session``. Without a session the map is taken as unsharded."""
        self._session = session
        self._keys = keys
        self._call = call
        self._fixed = shards if session is not None else 1
        self.refresh_s = refresh_s
        self._count = shards or 1
        self._refreshed_at: float | None = None
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None

    # ------------------------------------------------------------------ who serves the map
    @property
    def shard_count(self) -> int:
        """The number of shards (given, or seen live at most ``refresh_s`` ago)."""
        if self._fixed is not None:
            return self._fixed
        now = time.monotonic()
        with self._lock:
            stale = self._refreshed_at is None or now - self._refreshed_at >= self.refresh_s
        if stale:
            count = shard_count_of(live_services(self._session, self._keys, timeout_s=0.5))
            with self._lock:
                self._count, self._refreshed_at = count, now
        return self._count

    def _ask(self, endpoint: Endpoint, request: Any, timeout_s: float) -> list[Any]:
        """Every shard's reply to ``request`` (in shard order), asked in parallel."""
        n = self.shard_count
        if n == 1:
            return [self._one(endpoint, request, timeout_s)]
        with self._lock:
            if self._pool is None or self._pool._max_workers < n:  # noqa: SLF001 (sized once per split)
                self._pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="shard-read")
            pool = self._pool
        # A replica that goes away with the query pending leaves it unanswered: asked again for a
        # moment, Zenoh gives it to the shard's other replica.
        futures = [pool.submit(get, self._session, endpoint.shard_key(self._keys, shard), request, endpoint.reply,
                               timeout_s=timeout_s, service=shard.service, retry_unanswered_s=RETRY_UNANSWERED_S)
                   for shard in ShardId.all(n)]
        return [f.result() for f in futures]

    def _one(self, endpoint: Endpoint, request: Any, timeout_s: float) -> Any:
        if self._call is not None:
            return self._call(endpoint, request, timeout_s=timeout_s)
        return get(self._session, endpoint.key(self._keys), request, endpoint.reply, timeout_s=timeout_s,  # type: ignore[arg-type]
                   service=endpoint.owner)

    def close(self) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(wait=False)
                self._pool = None

    # ------------------------------------------------------------------------ the endpoints
    def render(self, request: RenderRequest, *, timeout_s: float = 5.0) -> RenderReply:
        """The map's render of a view: the shards' renders composited by nearest depth."""
        replies = self._ask(GEOMETRY_RENDER, request, timeout_s)
        if len(replies) == 1:
            return replies[0]
        keys, conf, depth = merge.composite_renders([(r.key_map, r.conf_map, r.depth_m) for r in replies])
        return RenderReply(frame_id=replies[0].frame_id, T_map_cam=replies[0].T_map_cam, key_map=keys,
                           conf_map=conf, depth_m=depth)

    def points(self, request: PointsRequest, *, timeout_s: float = 5.0) -> PointsReply:
        replies = self._ask(GEOMETRY_POINTS, request, timeout_s)
        if len(replies) == 1:
            return replies[0]
        pts, col, keys, cut = merge.concat_points([(r.points, r.colors, r.keys) for r in replies], request.max_points)
        return PointsReply(points=pts, colors=col, keys=keys, truncated=cut or any(r.truncated for r in replies))

    def regions(self, request: RegionSummaryRequest, *, timeout_s: float = 5.0) -> RegionSummaryReply:
        replies = self._ask(GEOMETRY_REGIONS, request, timeout_s)
        if len(replies) == 1:
            return replies[0]
        keys, num, lo, hi, cen = merge.merge_region_tables(
            [(r.keys, r.num_points, r.bbox_min, r.bbox_max, r.centroid) for r in replies])
        # Versions add (each shard's only grows, so the sum does: caches keyed on it stay right);
        # every key under the smallest horizon is covered by every shard.
        return RegionSummaryReply(map_version=sum(r.map_version for r in replies),
                                  key_horizon=min(r.key_horizon for r in replies),
                                  age_s=max(r.age_s for r in replies), keys=keys, bbox_min=lo, bbox_max=hi,
                                  num_points=num, centroid=cen)

    def contacts(self, request: RegionContactsRequest, *, timeout_s: float = 5.0) -> RegionContactsReply:
        replies = self._ask(GEOMETRY_CONTACTS, request, timeout_s)
        if len(replies) == 1:
            return replies[0]
        keys, surf, pa, pb, ca, cb = merge.merge_contacts(
            [(r.keys, r.surface_voxels, r.pair_a, r.pair_b, r.contact_a, r.contact_b) for r in replies])
        return RegionContactsReply(map_version=sum(r.map_version for r in replies), keys=keys.astype(np.int32),
                                   surface_voxels=surf, pair_a=pa.astype(np.int32), pair_b=pb.astype(np.int32),
                                   contact_a=ca, contact_b=cb)

    def mesh(self, request: MeshRequest, *, timeout_s: float = 30.0) -> MeshReply:
        replies = self._ask(GEOMETRY_MESH, request, timeout_s)
        if len(replies) == 1:
            return replies[0]
        v, t, c, k = merge.concat_meshes([(r.vertices, r.triangles, r.vertex_colors, r.vertex_keys) for r in replies])
        return MeshReply(vertices=v, triangles=t, vertex_colors=c, vertex_keys=k)

    def dictionary(self, request: DictionaryRequest, *, timeout_s: float = 5.0) -> DictionarySnapshot:
        """The dictionary geometry checkpoints with the map: the first shard that holds one (every
        shard follows the same deltas)."""
        n = self.shard_count
        if n == 1:
            return self._one(GEOMETRY_DICTIONARY, request, timeout_s)
        errors: list[QueryError] = []
        for shard in ShardId.all(n):
            try:
                return get(self._session, GEOMETRY_DICTIONARY.shard_key(self._keys, shard), request,
                           DictionarySnapshot, timeout_s=timeout_s, service=shard.service,
                           retry_unanswered_s=RETRY_UNANSWERED_S)
            except QueryError as exc:
                errors.append(exc)
        raise errors[-1]

    def control(self, action: str, request: ControlRequest, *, timeout_s: float = 60.0) -> ControlReply:
        """Save, load or reset on every shard (each saves its part under the path it is given:
        ``PATH/shard-IofN``); ok when every shard says ok."""
        replies = self._ask(CONTROL[action], request, timeout_s)
        if len(replies) == 1:
            return replies[0]
        ok = all(r.ok for r in replies)
        text = "; ".join(f"{s.service}: {r.message}" for s, r in zip(ShardId.all(len(replies)), replies, strict=True))
        return ControlReply(ok=ok, message=text)


__all__ = ["DEFAULT_REFRESH_S", "GeometryReader", "reader_for", "shard_count_of"]


def reader_for(runner: Any) -> GeometryReader:
    """The :class:`GeometryReader` of a service's :class:`~openfusion.bus.ServiceRunner` (made on
    first use, kept with the runner: one shard count cache per service)."""
    reader = getattr(runner, "_geometry_reader", None)
    if reader is None:
        reader = GeometryReader(getattr(runner, "session", None), getattr(runner, "keys", None), call=runner.call)  # type: ignore[arg-type]
        runner._geometry_reader = reader  # noqa: SLF001
    return reader
