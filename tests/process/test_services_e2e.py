"""End to end with real service processes on loopback (multicast off): what a client sees of a
running map. One cluster (e2e_support.Env) serves the module; every test here only reads the
map or sends what must change nothing, so they pass in any order or alone. Tests that kill,
restart or slow down a service have their own cluster (test_services_faults.py).

Bad input tried: garbage bytes and wrong-schema messages on every subscribed key and every
queryable; a query in another embedding space; oversize requests.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from e2e_support import SOURCE, Env

from openfusion.bus import QueryError, get
from openfusion.testing.bus import subprocess_env
from openfusion.wire.endpoints import (
    CONTROL,
    DICTIONARY_DELTA,
    GEOMETRY_DICTIONARY,
    GEOMETRY_MESH,
    GEOMETRY_POINTS,
    GEOMETRY_REGIONS,
    GEOMETRY_RENDER,
    QUERY_IMAGE,
    QUERY_POINT,
    QUERY_TEXT,
    QUERY_TEXT_BATCH,
    SEMANTIC_DICTIONARY,
    SEMANTIC_UPDATE,
    SENSOR_INSTANCE,
    SENSOR_RGBD,
)
from openfusion.wire.limits import LimitError
from openfusion.wire.schemas import ControlRequest, PointsReply, PointsRequest, RenderReply, RenderRequest

#: The repository root.
ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Env]:
    e = Env(tmp_path_factory.mktemp("e2e"))
    try:
        e.start_all()
        e.play(30)
        yield e
    finally:
        e.close()


def test_remote_query_from_a_separate_client_process_finds_the_chair(env: Env) -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "openfusion.app.cli",
            "query",
            "chair",
            "--map",
            env.map_id,
            "--mode",
            "client",
            "--connect",
            env.endpoint,
            "--no-multicast",
            "--top-k",
            "3",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
        env=subprocess_env(HF_HUB_OFFLINE="1"),
    )
    assert result.returncode == 0, result.stderr
    reply = json.loads(result.stdout)
    assert reply["embedding_space"] == "minilm-l6-v2"
    assert reply["regions"], "no region came back for 'chair'"
    best = reply["regions"][0]
    assert best["label"] in ("chair", "office chair") and best["score"] > 0.8 and best["num_points"] > 0


def test_query_in_another_embedding_space_is_refused_with_both_names(env: Env) -> None:
    with pytest.raises(QueryError) as info:
        env.client.query_text("chair", embedding_space="clip-vit-b-32")
    assert info.value.code == "embedding_space_mismatch"
    assert "clip-vit-b-32" in info.value.reason and "minilm-l6-v2" in info.value.reason


def test_oversize_requests_are_refused_naming_the_limit(env: Env) -> None:
    with pytest.raises(LimitError, match="top_k must be from 1 to 100, got 5000"):  # by the client, before sending
        env.client.query_text("chair", top_k=5000)
    with pytest.raises(QueryError) as info:
        get(env.client.session, GEOMETRY_POINTS.key(env.client.keys), PointsRequest(max_points=10**9), PointsReply)
    assert "max_points_reply" in info.value.reason


def test_malformed_payloads_on_every_key_are_counted_and_change_nothing(env: Env) -> None:
    keys = env.client.keys
    session = env.client.session
    before_points = env.client.points(max_points=500_000)
    before_dict = env.client.dictionary()  # the module's playback has settled (Env.play)
    geo_before = env.health()["geometry"]
    garbage = [b"", b"\x00\x01garbage", b"\x93\xa3abc", json.dumps({"schema": "sensor.rgbd"}).encode()]
    # Wrong schema on a subscribed key: a valid message of another type.
    wrong = ControlRequest(action="reset")
    from openfusion.wire.codec import encode

    for key in (SENSOR_RGBD.key(keys), SENSOR_INSTANCE.key(keys), SEMANTIC_UPDATE.key(keys), DICTIONARY_DELTA.key(keys)):
        for payload in [*garbage, encode(wrong)]:
            session.put(key, payload)
    for key in (
        GEOMETRY_RENDER.key(keys),
        GEOMETRY_POINTS.key(keys),
        GEOMETRY_MESH.key(keys),
        GEOMETRY_REGIONS.key(keys),
        GEOMETRY_DICTIONARY.key(keys),
        SEMANTIC_DICTIONARY.key(keys),
        QUERY_TEXT.key(keys),
        QUERY_TEXT_BATCH.key(keys),
        QUERY_IMAGE.key(keys),
        QUERY_POINT.key(keys),
        CONTROL["save"].key(keys),
        CONTROL["reset"].key(keys),
    ):
        for payload in garbage:
            replies = list(session.get(key, payload=payload, timeout=10))
            assert replies and replies[0].err is not None, f"{key} accepted garbage {payload!r}"
    # The reset request above never decoded as a ControlRequest on a subscriber, and no garbage
    # reached the map: same points, same dictionary, services alive, errors counted.
    env.cluster.check_alive()
    after_points = env.client.points(max_points=500_000)
    assert len(after_points.points) == len(before_points.points)
    np.testing.assert_array_equal(np.sort(after_points.keys), np.sort(before_points.keys))
    after_dict = env.client.dictionary()
    assert after_dict.version == before_dict.version
    geo_after = env.health()["geometry"]
    assert geo_after.errors > geo_before.errors
    assert geo_after.counters["frames_integrated"] == geo_before.counters["frames_integrated"]


def test_render_answers_keys_of_the_map_with_a_depth_test(env: Env) -> None:
    from openfusion.sources import open_source

    frame = next(iter(open_source(SOURCE.format(n=1))))
    K = frame.intrinsics.scaled(80, 60)
    reply = get(
        env.client.session,
        GEOMETRY_RENDER.key(env.client.keys),
        RenderRequest(frame_id=0, T_world_cam=frame.T_world_cam, **RenderRequest.intrinsics_fields(K)),
        RenderReply,
        timeout_s=20,
    )
    assert reply.key_map.shape == (60, 80)
    assert (reply.key_map >= 0).mean() > 0.5
    dictionary = env.client.dictionary()
    assert set(np.unique(reply.key_map[reply.key_map >= 0])) <= set(dictionary.keys.tolist())
