"""Image and small-text-file decoding shared by the dataset readers (Pillow only, no OpenCV).

Every function raises ``SkipFrame`` with a reason (``missing_<what>``, ``unreadable_<what>``,
``<what>_dtype``, ``<what>_size``) so readers count bad files instead of crashing.
16-bit PNG depth decodes through Pillow mode ``I;16`` (little-endian in memory) to uint16;
``I;16B`` and 32-bit ``I`` images with values in 0..65535 are accepted and converted.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.poses import InvalidPoseError
from openfusion.poses import check_pose as _check_pose
from openfusion.sources.base import SkipFrame

logger = logging.getLogger(__name__)

_PIL_ERRORS = (OSError, UnidentifiedImageError, ValueError, SyntaxError, Image.DecompressionBombError)


def _open(path: Path, what: str) -> Image.Image:
    if not path.is_file():
        raise SkipFrame(f"missing_{what}", f"{what} file {path} does not exist")
    try:
        img = Image.open(path)
    except _PIL_ERRORS as exc:
        raise SkipFrame(f"unreadable_{what}", f"cannot open {what} image {path}: {exc}") from exc
    return img


def read_color(path: Path, *, size: tuple[int, int] | None = None) -> np.ndarray:
    """HxWx3 uint8 RGB; resized (bilinear, antialiased) to ``size=(width, height)`` if given.

    JPEGs larger than ``size`` are decoded at a reduced DCT scale first (Pillow ``draft``),
    which is several times faster than decoding full resolution and then shrinking. When what
    is left is a shrink by less than 3 % (ScanNet: 1296x968 decodes at 648x484 for 640x480),
    it is done by nearest neighbour (each output pixel within half a pixel of its true source;
    bilinear would cost more than the decode itself).
    """
    with _open(path, "color") as img:
        try:
            if size is not None and img.format == "JPEG" and img.size != size:
                img.draft("RGB", size)
            rgb = img.convert("RGB")
            if size is not None and rgb.size != size:
                sx, sy = size[0] / rgb.size[0], size[1] / rgb.size[1]
                tiny = 0.97 <= sx <= 1.0 and 0.97 <= sy <= 1.0
                rgb = rgb.resize(size, Image.Resampling.NEAREST if tiny else Image.Resampling.BILINEAR)
            return np.asarray(rgb)
        except _PIL_ERRORS as exc:
            raise SkipFrame("unreadable_color", f"cannot decode color image {path}: {exc}") from exc


def _gray_to_array(img: Image.Image, path: Path, what: str) -> np.ndarray:
    try:
        img.load()
    except _PIL_ERRORS as exc:
        raise SkipFrame(f"unreadable_{what}", f"cannot decode {what} image {path}: {exc}") from exc
    if img.mode in ("I;16", "I;16L", "I;16B", "I;16N"):
        return np.asarray(img).astype(np.uint16, copy=False)
    if img.mode == "I":
        arr = np.asarray(img)
        if arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise SkipFrame(f"{what}_dtype", f"{what} image {path} has 32-bit values outside 0..65535")
        return arr.astype(np.uint16)
    raise SkipFrame(f"{what}_dtype", f"{what} image {path} has mode {img.mode!r}, expected a 16-bit single-channel PNG")


def read_depth_u16(path: Path, *, size: tuple[int, int] | None = None) -> np.ndarray:
    """HxW uint16 raw depth from a 16-bit single-channel image; checks ``size=(width, height)``."""
    with _open(path, "depth") as img:
        if size is not None and img.size != size:
            raise SkipFrame("depth_size", f"depth image {path} is {img.size[0]}x{img.size[1]}, expected {size[0]}x{size[1]}")
        return _gray_to_array(img, path, "depth")


def read_rgbd_frame(
    *,
    frame_id: int,
    stamp_ns: int,
    color_path: Path,
    depth_path: Path,
    intrinsics: CameraIntrinsics,
    depth_scale: float,
    T_world_cam: np.ndarray,
    source: str,
) -> Frame:
    """A color image and a 16-bit depth PNG, both checked against the intrinsics' size, as a Frame
    (unreadable or wrongly sized files raise ``SkipFrame`` with the reason)."""
    size = (intrinsics.width_px, intrinsics.height_px)
    depth = read_depth_u16(depth_path, size=size)
    color = read_color(color_path, size=size)
    return Frame(
        frame_id=frame_id,
        stamp_ns=stamp_ns,
        color=color,
        depth=depth,
        depth_scale=depth_scale,
        intrinsics=intrinsics,
        T_world_cam=T_world_cam,
        source=source,
    )


def read_label_image(path: Path, *, what: str, size: tuple[int, int] | None = None) -> np.ndarray:
    """HxW int32 label/instance ids from an 8- or 16-bit single-channel image.

    Resized with nearest neighbour to ``size=(width, height)`` (labels must never be blended).
    """
    with _open(path, what) as img:
        try:
            img.load()
        except _PIL_ERRORS as exc:
            raise SkipFrame(f"unreadable_{what}", f"cannot decode {what} image {path}: {exc}") from exc
        if img.mode not in ("L", "P") and not img.mode.startswith("I"):
            raise SkipFrame(f"{what}_dtype", f"{what} image {path} has mode {img.mode!r}, expected 8/16-bit single channel")
        if size is not None and img.size != size:
            # Pillow's nearest uses the same pixel-centre mapping as resize_nearest, in C
            img = img.resize(size, Image.Resampling.NEAREST)
        if img.mode in ("L", "P"):
            return np.asarray(img).astype(np.int32)
        return _gray_to_array(img, path, what).astype(np.int32)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the image header, without decoding pixels."""
    with Image.open(path) as img:
        return img.size


def read_matrix(path: Path, *, what: str = "pose", shape: tuple[int, int] = (4, 4)) -> np.ndarray:
    """A whitespace-separated float matrix file (ScanNet pose/intrinsic txt)."""
    if not path.is_file():
        raise SkipFrame(f"missing_{what}", f"{what} file {path} does not exist")
    try:
        values = np.array(path.read_text().split(), dtype=np.float64)
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise SkipFrame(f"unreadable_{what}", f"cannot parse {what} file {path}: {exc}") from exc
    if values.size != shape[0] * shape[1]:
        raise SkipFrame(f"unreadable_{what}", f"{what} file {path} has {values.size} numbers, expected {shape[0] * shape[1]}")
    return values.reshape(shape)


def pose_or_skip(T_world_cam: np.ndarray, *, context: str) -> np.ndarray:
    """Return a float64 copy or raise ``SkipFrame('invalid_pose')`` for inf/NaN or non-rigid poses."""
    try:
        return _check_pose(T_world_cam, what="pose")
    except InvalidPoseError as exc:
        raise SkipFrame("invalid_pose", f"{context}: {exc}") from None


def numeric_key(path: Path) -> int | None:
    """The last run of digits in a file stem (``frame000012`` -> 12), or None."""
    digits = ""
    for ch in reversed(path.stem):
        if ch.isdigit():
            digits = ch + digits
        elif digits:
            break
    return int(digits) if digits else None
