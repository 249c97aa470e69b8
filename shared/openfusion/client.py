"""Python client for remote queries against running services.

    from openfusion.client import OpenFusionClient
    with OpenFusionClient.connect("tcp/127.0.0.1:7447", map_id="lab") as client:
        reply = client.query_text("something to sit on", top_k=3, with_points=True)
        for region in reply.regions:
            print(region.key, region.score, region.label, region.bbox_min, region.bbox_max)

Every call is a Zenoh ``get`` with a timeout; a refusal or a service that does not answer
raises :class:`openfusion.bus.QueryError` with the service's reason.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import zenoh

from openfusion.bus import get, live_services, open_session
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.wire.keys import KeySpace
from openfusion.wire.schemas import (
    ControlReply,
    ControlRequest,
    DictionaryRequest,
    DictionarySnapshot,
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
)


class OpenFusionClient:
    """Queries, points, meshes and admin actions of one map over an open Zenoh session."""

    def __init__(
        self, session: zenoh.Session, keys: KeySpace, *, timeout_s: float = 10.0, owns_session: bool = False
    ) -> None:
        self.session = session
        self.keys = keys
        self.timeout_s = timeout_s
        self._owns_session = owns_session

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
        return get(
            self.session,
            self.keys.query_text,
            TextQuery(
                text=text,
                top_k=top_k,
                with_points=with_points,
                max_points=max_points,
                embedding_space=embedding_space,
            ),
            QueryReply,
            timeout_s=self.timeout_s,
            service="query",
        )

    def query_image(
        self, image_rgb: np.ndarray, *, top_k: int = 5, with_points: bool = False, max_points: int = 20_000
    ) -> QueryReply:
        return get(
            self.session,
            self.keys.query_image,
            ImageQuery(
                image=np.ascontiguousarray(image_rgb, np.uint8),
                top_k=top_k,
                with_points=with_points,
                max_points=max_points,
            ),
            QueryReply,
            timeout_s=self.timeout_s,
            service="query",
        )

    def query_point(
        self,
        point_world: Sequence[float],
        *,
        radius_m: float = 0.1,
        top_k: int = 5,
        with_points: bool = False,
    ) -> QueryReply:
        return get(
            self.session,
            self.keys.query_point,
            PointQuery(
                point_world=np.asarray(point_world, np.float64),
                radius_m=radius_m,
                top_k=top_k,
                with_points=with_points,
            ),
            QueryReply,
            timeout_s=self.timeout_s,
            service="query",
        )

    # geometry
    def points(self, keys: Sequence[int] | None = None, *, max_points: int | None = None) -> PointsReply:
        return get(
            self.session,
            self.keys.geometry_points,
            PointsRequest(keys=list(keys) if keys is not None else None, max_points=max_points),
            PointsReply,
            timeout_s=self.timeout_s,
            service="geometry",
        )

    def regions(self, keys: Sequence[int] | None = None, *, fresh: bool = False) -> RegionSummaryReply:
        """Per-region bounding boxes and surface point counts (``fresh``: of the current map)."""
        return get(
            self.session,
            self.keys.geometry_regions,
            RegionSummaryRequest(keys=list(keys) if keys is not None else None, fresh=fresh),
            RegionSummaryReply,
            timeout_s=max(self.timeout_s, 30.0),
            service="geometry",
        )

    def mesh(self, keys: Sequence[int] | None = None) -> MeshReply:
        return get(
            self.session,
            self.keys.geometry_mesh,
            MeshRequest(keys=list(keys) if keys is not None else None),
            MeshReply,
            timeout_s=max(self.timeout_s, 30.0),
            service="geometry",
        )

    def dictionary(self) -> DictionarySnapshot:
        return get(
            self.session,
            self.keys.semantic_dictionary,
            DictionaryRequest(),
            DictionarySnapshot,
            timeout_s=self.timeout_s,
            service="semantic",
        )

    # admin
    def control(self, action: str, path: str | None = None) -> ControlReply:
        return get(
            self.session,
            self.keys.control(action),
            ControlRequest(action=action, path=path),
            ControlReply,
            timeout_s=max(self.timeout_s, 60.0),
            service="geometry",
        )

    def live_services(self, *, timeout_s: float = 2.0) -> list[str]:
        return live_services(self.session, self.keys, timeout_s=timeout_s)
