"""The semantic service's settings (:class:`SemanticSection`, ``[semantic]`` of a config file and
``openfusion run``'s options derive from it) and the semantic switch (:class:`SemanticSwitch`: which
frame ids get semantics at all, before any frame selection)."""

from __future__ import annotations

from pydantic import Field

from openfusion.config import ServiceConfig
from openfusion.mapping.params import MatchParams, MergeParams, SelectParams
from openfusion.services.encoder.options import EncoderOptions


class SemanticSection(MatchParams, MergeParams, SelectParams, EncoderOptions):
    """The semantic service's settings: every matching, merging and frame-selection parameter
    (:class:`MatchParams`, :class:`MergeParams`, :class:`SelectParams`, declared there once), the
    local encoder (:class:`EncoderOptions`, shared with the encoder workers) and the service's own."""

    encoder_pool: bool = Field(
        False, description="send frames to the encoder pool's workers (openfusion service encoder) instead of "
        "encoding them here"
    )
    local_encoder: bool = Field(True, description="with encoder_pool: encode here while no worker is alive")
    pool_reorder_wait_s: float = Field(
        1.0, ge=0, description="with encoder_pool: a result waits at most this long for older frames still in "
        "flight, so results apply in frame order without dropping the older ones")
    pool_timeout_s: float = Field(30.0, gt=0, description="with encoder_pool: a worker that has not answered a frame "
                                  "within this many seconds is taken for dead")
    every_k: int = Field(
        1, ge=0, description="semantics on every k-th frame id (0 = off)", json_schema_extra={"flag": "--semantic-every"}
    )
    max_hz: float | None = Field(None, gt=0, description="at most this many semantic frames per second")
    render_timeout_s: float = Field(5.0, gt=0, description="wait this long for geometry's render of a frame")
    contacts_timeout_s: float = Field(
        30.0, gt=0, description="a merge pass waits this long for geometry's region contacts (a floor's first "
        "pass after a long walk reads out many tiles: over 5 s on 2 cores, when every pass was skipped)")
    merge_min_interval_s: float = Field(
        2.0, ge=0, description="at least this long between two periodic merge passes (a pass costs geometry a "
        "contacts read-out; with a fast encoder pool merge_every frames come many times a second)")
    instance_wait_s: float = Field(
        0.5, ge=0, le=10, description="gt encoder: wait this long for a frame's instance image, then skip the frame"
    )
    integrate_wait_s: float = Field(
        2.0, ge=0, description="before rendering the map for a frame it fuses, wait this long at most for geometry "
        "to have integrated the frame (its geometry/progress acknowledgement; 0 = never wait)")
    recover_timeout_s: float = Field(
        10.0, ge=0, description="at start, try this long to recover the map's dictionary from geometry (0 = never)"
    )


#: select=every: frames waiting for the encoder (a slower encoder drops the oldest, counted as drops).
EVERY_QUEUE = 64
#: select=latest: frames waiting on the subscription while the encoder is busy (the oldest go first,
#: counted ``frames_dropped``), and frames kept for geometry to take (about 2.8 MB each at 640x480;
#: geometry runs at most the bridge's ``max_in_flight``, 16, behind the newest, and at camera rate a
#: few): latest-only memory, a few frames in hand, not a queue of every frame.
LATEST_QUEUE = 4
LATEST_BUFFER = 16
#: Instance images kept beyond the frames the rgbd queue holds (one is sent just before its frame).
INSTANCE_MARGIN = 16


class SemanticConfig(ServiceConfig):
    semantic: SemanticSection = Field(default_factory=SemanticSection)


class SemanticSwitch:
    """Decides which frames get semantics: off (every_k=0), every k-th frame id, at most max_hz."""

    def __init__(self, every_k: int, max_hz: float | None) -> None:
        self.every_k = every_k
        self.max_hz = max_hz
        self._last_s: float | None = None

    def accept(self, frame_id: int, now_s: float) -> bool:
        if self.every_k == 0 or frame_id % self.every_k != 0:
            return False
        if self.max_hz is not None and self._last_s is not None and now_s - self._last_s < 1.0 / self.max_hz:
            return False
        self._last_s = now_s
        return True
