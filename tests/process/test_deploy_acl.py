"""Production Zenoh security from deploy/zenoh/prod/, part 2: access control. Each test sends
what an identity must not (frames, updates, forged acknowledgements and dictionaries, control
queries, tokens of other services) next to an allowed positive control, through the committed
router config. Setup and waiting: deploy_support.py."""

from __future__ import annotations

import time

import zenoh
from deploy_support import (
    ABSENCE_WINDOW_S,
    MARKS,
    Router,
    ask,
    client,
    key,
    serve,
    subscribe,
    until_answered,
    until_routed,
    wait_for,
)

pytestmark = MARKS


def test_only_sensor_identities_put_frames(router: Router) -> None:
    """Bad input: frames put by identities that must not publish them (query client, query
    service); robot-sensor's and admin's frames arrive."""
    with (
        client("geometry", router) as geometry,
        client("robot-sensor", router) as sensor,
        client("query-client", router) as asker,
        client("query-service", router) as query_service,
        client("admin", router) as admin,
    ):
        _sub, inbox = subscribe(geometry, key("sensor", "rgbd"))
        until_routed(sensor, key("sensor", "rgbd"), inbox)
        asker.put(key("sensor", "rgbd"), b"query-client")
        query_service.put(key("sensor", "rgbd"), b"query-service")
        denied_publisher = asker.declare_publisher(key("sensor", "rgbd"))
        publisher = sensor.declare_publisher(key("sensor", "rgbd"))
        assert wait_for(lambda: publisher.matching_status.matching)
        publisher.put(b"robot-sensor")
        admin.put(key("sensor", "rgbd"), b"admin")
        assert wait_for(lambda: {b"robot-sensor", b"admin"} <= set(inbox.items))
        time.sleep(ABSENCE_WINDOW_S)
        # The query client is not even told that a subscriber exists.
        assert denied_publisher.matching_status.matching is False
        assert sorted(inbox.items) == [b"admin", b"robot-sensor"]


def test_sensor_identity_cannot_write_outside_sensor_keys(router: Router) -> None:
    """Bad input: robot-sensor putting semantic updates, dictionary deltas, another map's control
    keys; gpu-semantic's update and delta (positive controls) arrive."""
    with (
        client("geometry", router) as geometry,
        client("query-service", router) as query_service,
        client("robot-sensor", router) as sensor,
        client("gpu-semantic", router) as semantic,
    ):
        _sub_u, updates = subscribe(geometry, key("semantic", "update"))
        _sub_d, deltas = subscribe(query_service, key("semantic", "dictionary", "delta"))
        until_routed(semantic, key("semantic", "update"), updates)
        until_routed(semantic, key("semantic", "dictionary", "delta"), deltas)
        sensor.put(key("semantic", "update"), b"robot-sensor")
        sensor.put(key("semantic", "dictionary", "delta"), b"robot-sensor")
        semantic.put(key("semantic", "update"), b"gpu-semantic")
        semantic.put(key("semantic", "dictionary", "delta"), b"gpu-semantic")
        assert wait_for(lambda: updates.items and deltas.items)
        time.sleep(ABSENCE_WINDOW_S)
        assert updates.items == [b"gpu-semantic"]
        assert deltas.items == [b"gpu-semantic"]


def test_sensor_identity_reads_geometry_progress_and_nothing_else_of_geometry(router: Router) -> None:
    """The bridge's flow control: robot-sensor receives geometry's acknowledgements on
    geometry/progress. Bad input: robot-sensor subscribing to other geometry keys (render, points)
    and putting a forged acknowledgement; the query client subscribing to progress."""
    with (
        client("geometry", router) as geometry,
        client("robot-sensor", router) as sensor,
        client("query-client", router) as asker,
    ):
        _sub_p, progress = subscribe(sensor, key("geometry", "progress"))
        _sub_r, render = subscribe(sensor, key("geometry", "render"))
        _sub_q, asked = subscribe(asker, key("geometry", "progress"))
        _sub_g, forged = subscribe(geometry, key("geometry", "progress"))
        until_routed(geometry, key("geometry", "progress"), progress)
        sensor.put(key("geometry", "progress"), b"forged-by-robot-sensor")
        geometry.put(key("geometry", "render"), b"geometry-render")
        geometry.put(key("geometry", "progress"), b"geometry-ack")
        assert wait_for(lambda: b"geometry-ack" in progress.items)
        time.sleep(ABSENCE_WINDOW_S)
        # A session's own subscribers see its own puts (Zenoh delivers them without the router):
        # the forged acknowledgement reaches only robot-sensor itself, never geometry.
        assert progress.items == [b"forged-by-robot-sensor", b"geometry-ack"]
        assert forged.items == [b"geometry-ack"]
        assert render.items == [] and asked.items == []


def test_control_queries_need_the_admin_identity(router: Router) -> None:
    """Bad input: control/save asked by the query client, the robot sensor, the semantic service
    (which may answer control but not ask it). Only the admin's query reaches the queryable."""
    with (
        client("geometry", router) as geometry,
        client("query-client", router) as asker,
        client("robot-sensor", router) as sensor,
        client("gpu-semantic", router) as semantic,
        client("admin", router) as admin,
    ):
        _qbl, received = serve(geometry, key("control", "save"), b"saved")
        assert until_answered(admin, key("control", "save")) == [b"saved"]  # routed, admin may ask
        before = len(received.items)
        for session in (asker, sensor, semantic):
            assert ask(session, key("control", "save"), timeout_s=1.0) == []
        assert len(received.items) == before  # the denied queries never reached the queryable
        assert ask(admin, key("control", "save")) == [b"saved"]
        assert received.items[before:] == [key("control", "save").encode()]


def test_query_client_may_only_ask_queries(router: Router) -> None:
    """Bad input: the query client asking geometry points, the dictionary, subscribing to frames.
    Its text query (one text, and a batch on query/text_batch) is answered."""
    with (
        client("geometry", router) as geometry,
        client("gpu-semantic", router) as semantic,
        client("query-service", router) as query_service,
        client("robot-sensor", router) as sensor,
        client("query-client", router) as asker,
    ):
        _q1, text_queries = serve(query_service, key("query", "text"), b"regions")
        _q4, _batches = serve(query_service, key("query", "text_batch"), b"batch")
        _q2, point_queries = serve(geometry, key("geometry", "points"), b"points")
        _q3, dict_queries = serve(semantic, key("semantic", "dictionary"), b"dictionary")
        _s1, asker_frames = subscribe(asker, key("sensor", "rgbd"))
        _s2, geometry_frames = subscribe(geometry, key("sensor", "rgbd"))
        # The services that need them are answered (positive controls; the routes now exist).
        assert until_answered(query_service, key("geometry", "points")) == [b"points"]
        assert until_answered(query_service, key("semantic", "dictionary")) == [b"dictionary"]
        assert until_answered(asker, key("query", "text")) == [b"regions"]
        assert until_answered(asker, key("query", "text_batch")) == [b"batch"]
        points_before, dict_before = len(point_queries.items), len(dict_queries.items)

        assert ask(asker, key("geometry", "points"), timeout_s=1.0) == []
        assert ask(asker, key("semantic", "dictionary"), timeout_s=1.0) == []
        assert len(point_queries.items) == points_before and len(dict_queries.items) == dict_before

        until_routed(sensor, key("sensor", "rgbd"), geometry_frames)
        sensor.put(key("sensor", "rgbd"), b"frame")
        assert wait_for(lambda: geometry_frames.items == [b"frame"])
        time.sleep(ABSENCE_WINDOW_S)
        assert asker_frames.items == []


def test_dictionary_is_served_only_by_semantic_or_admin(router: Router) -> None:
    """Bad input: geometry and the query client declaring a queryable on the dictionary key
    (a forged dictionary). Only the semantic service's answer reaches the reader."""
    with (
        client("gpu-semantic", router) as semantic,
        client("geometry", router) as geometry,
        client("query-client", router) as asker,
        client("query-service", router) as query_service,
    ):
        _q1, forged_geometry = serve(geometry, key("semantic", "dictionary"), b"forged-by-geometry")
        _q2, forged_client = serve(asker, key("semantic", "dictionary"), b"forged-by-client")
        # Barriers on the forgers' own links: a declaration geometry may make and a query the client
        # may ask are answered only after the router has handled their forged declarations.
        _q4, _points = serve(geometry, key("geometry", "points"), b"points")
        _q5, _text = serve(query_service, key("query", "text"), b"regions")
        until_answered(query_service, key("geometry", "points"))
        until_answered(asker, key("query", "text"))
        _q3, genuine = serve(semantic, key("semantic", "dictionary"), b"genuine")
        assert until_answered(query_service, key("semantic", "dictionary")) == [b"genuine"]
        assert forged_geometry.items == [] and forged_client.items == []
        assert len(genuine.items) == 1


def test_services_announce_only_themselves(router: Router) -> None:
    """Bad input: the robot-sensor identity declaring the geometry service's liveliness token
    on another map (impersonation); its own bridge token and geometry's own token are seen."""
    with (
        client("robot-sensor", router) as sensor,
        client("geometry", router) as geometry,
        client("admin", router) as admin,
        client("query-client", router) as asker,
    ):
        tokens = [
            sensor.liveliness().declare_token("openfusion/other/health/geometry"),
            sensor.liveliness().declare_token("openfusion/other/health/bridge"),
            geometry.liveliness().declare_token(key("health", "geometry")),
        ]
        try:

            def alive(session: zenoh.Session, key_expr: str) -> list[str]:
                replies = session.liveliness().get(key_expr, timeout=1.0)
                return sorted(str(reply.ok.key_expr) for reply in replies if reply.ok is not None)

            # The sensor's allowed token was declared after its forged one, on the same link: once
            # the admin sees it (and geometry's), the router has handled the forged declaration too.
            assert wait_for(lambda: "openfusion/other/health/bridge" in alive(admin, "openfusion/other/health/*"))
            assert wait_for(lambda: alive(admin, key("health", "*")) == [key("health", "geometry")])

            assert alive(admin, "openfusion/other/health/*") == ["openfusion/other/health/bridge"]
            assert alive(admin, key("health", "*")) == [key("health", "geometry")]
            assert alive(sensor, key("health", "*")) == [key("health", "geometry")]  # health check
            assert alive(asker, key("health", "*")) == []  # query clients see no health
        finally:
            for token in tokens:
                token.undeclare()


def test_health_check_reads_tokens_and_stats_through_the_router(router: Router) -> None:
    """What `openfusion health` does, as each service identity (compose runs the health check
    inside the service's container with its credentials): a liveliness get and a stats get
    (target ALL) on the wildcard `…/health/*`, and a subscriber on it. Bad input guarded: rules
    written for concrete keys only, which Zenoh does not apply to a wider wildcard query."""
    with (
        client("geometry", router) as geometry,
        client("gpu-semantic", router) as semantic,
        client("robot-sensor", router) as sensor,
    ):
        _qbl, stats_queries = serve(geometry, key("health", "geometry"), b"geometry-stats")
        token = geometry.liveliness().declare_token(key("health", "geometry"))
        publisher = geometry.declare_publisher(key("health", "geometry"))
        try:
            _sub, stats_seen = subscribe(sensor, key("health", "*"))
            assert wait_for(lambda: publisher.matching_status.matching)
            publisher.put(b"geometry-periodic")
            assert wait_for(lambda: stats_seen.items == [b"geometry-periodic"])
            for checker in (semantic, sensor):
                replies = checker.liveliness().get(key("health", "*"), timeout=1.0)
                assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [
                    key("health", "geometry")
                ]
                replies = checker.get(
                    key("health", "*"),
                    timeout=2.0,
                    target=zenoh.QueryTarget.ALL,
                    consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
                )
                assert [r.ok.payload.to_bytes() for r in replies if r.ok is not None] == [b"geometry-stats"]
            assert len(stats_queries.items) == 2
        finally:
            token.undeclare()


