"""Python client for remote queries against running services.

    from openfusion.client import OpenFusionClient
    with OpenFusionClient.connect("tcp/127.0.0.1:7447", map_id="lab") as client:
        reply = client.query_text("something to sit on", top_k=3, with_points=True)
        for region in reply.regions:
            print(region.key, region.score, region.label, region.bbox_min, region.bbox_max)
        for reply in client.query_texts(["chair", "table", "lamp"]):  # one round trip
            print(reply.query, [region.key for region in reply.regions])
        reply = client.query_text("zebra")
        if not reply.matched:  # no region's relevancy reaches the space's threshold
            print("no match; closest:", reply.regions[0].label if reply.regions else None)
        reply = client.query_text("the chair next to the table")  # "X on/under/above/next to Y"
        for region in reply.regions:
            print(region.key, region.relevancy, region.match, region.centroid,
                  region.relation,  # the anchor it stands in the relation to (None: it does not)
                  [(n.relation, n.label) for n in region.nearby])  # up to 3 related regions

Each hit (:class:`~openfusion.wire.schemas.RegionHit`) carries ``score`` (cosine), ``relevancy``
in [0, 1] and ``match`` (:mod:`openfusion.mapping.relevancy`), its box and centroid, up to three
``nearby`` regions with the hit's relation to each, and for relation queries ``relation``;
:attr:`QueryReply.matched` says whether any hit is a match, ``QueryReply.relation`` how a
relation query was read (X, relation, Y and the Y regions used).

A value past a limit of :mod:`openfusion.wire.limits` (a text over 512 characters, ``top_k``
outside 1..100, ``max_points`` outside 1..200,000) raises :class:`openfusion.wire.limits.LimitError`
(a :class:`~openfusion.errors.UserError`) before anything is sent, with the one line every surface
gives; any other value a request schema refuses raises a :class:`~openfusion.errors.UserError`
naming it. Every call is a Zenoh ``get`` with a timeout; a refusal or a service that does not answer
raises :class:`openfusion.bus.QueryError` with the service's reason. Keys, message types and
owners come from :mod:`openfusion.wire.endpoints`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

import numpy as np
import zenoh
from pydantic import ValidationError

from openfusion.bus import QueryError, call, collect_health, get, live_services, open_session
from openfusion.bus.instances import InstancePicker
from openfusion.bus.query import RETRY_UNANSWERED_S
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.errors import UsageError, UserError
from openfusion.shard_client import GeometryReader
from openfusion.wire import limits
from openfusion.wire.endpoints import (
    CONTROL,
    QUERY_ENDPOINTS,
    QUERY_IMAGE,
    QUERY_POINT,
    QUERY_TEXT,
    QUERY_TEXT_BATCH,
    SEMANTIC_DICTIONARY,
    Endpoint,
    is_query_service,
)
from openfusion.wire.keys import KeySpace
from openfusion.wire.message import Message
from openfusion.wire.schemas import (
    ControlReply,
    ControlRequest,
    DictionaryRequest,
    DictionarySnapshot,
    HealthStats,
    ImageQuery,
    MeshReply,
    MeshRequest,
    PointQuery,
    PointsReply,
    PointsRequest,
    QueryReply,
    RegionSummaryReply,
    RegionSummaryRequest,
    TextQuery,
    TextQueryBatch,
)

MAX_BATCH_TEXTS = limits.MAX_BATCH_TEXTS

Q = TypeVar("Q", bound=Message)
R = TypeVar("R", bound=Message)


class OpenFusionClient:
    """Queries, points, meshes and admin actions of one map over an open Zenoh session."""

    def __init__(
        self, session: zenoh.Session, keys: KeySpace, *, timeout_s: float = 10.0, owns_session: bool = False,
        spread_queries: bool = True,
    ) -> None:
        self.session = session
        self.keys = keys
        self.timeout_s = timeout_s
        self._owns_session = owns_session
        # several query services on the map: requests taken to each in turn (openfusion.bus.instances)
        self._query_instances = InstancePicker(session, keys, is_query_service) if spread_queries else None
        #: geometry read from however many shards serve the map (docs/SHARDS.md)
        self._geometry = GeometryReader(session, keys)

    @classmethod
    def from_config(cls, config: ServiceConfig, *, timeout_s: float = 10.0) -> OpenFusionClient:
        return cls(open_session(config), config.keys, timeout_s=timeout_s, owns_session=True)

    @classmethod
    def connect(
        cls, *endpoints: str, map_id: str = "default", prefix: str = "openfusion", timeout_s: float = 10.0
    ) -> OpenFusionClient:
        """A client-mode session to ``endpoints`` (a router or a service), multicast off."""
        config = ServiceConfig(
            map_id=map_id,
            prefix=prefix,
            zenoh=ZenohSettings(mode="client", connect=list(endpoints), multicast_scouting=False),
        )
        return cls.from_config(config, timeout_s=timeout_s)

    def __enter__(self) -> OpenFusionClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._geometry.close()
        if self._owns_session:
            self.session.close()
            self._owns_session = False

    # queries
    def query_text(
        self,
        text: str,
        *,
        top_k: int = 5,
        with_points: bool = False,
        max_points: int = 20_000,
        embedding_space: str | None = None,
    ) -> QueryReply:
        limits.check_text(text)
        _check_options(top_k, max_points)
        request = _request(TextQuery, text=text, top_k=top_k, with_points=with_points, max_points=max_points,
                           embedding_space=embedding_space)
        return self._call(QUERY_TEXT, request)

    def query_texts(
        self,
        texts: Sequence[str],
        *,
        top_k: int = 5,
        with_points: bool = False,
        max_points: int = 20_000,
        embedding_space: str | None = None,
    ) -> list[QueryReply]:
        """One reply per text, in order, as :meth:`query_text` would give each: ONE round trip
        (``query/text_batch``, the texts embedded in one encoder call) per
        :data:`~openfusion.wire.schemas.query.MAX_BATCH_TEXTS` (64) texts. No texts, no call."""
        texts = list(texts)
        for i, text in enumerate(texts):
            limits.check_text(text, which=f"text {i + 1} of {len(texts)} " if len(texts) > 1 else "")
        _check_options(top_k, max_points)
        replies: list[QueryReply] = []
        for start in range(0, len(texts), MAX_BATCH_TEXTS):
            chunk = texts[start : start + MAX_BATCH_TEXTS]
            request = _request(TextQueryBatch, texts=chunk, top_k=top_k, with_points=with_points,
                               max_points=max_points, embedding_space=embedding_space)
            reply = self._call(QUERY_TEXT_BATCH, request)
            if len(reply.replies) != len(chunk):
                raise QueryError(QUERY_TEXT_BATCH.key(self.keys), "bad_reply:count",
                                 f"{len(chunk)} texts asked, {len(reply.replies)} replies came back")
            replies.extend(reply.replies)
        return replies

    def query_image(
        self, image_rgb: np.ndarray, *, top_k: int = 5, with_points: bool = False, max_points: int = 20_000
    ) -> QueryReply:
        _check_options(top_k, max_points)
        request = _request(ImageQuery, image=np.ascontiguousarray(image_rgb, np.uint8), top_k=top_k,
                           with_points=with_points, max_points=max_points)
        return self._call(QUERY_IMAGE, request)

    def query_point(
        self, point_world: Sequence[float], *, radius_m: float = 0.1, top_k: int = 5, with_points: bool = False
    ) -> QueryReply:
        limits.check_top_k(top_k)
        request = _request(PointQuery, point_world=np.asarray(point_world, np.float64), radius_m=radius_m,
                           top_k=top_k, with_points=with_points)
        return self._call(QUERY_POINT, request)

    # geometry
    def points(self, keys: Sequence[int] | None = None, *, max_points: int | None = None) -> PointsReply:
        return self._geometry.points(PointsRequest(keys=_key_list(keys), max_points=max_points),
                                     timeout_s=self.timeout_s)

    def regions(self, keys: Sequence[int] | None = None, *, fresh: bool = False) -> RegionSummaryReply:
        """Per-region bounding boxes and surface point counts (``fresh``: of the current map)."""
        return self._geometry.regions(RegionSummaryRequest(keys=_key_list(keys), fresh=fresh),
                                      timeout_s=max(self.timeout_s, 30.0))

    def mesh(self, keys: Sequence[int] | None = None) -> MeshReply:
        return self._geometry.mesh(MeshRequest(keys=_key_list(keys)), timeout_s=max(self.timeout_s, 30.0))

    def dictionary(self) -> DictionarySnapshot:
        return self._call(SEMANTIC_DICTIONARY, DictionaryRequest())

    # admin
    def control(self, action: str, path: str | None = None) -> ControlReply:
        if action not in CONTROL:
            raise UsageError(f"control action {action!r} is not one of {', '.join(CONTROL)}")
        return self._geometry.control(action, ControlRequest(action=action, path=path),
                                      timeout_s=max(self.timeout_s, 60.0))

    def live_services(self, *, timeout_s: float = 2.0) -> list[str]:
        return live_services(self.session, self.keys, timeout_s=timeout_s)

    def health(self, *, timeout_s: float = 2.0) -> dict[str, HealthStats]:
        """The latest stats of every service of the map that answers in ``timeout_s``, by name."""
        return collect_health(self.session, self.keys, timeout_s=timeout_s)

    def _call(self, endpoint: Endpoint[Q, R], request: Q, *, min_timeout_s: float = 0.0) -> R:
        timeout_s = max(self.timeout_s, min_timeout_s)
        picker = self._query_instances if endpoint in QUERY_ENDPOINTS else None
        name = picker.pick() if picker is not None else None
        if name is not None:  # one of several query services, by name; the shared key when it is gone
            try:
                return get(self.session, endpoint.instance_key(self.keys, name), request, endpoint.reply,
                           timeout_s=timeout_s, service=name)
            except QueryError as exc:
                if not (exc.timed_out or exc.code in _NOT_THIS_INSTANCE):
                    raise
                picker.forget(name)  # type: ignore[union-attr]
        # a query left unanswered by a query service going away is asked again for a moment
        retry = RETRY_UNANSWERED_S if endpoint in QUERY_ENDPOINTS else 0.0
        return call(self.session, self.keys, endpoint, request, timeout_s=timeout_s, retry_unanswered_s=retry)


#: A query service asked by name that answers so (just started, no dictionary yet), or that does not
#: answer in time (gone, or closed with the request pending: Zenoh's ``Timeout`` error reply),
#: leaves the request to the shared key, where Zenoh picks one that answers.
_NOT_THIS_INSTANCE = ("no_map",)


def _key_list(keys: Sequence[int] | None) -> list[int] | None:
    return list(keys) if keys is not None else None


def _check_options(top_k: int, max_points: int) -> None:
    limits.check_top_k(top_k)
    limits.check_max_points(max_points)


def _request(model: type[Q], **fields: object) -> Q:
    """``model(**fields)``; a value its schema refuses is a :class:`UserError` naming it (one line,
    no pydantic traceback)."""
    try:
        return model(**fields)
    except ValidationError as exc:
        first = exc.errors()[0] if exc.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ())) or model.__name__
        message = str(first.get("msg", exc)).removeprefix("Value error, ")
        raise UserError(f"{where}: {message}" if where not in message else message) from None
