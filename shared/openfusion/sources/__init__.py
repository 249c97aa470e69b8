"""Frame sources: dataset readers, the synthetic world, live sensors, ROS 2 and record/replay.

Every source yields ``openfusion.frame.Frame`` in the canonical convention (metres, OpenCV
camera axes, camera-to-world ``T_world_cam``); each reader module says in its docstring what
it converted from. See docs/ARCHITECTURE.md, "Sources".
"""

from openfusion.sources.base import FrameSource, IndexedFrameSource, SourceStats

__all__ = ["FrameSource", "IndexedFrameSource", "SourceStats"]
