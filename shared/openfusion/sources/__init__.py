"""Frame sources: dataset readers, the synthetic world, live sensors, ROS 2 and record/replay.

Every source yields ``openfusion.frame.Frame`` in the canonical convention (metres, OpenCV
camera axes, camera-to-world ``T_world_cam``); each reader module says in its docstring what
it converted from. See docs/ARCHITECTURE.md, "Sources".

=====================  =====================================================================
module                 what
=====================  =====================================================================
``base``               ``FrameSource``, ``SourceStats``, skip counting
``registry``           ``open_source(spec, **options)``
``scannet``            ScanNet export reader (+ label tsv, instance categories)
``scannet_writer``     ``write_scannet_layout``: any source -> ScanNet layout on disk
``record_scannet``     ``python -m openfusion.sources.record_scannet SPEC OUT``: that, from a source spec
``replica``            Replica (NICE-SLAM release)
``tum``                TUM RGB-D (timestamp association, pose interpolation)
``redwood``            Redwood / Open3D captures (``trajectory.log``)
``folder``             any folder described by ``openfusion_source.json``
``synthetic``          the embedded worlds: a furnished room and a building of them (ray-cast RGB-D + ground truth)
``synthetic_spec``     the ``synthetic[:building],key=value`` options and routes, parsed without building the world
``sync``               image/pose time pairing, T265 axes, downsampling (live sources)
``live``               Azure Kinect + Intel T265 (optional extra ``live``)
``cdr``                ROS 2 messages in CDR through ``rosbags`` (thin adapter, image pixels)
``ros2``               live ROS 2 topics over Zenoh (bridge and rmw_zenoh layouts), publisher
``ros2_frames``        ROS 2 messages -> frames: topics, config, ``Ros2FrameAssembler`` (no bus)
``ros_layout``         ROS 2 topic -> Zenoh key in both layouts, rmw_zenoh attachment
``rosbag``             rosbag2 recordings (folder, .mcap, .db3) via ``rosbags``
``rosbag_writer``      ``write_rosbag``: any source -> rosbag2
``record``             ``FrameRecorder`` / ``ReplaySource`` (length-prefixed RgbdFrame files)
=====================  =====================================================================
"""

from openfusion.sources.base import FrameSource, IndexedFrameSource, Skip, SkipFrame, SourceStats
from openfusion.sources.registry import SCHEMES, open_source

__all__ = ["SCHEMES", "FrameSource", "IndexedFrameSource", "Skip", "SkipFrame", "SourceStats", "open_source"]
