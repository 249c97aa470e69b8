"""Key expressions: one builder, the documented key space, and map ids that would widen or
escape a key (wildcards, separators, whitespace) refused with a message naming the id."""

from __future__ import annotations

import pytest
import zenoh

from openfusion.wire.keys import KeySpace, health_all_maps, key_for, validate_map_id


def test_keyspace_builds_the_documented_keys() -> None:
    """Every named key of design §2, under the default and a multi-segment prefix."""
    keys = KeySpace("openfusion", "lab-1")
    assert keys.sensor_rgbd == "openfusion/lab-1/sensor/rgbd"
    assert keys.sensor_instance == "openfusion/lab-1/sensor/instance"
    assert keys.geometry_render == "openfusion/lab-1/geometry/render"
    assert keys.geometry_points == "openfusion/lab-1/geometry/points"
    assert keys.geometry_mesh == "openfusion/lab-1/geometry/mesh"
    assert keys.geometry_regions == "openfusion/lab-1/geometry/regions"
    assert keys.semantic_update == "openfusion/lab-1/semantic/update"
    assert keys.semantic_dictionary == "openfusion/lab-1/semantic/dictionary"
    assert keys.semantic_dictionary_delta == "openfusion/lab-1/semantic/dictionary/delta"
    assert keys.query_text == "openfusion/lab-1/query/text"
    assert keys.query_image == "openfusion/lab-1/query/image"
    assert keys.query_point == "openfusion/lab-1/query/point"
    assert [keys.control(a) for a in ("save", "load", "reset")] == [
        "openfusion/lab-1/control/save",
        "openfusion/lab-1/control/load",
        "openfusion/lab-1/control/reset",
    ]
    assert keys.health("geometry") == keys.liveliness("geometry") == "openfusion/lab-1/health/geometry"
    assert keys.health_all == "openfusion/lab-1/health/*"
    assert KeySpace("fleet/openfusion", "r2").sensor_rgbd == "fleet/openfusion/r2/sensor/rgbd"
    assert key_for("lab", "sensor", "rgbd") == "openfusion/lab/sensor/rgbd"
    assert health_all_maps() == "openfusion/*/health/*"


def test_every_key_is_a_canonical_zenoh_key_expression() -> None:
    """Zenoh accepts each key as-is (canonical form), and the health wildcard matches each service."""
    keys = KeySpace("openfusion", "lab")
    every = [keys.sensor_rgbd, keys.sensor_instance, keys.geometry_render, keys.semantic_dictionary_delta, keys.control("reset")]
    for key in every + [keys.health_all, keys.all]:
        assert str(zenoh.KeyExpr(key)) == key
    wildcard = zenoh.KeyExpr(keys.health_all)
    assert wildcard.intersects(keys.health("semantic"))
    assert not wildcard.intersects(KeySpace("openfusion", "other").health("semantic"))
    assert zenoh.KeyExpr(keys.all).includes(keys.sensor_rgbd)


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
    with pytest.raises(ValueError, match="not one of save, load, reset"):
        KeySpace().control("drop")


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
