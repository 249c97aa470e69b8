"""Frames on the bus: ``sensor/rgbd`` and ``sensor/instance``."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field, model_validator

from openfusion.frame import Frame
from openfusion.wire.message import Message
from openfusion.wire.schemas.base import (
    DEFAULT_ROBOT,
    DepthImage,
    ImageRGB8,
    KeyMap,
    PinholeMessage,
    Pose4x4,
    RobotName,
)


class RgbdFrame(PinholeMessage):
    """One registered RGB-D frame with its camera-to-world pose (see :class:`openfusion.frame.Frame`).

    ``playback`` and ``prev_frame_id`` (v2): in a playback the bridge can replay, the playback's
    name (new for each bridge process) and the id of the frame it published before this one (-1 for
    the first): geometry integrates a frame only right after that one, so after a restart it neither
    skips nor repeats a frame (:mod:`openfusion.services.geometry.service`). ``""`` and None for
    live frames (taken as they come).

    ``robot`` (v3): the robot whose stream the frame belongs to. Frame ids, playbacks, chains and
    poses are per robot: ``T_world_cam`` is in that robot's odometry frame, which geometry joins to
    the map's (:mod:`openfusion.mapping.robot_join`)."""

    schema_name: ClassVar[str] = "sensor.rgbd"
    schema_version: ClassVar[int] = 3
    #: recordings of v2 frames (before robots) still replay: their robot is the default one
    reads_versions: ClassVar[tuple[int, ...]] = (2,)

    frame_id: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    T_world_cam: Pose4x4
    depth_scale: float = Field(gt=0)
    color: ImageRGB8
    depth: DepthImage
    instance: KeyMap | None = None
    instance_categories: dict[int, str] = Field(default_factory=dict)
    source: str = ""
    playback: str = Field("", max_length=64)
    prev_frame_id: int | None = Field(None, ge=-1)
    robot: RobotName = DEFAULT_ROBOT

    @model_validator(mode="after")
    def _check_frame(self) -> RgbdFrame:
        with np.errstate(all="ignore"):  # a garbage pose must fail validation, not overflow-warn
            self.to_frame().validate()
        return self

    @classmethod
    def from_frame(cls, frame: Frame, *, with_instance: bool = True, playback: str = "",
                   prev_frame_id: int | None = None, robot: str = DEFAULT_ROBOT) -> RgbdFrame:
        """The message of a frame (arrays are not copied). ``with_instance=False`` leaves the
        ground-truth instance image out: the bridge sends it on its own key
        (:class:`InstanceFrame`), so geometry never receives those bytes."""
        frame.validate()
        return cls(
            frame_id=frame.frame_id,
            stamp_ns=frame.stamp_ns,
            **cls.intrinsics_fields(frame.intrinsics),
            T_world_cam=np.asarray(frame.T_world_cam, dtype=np.float64),
            depth_scale=frame.depth_scale,
            color=frame.color,
            depth=frame.depth,
            instance=frame.instance if with_instance else None,
            instance_categories=dict(frame.instance_categories) if with_instance else {},
            source=frame.source,
            playback=playback,
            prev_frame_id=prev_frame_id,
            robot=robot,
        )

    def to_frame(self, instance: InstanceFrame | None = None) -> Frame:
        """The in-memory frame (arrays are shared, so read-only after :func:`codec.decode`).

        ``instance``: the frame's :class:`InstanceFrame` from ``…/sensor/instance``, joined in
        place of this message's own (usually absent) instance image. Raises ValueError when it
        belongs to another frame or its image size differs."""
        inst, categories = self.instance, dict(self.instance_categories)
        if instance is not None:
            if not instance.belongs_to(self):
                raise ValueError(
                    f"instance image of frame {instance.frame_id} (stamp {instance.stamp_ns} ns, robot "
                    f"{instance.robot}) joined to frame {self.frame_id} (stamp {self.stamp_ns} ns, robot {self.robot})"
                )
            self._check_image("instance", instance.instance)
            inst, categories = instance.instance, dict(instance.instance_categories)
        return Frame(
            frame_id=self.frame_id,
            stamp_ns=self.stamp_ns,
            color=self.color,
            depth=self.depth,
            depth_scale=self.depth_scale,
            intrinsics=self.intrinsics,
            T_world_cam=self.T_world_cam,
            instance=inst,
            instance_categories=categories,
            source=self.source,
        )


class InstanceFrame(Message):
    """Ground-truth instance ids of one frame, on ``…/sensor/instance`` next to its
    :class:`RgbdFrame` (same ``frame_id`` and ``stamp_ns``).

    Sources with labels (synthetic scene, ScanNet ``instance-filt``, Replica) have them; only the
    gt encoder of the semantic service reads them. Keeping them off ``…/sensor/rgbd`` saves
    geometry 45 % of each 640x480 frame's bytes (the int32 image is larger than color and depth
    together). ``instance`` is HxW int32 (0 = no instance); ``instance_categories`` maps ids to
    raw category names. ``robot`` (v2): the frame's robot (frame ids are per robot).
    """

    schema_name: ClassVar[str] = "sensor.instance"
    schema_version: ClassVar[int] = 2

    frame_id: int = Field(ge=0)
    stamp_ns: int = Field(ge=0)
    instance: KeyMap
    instance_categories: dict[int, str] = Field(default_factory=dict)
    source: str = ""
    robot: RobotName = DEFAULT_ROBOT

    @model_validator(mode="after")
    def _check_not_empty(self) -> InstanceFrame:
        if self.instance.size == 0:
            raise ValueError(f"instance image is empty ({self.instance.shape})")
        return self

    @classmethod
    def from_frame(cls, frame: Frame, *, robot: str = DEFAULT_ROBOT) -> InstanceFrame | None:
        """The instance message of a frame, or None when the frame has no instance image."""
        if frame.instance is None:
            return None
        return cls(
            frame_id=frame.frame_id,
            stamp_ns=frame.stamp_ns,
            instance=frame.instance,
            instance_categories=dict(frame.instance_categories),
            source=frame.source,
            robot=robot,
        )

    def belongs_to(self, msg: RgbdFrame) -> bool:
        """Same robot, frame id and time stamp as ``msg``."""
        return self.frame_id == msg.frame_id and self.stamp_ns == msg.stamp_ns and self.robot == msg.robot
