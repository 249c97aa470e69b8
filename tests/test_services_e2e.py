"""End to end with real service processes on loopback (multicast off).

One cluster (geometry, semantic, query; a router session in the test process) serves the whole
module; each test is named after what it guards. Bad input tried: garbage bytes and
wrong-schema messages on every subscribed key and every queryable; a query in another
embedding space; oversize requests.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from openfusion.app.launcher import Cluster, wait_for_services
from openfusion.bus import QueryError, collect_health, get, open_session
from openfusion.bus import free_loopback_port as free_port
from openfusion.client import OpenFusionClient
from openfusion.config import ServiceConfig, ZenohSettings
from openfusion.testing.bus import subprocess_env, unique_map_id, wait_until
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
    SEMANTIC_DICTIONARY,
    SEMANTIC_UPDATE,
    SENSOR_INSTANCE,
    SENSOR_RGBD,
)
from openfusion.wire.schemas import (
    ControlReply,
    ControlRequest,
    DictionaryRequest,
    DictionarySnapshot,
    HealthStats,
    PointsReply,
    PointsRequest,
    RenderReply,
    RenderRequest,
)

#: The repository root (deploy files, docs, the README's commands).
ROOT = next(p for p in Path(__file__).resolve().parents if (p / "pyproject.toml").is_file())

pytestmark = pytest.mark.timeout(600)

SOURCE = "synthetic:seed=1,frames={n},width=320,height=240"


class Env:
    def __init__(self, tmp: Path) -> None:
        self.map_id = unique_map_id("e2e")
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.map_dir = tmp / "maps"
        self.router = open_session(
            ServiceConfig(
                map_id=self.map_id,
                zenoh=ZenohSettings(mode="router", listen=[self.endpoint], multicast_scouting=False),
            )
        )
        self.cluster = Cluster(self.map_id, self.endpoint, tmp / "logs")
        self.client = OpenFusionClient.from_config(
            ServiceConfig(
                map_id=self.map_id,
                zenoh=ZenohSettings(mode="client", connect=[self.endpoint], multicast_scouting=False),
            ),
            timeout_s=20.0,
        )

    def start(self, name: str, *extra: str) -> None:
        if name == "geometry":
            extra = ("--map-dir", str(self.map_dir), "--checkpoint-period-s", "0", *extra)
        self.cluster.start(name, list(extra), env=subprocess_env(HF_HUB_OFFLINE="1"))

    def health(self) -> dict[str, HealthStats]:
        return collect_health(self.client.session, self.client.keys, timeout_s=2.0)

    def counter(self, service: str, name: str) -> float:
        stats = self.health().get(service)
        return float(stats.counters.get(name, 0.0)) if stats else 0.0

    def play(self, frames: int, *extra: str, source: str = SOURCE) -> None:
        """Run a bridge for ``frames`` frames and wait until geometry integrated them all."""
        before = self.counter("geometry", "frames_integrated")
        self.cluster.start(
            "bridge",
            ["--source", source.format(n=frames), "--rate-hz", "0", *extra],
            env=subprocess_env(HF_HUB_OFFLINE="1"),
        )
        wait_until(lambda: self.counter("geometry", "frames_integrated") >= before + frames, timeout_s=240)
        self.cluster.stop("bridge")
        self.cluster.processes.pop("bridge")

    def close(self) -> None:
        self.cluster.stop()
        self.client.close()
        self.router.close()


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Env]:
    e = Env(tmp_path_factory.mktemp("e2e"))
    try:
        for name in ("geometry", "semantic", "query"):
            e.start(name)
        wait_for_services(e.client, e.cluster, {"geometry", "semantic", "query"}, 240)
        e.play(30)
        wait_until(lambda: e.counter("semantic", "regions") > 0, timeout_s=60)
        yield e
    finally:
        e.close()


def _settled_dictionary(env: Env) -> DictionarySnapshot:
    """The semantic dictionary once it stopped changing for a moment."""
    last = None
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        snap = env.client.dictionary()
        if last is not None and snap.version == last.version:
            return snap
        last = snap
        time.sleep(1.0)
    raise AssertionError("the dictionary did not settle")


def _settle_map(env: Env) -> None:
    """Wait until geometry stopped receiving semantic updates and frames for a moment (the semantic
    service may still be encoding the last frames of an earlier test's playback)."""
    last = None
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        now = (env.counter("geometry", "updates_applied"), env.counter("geometry", "frames_integrated"))
        if now == last:
            return
        last = now
        time.sleep(1.0)
    raise AssertionError("the map did not settle")


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
    with pytest.raises(QueryError) as info:
        env.client.query_text("chair", top_k=5000)
    assert info.value.code == "too_large" and "max_top_k" in info.value.reason
    with pytest.raises(QueryError) as info:
        get(env.client.session, GEOMETRY_POINTS.key(env.client.keys), PointsRequest(max_points=10**9), PointsReply)
    assert "max_points_reply" in info.value.reason


def test_malformed_payloads_on_every_key_are_counted_and_change_nothing(env: Env) -> None:
    keys = env.client.keys
    session = env.client.session
    before_points = env.client.points(max_points=500_000)
    before_dict = _settled_dictionary(env)
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


def test_kill_semantic_geometry_keeps_integrating_then_restart_keeps_the_dictionary(env: Env) -> None:
    before = _settled_dictionary(env)
    env.cluster.processes["semantic"].proc.kill()
    env.cluster.processes["semantic"].proc.wait(10)
    env.cluster.processes.pop("semantic")
    integrated = env.counter("geometry", "frames_integrated")
    env.play(8)
    assert env.counter("geometry", "frames_integrated") >= integrated + 8
    env.start("semantic")
    wait_for_services(env.client, env.cluster, {"semantic"}, 240)
    recovered = env.client.dictionary()
    assert recovered.version == before.version
    np.testing.assert_array_equal(recovered.keys, before.keys)
    np.testing.assert_allclose(recovered.embeddings, before.embeddings)
    semantic_frames = env.counter("semantic", "semantic_frames")
    env.play(8)
    wait_until(lambda: env.counter("semantic", "semantic_frames") > semantic_frames, timeout_s=60)


def test_kill_geometry_after_save_and_restart_loses_nothing_saved(env: Env) -> None:
    _settle_map(env)  # what is compared below must be what the checkpoint holds
    reply: ControlReply = env.client.control("save")
    assert reply.ok, reply.message
    saved = env.client.points(max_points=500_000)
    env.cluster.processes["geometry"].proc.kill()
    env.cluster.processes["geometry"].proc.wait(10)
    env.cluster.processes.pop("geometry")
    env.start("geometry")
    wait_for_services(env.client, env.cluster, {"geometry"}, 240)
    restored = env.client.points(max_points=500_000)
    assert len(restored.points) == len(saved.points)
    np.testing.assert_array_equal(np.sort(restored.keys), np.sort(saved.keys))
    snap = get(
        env.client.session, GEOMETRY_DICTIONARY.key(env.client.keys), DictionaryRequest(), DictionarySnapshot
    )
    assert len(snap.keys) > 0


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError("no VmRSS")


def test_ten_times_slower_encoder_keeps_memory_bounded_and_geometry_at_camera_rate(env: Env) -> None:
    env.cluster.stop("semantic")
    env.cluster.processes.pop("semantic")
    env.start("semantic", "--set", "semantic.simulate_latency_s=0.5")
    wait_for_services(env.client, env.cluster, {"semantic"}, 240)
    pid = env.cluster.processes["semantic"].proc.pid
    env.play(3)  # warm-up: the encoder loads its text model on the first frame
    wait_until(lambda: env.counter("semantic", "semantic_frames") >= 1, timeout_s=60)
    before = env.health()["semantic"]
    rss_start = _rss_mb(pid)
    env.play(60, source="synthetic:seed=1,frames={n},width=640,height=480")
    time.sleep(1.5)
    rss_end = _rss_mb(pid)
    after = env.health()["semantic"]
    processed = after.counters["semantic_frames"] - before.counters["semantic_frames"]
    dropped = after.drops - before.drops
    # Latest-only: at 0.5 s per frame the service handled a few of the 60 frames and dropped the
    # rest instead of queueing them (60 frames x 2.8 MB at 640x480 would be ~170 MB of queue).
    assert processed < 30 and dropped >= 60 - processed - 2, (processed, dropped)
    assert rss_end - rss_start < 60.0, f"semantic RSS grew {rss_end - rss_start:.1f} MB"
    # play() already waited until geometry integrated every one of the 40 frames.
    assert env.health()["geometry"].drops == 0


def test_services_stay_alive_and_exit_cleanly_on_sigterm(env: Env) -> None:
    env.cluster.check_alive()
    procs = list(env.cluster.processes.values())
    env.cluster.stop()
    assert all(p.proc.returncode == 0 for p in procs), {p.name: p.proc.returncode for p in procs}
