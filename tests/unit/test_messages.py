"""Message schemas: every registered message round-trips through the codec, nested models
survive, and each cross-field rule refuses an inconsistent message with a clear error."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest
from pydantic import ValidationError

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.wire import schemas as m
from openfusion.wire.codec import decode, encode
from openfusion.wire.message import registered_schemas

K = CameraIntrinsics(8, 6, 10.0, 10.0, 4.0, 3.0)
K_FIELDS = m.PinholeMessage.intrinsics_fields(K)
rng = np.random.default_rng(1)


def _pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [1.0, -2.0, 0.5]
    return T


def _f32(*shape: int) -> np.ndarray:
    return rng.random(shape, dtype=np.float32)


def _i32(*shape: int) -> np.ndarray:
    return rng.integers(-1, 50, shape, dtype=np.int32)


def _hit(with_points: bool) -> m.RegionHit:
    return m.RegionHit(
        key=4,
        score=0.9,
        label="chair",
        bbox_min=np.zeros(3, np.float32),
        bbox_max=np.ones(3, np.float32),
        num_points=5,
        points=_f32(5, 3) if with_points else None,
    )


EXAMPLES: dict[str, m.Message] = {
    "sensor.rgbd": m.RgbdFrame(
        frame_id=1,
        stamp_ns=5,
        **K_FIELDS,
        T_world_cam=_pose(),
        depth_scale=1.0,
        color=rng.integers(0, 255, (6, 8, 3), dtype=np.uint8),
        depth=_f32(6, 8),
        instance=_i32(6, 8),
        instance_categories={3: "office chair"},
        source="synthetic",
    ),
    "sensor.instance": m.InstanceFrame(
        frame_id=1, stamp_ns=5, instance=_i32(6, 8), instance_categories={3: "office chair"}, source="synthetic"
    ),
    "geometry.progress": m.GeometryProgress(frame_id=1, stamp_ns=5, integrated=True, frames_integrated=9, queued=2),
    "geometry.render_request": m.RenderRequest(frame_id=2, T_world_cam=_pose(), after_update_source="a1b2",
                                               after_update_seq=4, **K_FIELDS),
    "geometry.render_reply": m.RenderReply(
        frame_id=2, key_map=_i32(6, 8), conf_map=_f32(6, 8), depth_m=_f32(6, 8)
    ),
    "geometry.points_request": m.PointsRequest(keys=[1, 2], max_points=10),
    "geometry.points_reply": m.PointsReply(
        points=_f32(4, 3), colors=np.zeros((4, 3), np.uint8), keys=_i32(4), truncated=True
    ),
    "geometry.regions_request": m.RegionSummaryRequest(keys=[3, 4], fresh=True),
    "geometry.regions_reply": m.RegionSummaryReply(
        map_version=12,
        key_horizon=9,
        age_s=0.25,
        keys=np.array([3, 4], np.int32),
        bbox_min=_f32(2, 3),
        bbox_max=_f32(2, 3) + 1.0,
        num_points=np.array([10, 0], np.int64),
    ),
    "geometry.contacts_request": m.RegionContactsRequest(radius_vox=2),
    "geometry.contacts_reply": m.RegionContactsReply(
        map_version=7,
        keys=np.array([1, 4, 6], np.int32),
        surface_voxels=np.array([300, 20, 5], np.int64),
        pair_a=np.array([1, 4], np.int32),
        pair_b=np.array([4, 6], np.int32),
        contact_a=np.array([12, 3], np.int64),
        contact_b=np.array([9, 2], np.int64),
    ),
    "geometry.mesh_request": m.MeshRequest(keys=None),
    "geometry.mesh_reply": m.MeshReply(
        vertices=_f32(3, 3),
        triangles=np.array([[0, 1, 2]], np.int32),
        vertex_colors=np.zeros((3, 3), np.uint8),
        vertex_keys=_i32(3),
    ),
    "semantic.update": m.SemanticUpdate(
        frame_id=3,
        T_world_cam=_pose(),
        **K_FIELDS,
        key_map=_i32(6, 8),
        conf_map=_f32(6, 8),
        new_keys=np.array([7, 8], np.int32),
        source="a1b2",
        seq=4,
    ),
    "semantic.dictionary_request": m.DictionaryRequest(),
    "semantic.dictionary": m.DictionarySnapshot(
        embedding_space="minilm-l6-v2",
        dim=4,
        version=9,
        next_key=3,
        keys=np.array([1, 2], np.int32),
        embeddings=_f32(2, 4),
        counts=np.array([3, 1], np.int64),
        labels=["chair", ""],
        merged_keys=np.array([0], np.int32),
        merged_into=np.array([2], np.int32),
    ),
    "semantic.merge_request": m.MergeRequest(),
    "semantic.merge_reply": m.MergeReply(ok=True, regions_merged=3, regions_pruned=1, dictionary_version=12),
    "semantic.dictionary_delta": m.DictionaryDelta(
        embedding_space="minilm-l6-v2",
        dim=4,
        version=10,
        prev_version=9,
        next_key=7,
        keys=np.array([2], np.int32),
        embeddings=_f32(1, 4),
        counts=np.array([2], np.int64),
        labels=["table"],
        removed_keys=np.array([5, 6], np.int32),
        merged_into=np.array([2, -1], np.int32),
    ),
    "query.text": m.TextQuery(text="a red chair", top_k=3, with_points=True, embedding_space="minilm-l6-v2"),
    "query.text_batch": m.TextQueryBatch(texts=["a red chair", "table"], top_k=3, with_points=True,
                                         embedding_space="minilm-l6-v2"),
    "query.image": m.ImageQuery(image=np.zeros((4, 5, 3), np.uint8), top_k=2),
    "query.point": m.PointQuery(point_world=np.array([1.0, 2.0, 3.0]), radius_m=0.2),
    "query.reply": m.QueryReply(
        embedding_space="minilm-l6-v2", query="chair", regions=[_hit(True), _hit(False)]
    ),
    "query.batch_reply": m.QueryBatchReply(replies=[
        m.QueryReply(embedding_space="minilm-l6-v2", query="chair", regions=[_hit(True), _hit(False)]),
        m.QueryReply(embedding_space="minilm-l6-v2", query="lamp", regions=[]),
    ]),
    "control.request": m.ControlRequest(action="save", path="/tmp/map"),
    "control.reply": m.ControlReply(ok=False, message="no such file"),
    "geometry.checkpoint_list_request": m.CheckpointListRequest(checkpoint_first=False, requester="geometry-0of2-r1"),
    "geometry.checkpoint_listing": m.CheckpointListing(
        snapshot_id="ab" * 16, source="geometry-0of2",
        files=[m.CheckpointFile(name="map.ofz/data.mdb", size_bytes=123456, sha256="0f" * 32)],
        chunk_bytes=4 << 20, last_frame_id=41, frames_integrated=42, tiles=17),
    "geometry.checkpoint_chunk_request": m.CheckpointChunkRequest(
        snapshot_id="ab" * 16, name="map.ofz/data.mdb", offset_bytes=4 << 20, length_bytes=4 << 20),
    "geometry.checkpoint_chunk": m.CheckpointChunk(
        snapshot_id="ab" * 16, name="map.ofz/data.mdb", offset_bytes=0, data=np.arange(10, dtype=np.uint8),
        sha256="1e" * 32),
    "geometry.checkpoint_release": m.CheckpointRelease(snapshot_id="ab" * 16),
    "health.stats": m.HealthStats(
        service="geometry",
        map_id="lab",
        pid=12,
        uptime_s=3.5,
        fps=30.0,
        latency_ms_p50=4.0,
        latency_ms_p99=9.0,
        drops=2,
        errors=0,
        counters={"blocks": 5700.0},
    ),
    "error": m.ErrorReply(reason="bad", code="handler_error"),
    "pool.worker_info_request": m.WorkerInfoRequest(),
    "pool.worker_info": m.WorkerInfo(worker_id="gpu1-0", encoder="clip-dense", embedding_space="clip-vit-b-32", dim=512,
                                     device="cuda", needs_instances=False, max_in_flight=2),
    "pool.encode_request": m.EncodeRequest(
        frame_id=1, stamp_ns=5, **K_FIELDS, T_world_cam=_pose(), depth_scale=1.0,
        color=rng.integers(0, 255, (6, 8, 3), dtype=np.uint8), depth=_f32(6, 8), instance=_i32(6, 8),
        instance_categories={3: "office chair"}, source="synthetic", map_id="lab", embedding_space="minilm-l6-v2",
    ),
    "pool.encode_reply": m.EncodeReply(frame_id=1, worker_id="gpu1-0", embedding_space="minilm-l6-v2",
                                       conf_maps=_f32(3, 2, 2), embeddings=_f32(3, 4), encode_ms=12.5),
}


def _assert_same(a: Any, b: Any) -> None:
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    elif isinstance(a, m.Record):
        assert type(a) is type(b)
        for name in type(a).model_fields:
            _assert_same(getattr(a, name), getattr(b, name))
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _assert_same(x, y)
    else:
        assert a == b


def test_every_registered_schema_has_an_example() -> None:
    """A new message without a round-trip example here fails (keep this table complete)."""
    library = {n for n, cls in registered_schemas().items() if cls.__module__.startswith("openfusion.wire.schemas")}
    assert library == set(EXAMPLES)


@pytest.mark.parametrize("schema", sorted(EXAMPLES))
def test_every_message_round_trips(schema: str) -> None:
    """Each message (incl. nested RegionHit lists and optional arrays) decodes equal to what was sent."""
    msg = EXAMPLES[schema]
    assert type(msg).schema_name == schema and isinstance(type(msg).schema_version, int)
    out = decode(encode(msg), expected=type(msg))
    _assert_same(msg, out)


def test_rgbd_frame_from_and_to_frame() -> None:
    """A Frame converts to RgbdFrame and back; an invalid Frame is refused by Frame.validate()."""
    frame = EXAMPLES["sensor.rgbd"].to_frame()
    assert isinstance(frame, Frame) and frame.intrinsics == K
    again = m.RgbdFrame.from_frame(frame)
    _assert_same(again, EXAMPLES["sensor.rgbd"])
    frame.depth = frame.depth[:, :4]
    with pytest.raises(ValueError, match="color must be 6x4x3"):
        m.RgbdFrame.from_frame(frame)


def test_frame_splits_into_rgbd_without_instance_and_instance_frame_and_joins_back() -> None:
    """The bridge's split: geometry's message carries no instance image; the semantic service
    joins the InstanceFrame back by frame id + stamp. Bad input tried: an instance image of
    another frame (other stamp) and one of another size are refused naming the problem."""
    frame = EXAMPLES["sensor.rgbd"].to_frame()
    rgbd = m.RgbdFrame.from_frame(frame, with_instance=False)
    assert rgbd.instance is None and rgbd.instance_categories == {}
    inst = m.InstanceFrame.from_frame(frame)
    assert inst is not None and inst.belongs_to(rgbd)
    joined = rgbd.to_frame(inst)
    np.testing.assert_array_equal(joined.instance, frame.instance)
    assert joined.instance_categories == {3: "office chair"}
    assert rgbd.to_frame().instance is None
    assert m.InstanceFrame.from_frame(rgbd.to_frame()) is None  # nothing to send without an image
    other = m.InstanceFrame(**_replace(inst, stamp_ns=6))
    with pytest.raises(ValueError, match="instance image of frame 1 \\(stamp 6 ns, robot robot0\\) joined to frame 1 "
                                         "\\(stamp 5 ns, robot robot0\\)"):
        rgbd.to_frame(other)
    # Frame ids are per robot: another robot's frame 1 (same stamp) is another frame.
    assert not m.InstanceFrame(**_replace(inst, robot="robot1")).belongs_to(rgbd)
    with pytest.raises(ValueError, match="robot robot1\\) joined to frame 1"):
        rgbd.to_frame(m.InstanceFrame(**_replace(inst, robot="robot1")))
    small = m.InstanceFrame(**_replace(inst, instance=_i32(5, 8)))
    with pytest.raises(ValueError, match="instance is 8x5 but the intrinsics are for 8x6"):
        rgbd.to_frame(small)


def _replace(msg: m.Message, **changes: Any) -> dict[str, Any]:
    return {**{k: getattr(msg, k) for k in type(msg).model_fields}, **changes}


@pytest.mark.parametrize(
    ("schema", "changes", "message"),
    [
        ("sensor.rgbd", {"depth": np.zeros((6, 8), np.int32)}, "dtype int32"),
        ("sensor.rgbd", {"instance": np.zeros((5, 8), np.int32)}, "instance must be 6x8"),
        ("sensor.rgbd", {"T_world_cam": np.diag([2.0, 1.0, 1.0, 1.0])}, "orthonormal"),
        ("sensor.instance", {"instance": np.zeros((6, 8), np.int64)}, "dtype int64"),
        ("sensor.instance", {"instance": np.zeros((0, 8), np.int32)}, "empty"),
        ("sensor.instance", {"frame_id": -1}, "greater than or equal to 0"),
        ("geometry.progress", {"queued": -1}, "greater than or equal to 0"),
        ("geometry.progress", {"integrated": "perhaps"}, "valid boolean"),
        ("geometry.render_request", {"T_world_cam": np.full((4, 4), np.inf)}, "finite"),
        ("geometry.render_request", {"after_update_seq": 3, "after_update_source": ""}, "must name after_update_source"),
        ("geometry.render_request", {"after_update_seq": -1}, "greater than or equal to 0"),
        ("geometry.render_request", {"probe_depth_m": _f32(6, 7)}, "probe_depth_m is"),
        ("geometry.render_request", {"probe_depth_m": np.full((6, 8), np.nan, np.float32)}, "finite and >= 0"),
        ("geometry.render_request", {"probe_depth_m": np.full((6, 8), -1.0, np.float32)}, "finite and >= 0"),
        ("geometry.render_reply", {"depth_m": _f32(6, 7)}, "same shape"),
        ("geometry.points_reply", {"keys": _i32(3)}, "differ in length"),
        ("geometry.mesh_reply", {"triangles": np.array([[0, 1, 3]], np.int32)}, "outside 0..2"),
        ("geometry.regions_reply", {"num_points": np.array([1], np.int64)}, "differ in length"),
        ("geometry.regions_reply", {"keys": np.array([3, 3], np.int32)}, "unique"),
        ("geometry.regions_reply", {"num_points": np.array([1, -1], np.int64)}, "num_points must be >= 0"),
        ("geometry.regions_reply", {"map_version": -1}, "greater than or equal to 0"),
        ("geometry.contacts_request", {"radius_vox": 0}, "greater than or equal to 1"),
        ("geometry.contacts_reply", {"contact_b": np.array([9], np.int64)}, "same length"),
        ("geometry.contacts_reply", {"pair_a": np.array([4, 4], np.int32)}, "pair_a < pair_b"),
        ("geometry.contacts_reply", {"surface_voxels": np.array([1, -2, 3], np.int64)}, "surface_voxels must be >= 0"),
        ("geometry.contacts_reply", {"keys": np.array([1, 1, 6], np.int32)}, "unique"),
        ("semantic.update", {"conf_map": _f32(3, 4)}, "conf_map is 4x3"),
        ("semantic.update", {"seq": 2, "source": ""}, "must name its source"),
        ("semantic.dictionary", {"embeddings": _f32(2, 5)}, "must be \\(2, 4\\)"),
        ("semantic.dictionary", {"keys": np.array([1, 1], np.int32)}, "unique"),
        ("semantic.dictionary", {"merged_into": np.array([2, 1], np.int32)}, "one entry per merged key"),
        ("semantic.dictionary", {"merged_keys": np.array([1], np.int32)}, "cannot also be a live key"),
        ("semantic.dictionary", {"merged_into": np.array([5], np.int32)}, "end in a live key"),
        ("semantic.merge_reply", {"regions_merged": -1}, "greater than or equal to 0"),
        ("semantic.dictionary_delta", {"merged_into": np.array([2], np.int32)}, "one entry per removed key"),
        ("semantic.dictionary_delta", {"prev_version": 10}, "greater than prev_version"),
        # the limits of openfusion.wire.limits, with the lines every surface gives
        ("query.text", {"text": ""}, "the query text is empty"),
        ("query.text", {"text": "x" * 513}, "the query text has 513 characters; the limit is 512"),
        ("query.text", {"top_k": 0}, "top_k must be from 1 to 100, got 0"),
        ("query.text", {"top_k": 101}, "top_k must be from 1 to 100, got 101"),
        ("query.text", {"max_points": 200_001}, "max_points must be from 1 to 200,000, got 200001"),
        ("query.text_batch", {"texts": []}, "a batch holds 1 to 64 texts, got 0"),
        ("query.text_batch", {"texts": ["chair"] * 65}, "a batch holds 1 to 64 texts, got 65"),
        ("query.text_batch", {"texts": ["chair", ""]}, "the query text 2 of 2 is empty"),
        ("query.text_batch", {"texts": ["x" * 600]}, "the query text has 600 characters; the limit is 512"),
        ("query.text_batch", {"texts": "chair"}, "valid list"),
        ("query.text_batch", {"top_k": 0}, "top_k must be from 1 to 100, got 0"),
        ("query.point", {"top_k": 10_000}, "top_k must be from 1 to 100, got 10000"),
        ("query.batch_reply", {"replies": [{"embedding_space": "s", "query": "q", "regions": 3}]},
         r"replies\.0\.regions"),
        ("query.image", {"image": np.zeros((0, 5, 3), np.uint8)}, "must not be empty"),
        ("query.point", {"point_world": np.array([1.0, np.nan, 0.0])}, "finite"),
        ("control.request", {"action": "drop"}, "'save', 'load' or 'reset'"),
        ("health.stats", {"fps": -1.0}, "greater than or equal to 0"),
        ("pool.encode_reply", {"embeddings": _f32(2, 4)}, "3 confidence maps but 2 embeddings"),
        ("pool.encode_request", {"depth": _f32(6, 7)}, "color must be 6x7x3"),
        ("pool.worker_info", {"max_in_flight": 0}, "greater than or equal to 1"),
    ],
)
def test_inconsistent_messages_are_refused(schema: str, changes: dict[str, Any], message: str) -> None:
    """Wrong dtypes, shapes that disagree between fields, bad poses, out-of-range values."""
    msg = EXAMPLES[schema]
    with pytest.raises(ValidationError, match=message):
        type(msg)(**_replace(msg, **changes))


def test_nested_region_hit_errors_name_their_location() -> None:
    """A bad RegionHit inside QueryReply is refused and the error names regions.0.bbox_min."""
    bad = _hit(False).model_dump()
    bad["bbox_min"] = np.zeros(2, np.float32)
    with pytest.raises(ValidationError, match=r"regions\.0\.bbox_min"):
        m.QueryReply(embedding_space="s", query="q", regions=[bad])


def test_schema_names_are_unique_and_need_a_version() -> None:
    """Registering a second class under an existing schema name, or without a version, fails."""
    with pytest.raises(TypeError, match="already registered"):

        class Clash(m.Message):
            schema_name: ClassVar[str] = "sensor.rgbd"
            schema_version: ClassVar[int] = 1

    with pytest.raises(TypeError, match="schema_version"):

        class NoVersion(m.Message):
            schema_name: ClassVar[str] = "test.messages.no_version"
