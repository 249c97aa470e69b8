"""Array field types and the base of messages that carry pinhole intrinsics."""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from pydantic import AfterValidator, Field

from openfusion.frame import CameraIntrinsics
from openfusion.wire.codec import ndarray
from openfusion.wire.keys import segment_error
from openfusion.wire.message import Message

# Array field types used below.
Pose4x4 = ndarray("float64", shape=(4, 4))
Vec3f64 = ndarray("float64", shape=(3,))
Vec3f32 = ndarray("float32", shape=(3,))
ImageRGB8 = ndarray("uint8", shape=(None, None, 3))
DepthImage = ndarray("uint16", "float32", shape=(None, None))
KeyMap = ndarray("int32", shape=(None, None))
FloatMap = ndarray("float32", shape=(None, None))
KeyList = ndarray("int32", shape=(None,))
Points3f = ndarray("float32", shape=(None, 3))
Colors3u8 = ndarray("uint8", shape=(None, 3))

#: The robot a frame's stream belongs to when none is named (one robot: today's single stream).
DEFAULT_ROBOT = "robot0"


def check_robot_name(name: str) -> str:
    """A robot name is one key segment (ASCII letters, digits, ``_ - .``; at most 64 characters),
    so it can name a key, a log line or a config entry as it is."""
    why = segment_error(name) if len(name) <= 64 else "is longer than 64 characters"
    if why is not None:
        raise ValueError(f"robot name {name!r} is not valid: it {why}")
    return name


RobotName = Annotated[str, AfterValidator(check_robot_name)]


class PinholeMessage(Message):
    """Base of messages that carry pinhole intrinsics of an image of ``width_px`` x ``height_px``."""

    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(self.width_px, self.height_px, self.fx, self.fy, self.cx, self.cy)

    @staticmethod
    def intrinsics_fields(intrinsics: CameraIntrinsics) -> dict[str, Any]:
        """Keyword arguments for the intrinsics fields: ``RenderRequest(**intrinsics_fields(K), ...)``."""
        return {
            "width_px": intrinsics.width_px,
            "height_px": intrinsics.height_px,
            "fx": intrinsics.fx,
            "fy": intrinsics.fy,
            "cx": intrinsics.cx,
            "cy": intrinsics.cy,
        }

    def _check_image(self, name: str, arr: np.ndarray) -> None:
        if arr.shape[:2] != (self.height_px, self.width_px):
            raise ValueError(
                f"{name} is {arr.shape[1]}x{arr.shape[0]} but the intrinsics are for {self.width_px}x{self.height_px}"
            )
