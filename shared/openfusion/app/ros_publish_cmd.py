"""``openfusion ros-publish``: a running map's answers as ROS 2 topics, for RViz and Foxglove.

    openfusion ros-publish "chair" [--map ID] [--connect EP] [--layout bridge|rmw_zenoh]
        [--domain-id N] [--ros-namespace NS] [--ros-connect EP] [--frame-id map]
        [--map-cloud] [--every S | --once] [--distro jazzy|humble]

Each round (every ``--every`` seconds, 2 by default; once with ``--once``, which first waits up
to ``--timeout`` for a subscriber on each topic, so the one round is not sent before the route to a
subscriber exists; publishers block rather than drop a message when the link is busy) it asks the query
service (:class:`~openfusion.client.OpenFusionClient`, with points) and publishes

| topic | type | what |
|---|---|---|
| ``/openfusion/query/points`` | ``sensor_msgs/PointCloud2`` | the answers' points (x, y, z, rgb, region), each answer in its rank's colour |
| ``/openfusion/query/markers`` | ``visualization_msgs/MarkerArray`` | a box per answer and its label + score |
| ``/openfusion/map/points`` (``--map-cloud``) | ``sensor_msgs/PointCloud2`` | the whole labelled map (surface colour, region key), at most every 10 s |

in the chosen key layout (:class:`~openfusion.sources.ros2.Ros2Publisher`): ``bridge`` for a robot
running zenoh-bridge-ros2dds, ``rmw_zenoh`` for one running ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``.
Messages are serialised by ``rosbags`` for ``--distro`` (the robot's ROS 2 distribution; it picks
the type hash rmw_zenoh keys carry). The ROS messages go on the map's Zenoh session unless
``--ros-connect`` names the robot's router (``rmw_zenohd``, or the bridge's listen endpoint).
The frame id (``--frame-id``, default ``map``) is the map's world frame; set RViz's fixed frame to it.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from typing import Any

from openfusion.app.quiet import quiet_libraries
from openfusion.config import add_config_arguments, config_from_args, setup_logging
from openfusion.errors import UsageError

logger = logging.getLogger(__name__)

QUERY_POINTS_TOPIC = "/openfusion/query/points"
QUERY_MARKERS_TOPIC = "/openfusion/query/markers"
MAP_POINTS_TOPIC = "/openfusion/map/points"
MAP_CLOUD_EVERY_S = 10.0


def publish_answers(publisher: Any, texts: list[str], replies: list[Any], *, frame_id: str, stamp_ns: int,
                    distro: str) -> int:
    """Publish the points and markers of query replies (one per text); returns the number of regions."""
    from openfusion.viz.ros_messages import MARKER_ARRAY, POINTCLOUD2, answer_cloud, answer_markers

    hits = [hit for reply in replies for hit in reply.regions]
    publisher.publish(QUERY_POINTS_TOPIC, POINTCLOUD2, answer_cloud(hits, frame_id=frame_id, stamp_ns=stamp_ns,
                                                                    distro=distro))
    publisher.publish(QUERY_MARKERS_TOPIC, MARKER_ARRAY, answer_markers(hits, frame_id=frame_id, stamp_ns=stamp_ns,
                                                                        distro=distro))
    return len(hits)


def publish_map_cloud(publisher: Any, points_reply: Any, *, frame_id: str, stamp_ns: int, distro: str) -> int:
    """Publish the map's surface points (a ``PointsReply``) as one PointCloud2; returns the point count."""
    from openfusion.viz.ros_messages import POINTCLOUD2, point_cloud2

    publisher.publish(MAP_POINTS_TOPIC, POINTCLOUD2, point_cloud2(points_reply.points, points_reply.colors,
                                                                  points_reply.keys, frame_id=frame_id,
                                                                  stamp_ns=stamp_ns, distro=distro))
    return len(points_reply.points)


class RosPublishCommand:
    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        from openfusion.sources.cdr import DISTROS
        from openfusion.sources.ros_layout import LAYOUTS

        parser.add_argument("text", nargs="+", metavar="TEXT", help="what to look for; several texts are published "
                            "together")
        parser.add_argument("--layout", choices=LAYOUTS, default="bridge",
                            help="ROS 2 key layout: bridge (zenoh-bridge-ros2dds) or rmw_zenoh (default bridge)")
        parser.add_argument("--domain-id", type=int, default=0, help="rmw_zenoh: the robot's ROS_DOMAIN_ID (default 0)")
        parser.add_argument("--ros-namespace", default="", help="ROS namespace of the topics (bridge: its --namespace)")
        parser.add_argument("--ros-connect", default=None, metavar="EP",
                            help="publish the ROS messages on a session connected here (the robot's router) "
                                 "instead of the map's session")
        parser.add_argument("--distro", choices=DISTROS, default="jazzy", help="the robot's ROS 2 distribution")
        parser.add_argument("--keyed-attachment", action="store_true",
                            help="rmw_zenoh releases before PR #601 (2025): key strings in the attachment")
        parser.add_argument("--frame-id", default="map", help="frame id of the messages (the map's world frame)")
        parser.add_argument("--top-k", type=int, default=5, help="regions per text (default 5)")
        parser.add_argument("--max-points", type=int, default=20_000, help="points per region at most")
        parser.add_argument("--map-cloud", action="store_true",
                            help=f"also publish the whole labelled map on {MAP_POINTS_TOPIC} (every "
                                 f"{MAP_CLOUD_EVERY_S:g} s at most)")
        parser.add_argument("--every", type=float, default=2.0, help="seconds between rounds (default 2)")
        parser.add_argument("--once", action="store_true", help="publish one round and exit")
        parser.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the services (and, with --once, for a subscriber on each topic)")
        add_config_arguments(parser)

    @staticmethod
    def run(args: argparse.Namespace) -> int:
        import zenoh

        from openfusion.client import OpenFusionClient
        from openfusion.sources.ros2 import Ros2Publisher
        from openfusion.viz.ros_messages import MARKER_ARRAY, POINTCLOUD2
        from openfusion.wire.limits import check_max_points, check_text, check_top_k

        if any(not t.strip() for t in args.text):
            raise UsageError("a query text is empty")
        if args.every <= 0:
            raise UsageError(f"--every must be positive, got {args.every:g}")
        for i, text in enumerate(args.text):  # the one set of limits (openfusion.wire.limits), before joining
            check_text(text, which=f"text {i + 1} of {len(args.text)} " if len(args.text) > 1 else "")
        check_top_k(args.top_k, name="--top-k")
        check_max_points(args.max_points, name="--max-points")
        if args.domain_id < 0:
            raise UsageError(f"--domain-id must be >= 0 (the robot's ROS_DOMAIN_ID), got {args.domain_id}")
        config = config_from_args(args)
        setup_logging(config.log_level if args.log_level else "WARNING")
        texts = [t.strip() for t in args.text]
        ros_session = None
        with quiet_libraries(True), OpenFusionClient.from_config(config, timeout_s=args.timeout) as client:
            if args.ros_connect:
                zconf = zenoh.Config()
                zconf.insert_json5("mode", '"client"')
                zconf.insert_json5("connect/endpoints", f'["{args.ros_connect}"]')
                ros_session = zenoh.open(zconf)
            publisher = Ros2Publisher(ros_session or client.session, layout=args.layout, namespace=args.ros_namespace,
                                      domain_id=args.domain_id, distro=args.distro,
                                      keyed_attachment=args.keyed_attachment)
            last_map = float("-inf")
            if args.once:
                topics = [(QUERY_POINTS_TOPIC, POINTCLOUD2), (QUERY_MARKERS_TOPIC, MARKER_ARRAY)]
                topics += [(MAP_POINTS_TOPIC, POINTCLOUD2)] if args.map_cloud else []
                waiting = publisher.wait_for_subscribers(topics, args.timeout)
                if waiting:
                    print(f"no subscriber on {', '.join(waiting)} after {args.timeout:g} s; publishing anyway",
                          file=sys.stderr, flush=True)
            try:
                while True:
                    stamp = time.time_ns()
                    replies = client.query_texts(texts, top_k=args.top_k, with_points=True, max_points=args.max_points)
                    n = publish_answers(publisher, texts, replies, frame_id=args.frame_id, stamp_ns=stamp,
                                        distro=args.distro)
                    line = f"published {n} region(s) for {', '.join(repr(t) for t in texts)} ({args.layout} layout)"
                    if args.map_cloud and time.monotonic() - last_map >= MAP_CLOUD_EVERY_S:
                        count = publish_map_cloud(publisher, client.points(), frame_id=args.frame_id, stamp_ns=stamp,
                                                  distro=args.distro)
                        last_map = time.monotonic()
                        line += f", map cloud of {count} points"
                    print(line, file=sys.stderr, flush=True)
                    if args.once:
                        publisher.flush(args.timeout)  # the round has left before the session closes
                        return 0
                    time.sleep(args.every)
            except KeyboardInterrupt:
                return 0
            finally:
                publisher.close()
                if ros_session is not None:
                    ros_session.close()
