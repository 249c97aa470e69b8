"""One time base for the frame stamps of several robots: what "seen lately" means in a shared map.

Frame selection's staleness floor (:mod:`openfusion.mapping.coverage`, ``select_stale_s``) compares
the stamp of a view with the stamp a region was last encoded at, whichever robot's frames those
were. Robots whose clocks agree (ROS time over NTP or chrony, robots started together in one
synthetic run) need nothing more. Robots whose clocks do not agree do: a rosbag recorded last month
played as robot 2 next to a live robot 1, or a simulated robot counting from 0 next to a real one
stamped in Unix time. Compared as they come, one robot's regions look stale for ever to the other
(its every view of them is encoded again, and the other robot's next chosen view sets them back)
and the other way round never stale.

:class:`MapClock` maps each robot's stamps onto the map's time:

- the first robot keeps its own stamps (offset 0);
- a robot seen later whose first stamp lies within :data:`CLOCK_AGREE_S` of the map's time (the
  latest map time seen) is taken to share that clock (offset 0: synchronised robots stay exact,
  one that joins an hour later included);
- otherwise its first frame is taken as the map's "now" (offset = map time - its first stamp):
  from then on its stamps advance the map's time at their own rate.

Each robot's own stamps keep their meaning elsewhere (the patience rule runs on each robot's own
frames, a held view is keyed by its own stamp); only comparisons across robots read map time.

Why a tolerance and not the arrival clock: the in-process pipeline and the eval play frames as fast
as they go, with no arrival time that means anything, and the rule must give both pipelines the
same choices. What it cannot see: clocks that disagree by less than the tolerance (a robot without
time synchronisation a few minutes off) are compared as they come.

Written here: a dictionary of offsets; no library keeps a fleet's time base for this.
"""

from __future__ import annotations

import math
import threading

#: First stamps within this many seconds of the map's time share its clock (see the module docstring).
CLOCK_AGREE_S = 3600.0


class MapClock:
    """Per-robot offsets onto the map's time (module docstring). Thread-safe."""

    def __init__(self, agree_s: float = CLOCK_AGREE_S) -> None:
        if not (math.isfinite(agree_s) and agree_s >= 0):
            raise ValueError(f"agree_s must be finite and >= 0, got {agree_s}")
        self.agree_s = float(agree_s)
        self._lock = threading.Lock()
        self._offset_s: dict[str, float] = {}
        self._now_s = -math.inf  # the latest map time seen

    def map_s(self, robot: str, stamp_s: float) -> float:
        """``stamp_s`` of ``robot``'s frame in map time (its offset fixed by its first stamp)."""
        stamp_s = float(stamp_s)
        with self._lock:
            offset = self._offset_s.get(robot)
            if offset is None:
                far = math.isfinite(self._now_s) and abs(stamp_s - self._now_s) > self.agree_s
                offset = self._offset_s[robot] = (self._now_s - stamp_s) if far else 0.0
            out = stamp_s + offset
            self._now_s = max(self._now_s, out)
            return out

    def offset_s(self, robot: str) -> float | None:
        """The offset of ``robot``'s stamps (None: not seen yet)."""
        with self._lock:
            return self._offset_s.get(robot)

    def reset(self) -> None:
        with self._lock:
            self._offset_s.clear()
            self._now_s = -math.inf
