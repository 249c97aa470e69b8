"""``openfusion ros-publish --once`` against running services (geometry and query on ServiceRunners in
this process, a router session, a stand-in semantic dictionary queryable, hash text encoder): the
answer to "table" and the labelled map arrive on a robot-side session in rmw_zenoh's layout, and
rosbags reads them: the answer cloud is the table region's points, the markers name it, the map
cloud carries every surface point with its region key."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from openfusion.app.cli import main
from openfusion.bus import Queryable, ServiceRunner
from openfusion.encoders import make_text_encoder
from openfusion.mapping import RegionDictionary
from openfusion.services.geometry.service import GeometryConfig, GeometrySection, GeometryService
from openfusion.services.query.service import QueryConfig, QuerySection, QueryService
from openfusion.sources.ros_layout import parse_attachment, topic_key
from openfusion.sources.synthetic import SyntheticSource, SyntheticWorld
from openfusion.testing.bus import LoopbackRouter, endpoint, wait_until
from openfusion.wire.endpoints import SEMANTIC_DICTIONARY
from openfusion.wire.schemas import DictionaryRequest, RgbdFrame, SemanticUpdate

pytestmark = pytest.mark.timeout(180)

WORLD = SyntheticWorld(0)
PROBE_KEY = "0/openfusion/probe"  # not a topic: it shows the robot's subscription is routed
TEXT = make_text_encoder("hash")


def _geometry() -> tuple[GeometryService, RegionDictionary]:
    """Geometry with instance ids as region keys (id - 1), and the dictionary of those regions."""
    geo = GeometryService(GeometryConfig(map_id="unit", geometry=GeometrySection(load_on_start=False)))
    seen = 0
    for f in SyntheticSource(WORLD, num_frames=4, width_px=160, height_px=120):
        geo.on_frame(RgbdFrame.from_frame(f))
        keys = f.instance.astype(np.int32) - 1
        geo.on_update(SemanticUpdate(frame_id=f.frame_id, T_world_cam=f.T_world_cam,
                                     **SemanticUpdate.intrinsics_fields(f.intrinsics), key_map=keys,
                                     conf_map=np.where(keys >= 0, 0.9, 0.0).astype(np.float32),
                                     new_keys=np.zeros(0, np.int32)))
        seen = max(seen, int(f.instance.max()))
    dictionary = RegionDictionary(TEXT.embedding_space, TEXT.dim)
    for key in range(seen):
        dictionary.add(TEXT.encode([WORLD.categories[key + 1]])[0], label=WORLD.categories[key + 1])
    return geo, dictionary


def test_ros_publish_once_sends_the_answer_and_the_map_in_the_rmw_zenoh_layout() -> None:
    geo, dictionary = _geometry()
    closers: list = []
    got: list[tuple[str, bytes, bytes | None]] = []
    try:
        router = LoopbackRouter("rospub", health_period_s=0.2)
        closers.append(router.close)
        sem = router.open_client()
        closers.append(sem.close)
        closers.append(Queryable(sem, SEMANTIC_DICTIONARY.key(router.keys), DictionaryRequest,
                                 lambda _r: dictionary.snapshot()).close)
        geo.config = router.config(GeometryConfig, geometry=geo.section)
        grunner = ServiceRunner(geo.config, "geometry").start()
        closers.append(grunner.close)
        geo.setup(grunner)
        grunner.ready()
        qs = QueryService(router.config(QueryConfig, query=QuerySection(text_encoder="hash")), text_encoder=TEXT)
        qrunner = ServiceRunner(qs.config, "query").start()
        closers.append(qrunner.close)
        qs.setup(qrunner)
        qrunner.ready()
        robot = router.open_client()  # a ROS 2 node's session, rmw_zenoh layout
        closers.append(robot.close)
        sub = robot.declare_subscriber("0/openfusion/**", lambda s: got.append(
            (str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes() if s.attachment else None)))
        closers.append(sub.undeclare)
        # The router knows the robot's subscription before the command publishes (--once sends
        # each message once): a probe put through the router reaches it.
        wait_until(lambda: sem.put(PROBE_KEY, b"probe") or any(k == PROBE_KEY for k, _p, _a in got), timeout_s=30)
        from openfusion.client import OpenFusionClient

        with OpenFusionClient.from_config(router.config(), timeout_s=20.0) as probe:
            wait_until(lambda: {"query", "geometry"} <= set(probe.live_services(timeout_s=1.0)), timeout_s=30)
        code = main(["ros-publish", "table", "--once", "--layout", "rmw_zenoh", "--map-cloud", "--top-k", "1",
                     "--map", router.map_id, "--mode", "client", "--connect", endpoint(router.port),
                     "--no-multicast"])
        assert code == 0
        wait_until(lambda: len([g for g in got if g[0] != PROBE_KEY]) >= 3, timeout_s=30,
                   describe=lambda: f"got {sorted({k for k, _p, _a in got})}")
    finally:
        for close in reversed(closers):
            close()
    ts = get_typestore(Stores.ROS2_JAZZY)
    by_key = {key: (payload, att) for key, payload, att in got if key != PROBE_KEY}
    k_points = topic_key("/openfusion/query/points", layout="rmw_zenoh", typename="sensor_msgs/msg/PointCloud2")
    k_markers = topic_key("/openfusion/query/markers", layout="rmw_zenoh", typename="visualization_msgs/msg/MarkerArray")
    k_map = topic_key("/openfusion/map/points", layout="rmw_zenoh", typename="sensor_msgs/msg/PointCloud2")
    assert set(by_key) == {k_points, k_markers, k_map}
    assert all(parse_attachment(att).sequence_number == 1 for _payload, att in by_key.values())
    table_key = next(k for k in range(len(dictionary)) if WORLD.categories[k + 1] == "table")

    def region_field(cloud) -> np.ndarray:  # noqa: ANN001 - a rosbags PointCloud2
        return np.frombuffer(cloud.data.tobytes(), dtype=np.dtype({"names": ["region"], "formats": ["<i4"],
                                                                  "offsets": [16], "itemsize": 20}))["region"]

    answer = ts.deserialize_cdr(by_key[k_points][0], "sensor_msgs/msg/PointCloud2")
    assert answer.width == len(geo.volume.extract_points(keys=[table_key]).points) > 0
    assert set(region_field(answer).tolist()) == {table_key}
    markers = ts.deserialize_cdr(by_key[k_markers][0], "visualization_msgs/msg/MarkerArray").markers
    assert markers[2].text.startswith("table ")
    whole = ts.deserialize_cdr(by_key[k_map][0], "sensor_msgs/msg/PointCloud2")
    surface = geo.volume.extract_points()
    assert whole.width == len(surface.points)
    assert sorted(set(region_field(whole).tolist())) == sorted(set(np.asarray(surface.keys).tolist()))
