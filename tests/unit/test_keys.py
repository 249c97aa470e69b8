"""Key expressions: one builder, the documented key space, and map ids that would widen or
escape a key (wildcards, separators, whitespace) refused with a message naming the id."""

from __future__ import annotations

import pytest
import zenoh

from openfusion.wire.endpoints import CONTROL, ENDPOINTS, GEOMETRY_RENDER, SENSOR_RGBD, TOPICS
from openfusion.wire.keys import KeySpace, health_all_maps, key_for, validate_map_id
from openfusion.wire.schemas import RenderReply, RenderRequest, RgbdFrame


def test_keyspace_builds_the_documented_keys() -> None:
    """Every topic and queryable of the key table (README, docs/ARCHITECTURE.md), under the
    default and a multi-segment prefix, declared once in openfusion.wire.endpoints."""
    keys = KeySpace("openfusion", "lab-1")
    documented = {
        "sensor/rgbd", "sensor/instance", "geometry/progress", "geometry/render", "geometry/points",
        "geometry/mesh", "geometry/regions", "geometry/dictionary", "geometry/contacts",
        "geometry/checkpoint/list", "geometry/checkpoint/chunk", "geometry/checkpoint/release", "semantic/update", "semantic/dictionary", "semantic/merge",
        "semantic/dictionary/delta", "query/text", "query/text_batch", "query/image", "query/point", "control/save", "control/load",
        "control/reset",
    }
    declared = [*TOPICS, *ENDPOINTS]
    assert {d.path for d in declared} == documented
    for d in declared:
        assert d.key(keys) == f"openfusion/lab-1/{d.path}"
    assert SENSOR_RGBD.key(keys) == "openfusion/lab-1/sensor/rgbd"
    assert CONTROL["reset"].key(keys) == "openfusion/lab-1/control/reset"
    assert keys.health("geometry") == keys.liveliness("geometry") == "openfusion/lab-1/health/geometry"
    assert keys.health_all == "openfusion/lab-1/health/*"
    assert SENSOR_RGBD.key(KeySpace("fleet/openfusion", "r2")) == "fleet/openfusion/r2/sensor/rgbd"
    assert key_for("lab", "sensor", "rgbd") == "openfusion/lab/sensor/rgbd"
    assert health_all_maps() == "openfusion/*/health/*"


def test_every_endpoint_names_its_types_and_a_known_owner() -> None:
    """Each declaration carries the message types the bus checks and the service that publishes
    or answers (the owner a timeout message names)."""
    services = {"bridge", "geometry", "semantic", "query"}
    assert {t.publisher for t in TOPICS} <= services
    assert {e.owner for e in ENDPOINTS} <= services
    assert GEOMETRY_RENDER.request is RenderRequest and GEOMETRY_RENDER.reply is RenderReply
    assert SENSOR_RGBD.message is RgbdFrame


def test_every_key_is_a_canonical_zenoh_key_expression() -> None:
    """Zenoh accepts each key as-is (canonical form), and the health wildcard matches each service."""
    keys = KeySpace("openfusion", "lab")
    every = [d.key(keys) for d in (*TOPICS, *ENDPOINTS)]
    for key in every + [keys.health_all, keys.all]:
        assert str(zenoh.KeyExpr(key)) == key
    wildcard = zenoh.KeyExpr(keys.health_all)
    assert wildcard.intersects(keys.health("semantic"))
    assert not wildcard.intersects(KeySpace("openfusion", "other").health("semantic"))
    assert zenoh.KeyExpr(keys.all).includes(SENSOR_RGBD.key(keys))


@pytest.mark.parametrize(
    ("map_id", "why"),
    [
        ("", "is empty"),
        ("a/b", "contains '/'"),
        ("*", "contains '\\*'"),
        ("**", "contains '\\*'"),
        ("lab$", "contains '\\$'"),
        ("lab?x=1", "contains '\\?'"),
        ("lab#1", "contains '#'"),
        ("@admin", "contains '@'"),
        ("my lab", "whitespace"),
        ("lab\t", "whitespace"),
        ("küche", "contains 'ü'"),
        (".hidden", "starts with '.'"),
        ("x" * 129, "129 characters"),
    ],
)
def test_invalid_map_ids_are_refused_naming_id_and_reason(map_id: str, why: str) -> None:
    """Each id that is not one safe key segment raises ValueError with the id and the reason."""
    for build in (
        lambda: validate_map_id(map_id),
        lambda: KeySpace("openfusion", map_id),
        lambda: key_for(map_id, "x"),
    ):
        with pytest.raises(ValueError, match=why) as info:
            build()
        assert repr(map_id) in str(info.value)


def test_invalid_prefixes_parts_services_and_actions_are_refused() -> None:
    """Bad prefix segments, key parts, service names and control actions raise ValueError."""
    with pytest.raises(ValueError, match="segment '' is empty"):
        KeySpace("openfusion/", "lab")
    with pytest.raises(ValueError, match="prefix"):
        KeySpace("open fusion", "lab")
    with pytest.raises(ValueError, match="key part 'a/b'"):
        key_for("lab", "a/b")
    with pytest.raises(ValueError, match="at least one part"):
        key_for("lab")
    with pytest.raises(ValueError, match="service name 'geo\\*'"):
        KeySpace().health("geo*")
    assert sorted(CONTROL) == ["load", "reset", "save"]  # no other admin key exists to be reached


def test_service_names_are_parsed_back_from_health_keys() -> None:
    """The CLI turns liveliness keys back into service names; foreign keys are refused."""
    keys = KeySpace("openfusion", "lab")
    assert keys.service_from_health_key(keys.health("geometry")) == "geometry"
    for foreign in (
        "openfusion/other/health/geometry",
        "openfusion/lab/health/a/b",
        "openfusion/lab/health/",
    ):
        with pytest.raises(ValueError):
            keys.service_from_health_key(foreign)
