"""Image preprocessing for crop embedders (CLIP-style), in numpy + PIL (no torchvision).

Two entry points:

- :func:`preprocess_image`: a whole image for an image query: resize the shorter side to
  ``size`` (bicubic), center-crop ``size`` x ``size``, scale to [0, 1], normalise per channel.
- :func:`region_crops`: one crop per region mask: the mask's bounding box (scaled from the mask
  grid to the image, grown by ``padding`` of its longer side), pixels outside the mask replaced
  by the mean color (they normalise to exactly 0) when ``mask_background``, padded to a square with the
  mean color, resized to ``size`` x ``size``, normalised.

Both return float32 arrays in NCHW layout ready for a model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image

from openfusion.encoders.base import EncoderError, check_rgb

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


@dataclass(frozen=True)
class CropSpec:
    """How crops are made for an embedder: square ``size`` px, per-channel ``mean``/``std`` on [0, 1]."""

    size: int = 224
    mean: tuple[float, float, float] = CLIP_MEAN
    std: tuple[float, float, float] = CLIP_STD
    padding: float = 0.1
    mask_background: bool = True

    def __post_init__(self) -> None:
        if self.size < 1:
            raise ValueError(f"crop size must be >= 1, got {self.size}")
        if len(self.mean) != 3 or len(self.std) != 3 or min(self.std) <= 0:
            raise ValueError(f"mean/std must be 3 values with std > 0, got {self.mean} / {self.std}")
        if self.padding < 0:
            raise ValueError(f"padding must be >= 0, got {self.padding}")

    @property
    def mean_rgb_u8(self) -> tuple[int, int, int]:
        return tuple(int(round(255 * m)) for m in self.mean)  # type: ignore[return-value]


def _normalise(images_u8: np.ndarray, spec: CropSpec) -> np.ndarray:
    """(n, S, S, 3) uint8 -> (n, 3, S, S) float32 normalised (one table lookup per channel)."""
    lut = (np.arange(256, dtype=np.float32)[None, :] / 255.0 - np.asarray(spec.mean, np.float32)[:, None]) / np.asarray(
        spec.std, np.float32
    )[:, None]
    n, s = images_u8.shape[0], images_u8.shape[1]
    out = np.empty((n, 3, s, s), np.float32)
    for c in range(3):
        out[:, c] = lut[c][images_u8[..., c]]
    return out


def preprocess_image(rgb: np.ndarray, spec: CropSpec) -> np.ndarray:
    """HxWx3 uint8 -> (1, 3, S, S) float32: shorter side to S, center crop, normalise."""
    check_rgb(rgb)
    h, w = rgb.shape[:2]
    s = spec.size
    scale = s / min(h, w)
    nh, nw = max(s, int(round(h * scale))), max(s, int(round(w * scale)))
    img = Image.fromarray(rgb).resize((nw, nh), Image.Resampling.BICUBIC)
    top, left = (nh - s) // 2, (nw - s) // 2
    img = img.crop((left, top, left + s, top + s))
    return _normalise(np.asarray(img)[None], spec)


def region_boxes(masks: np.ndarray, image_hw: tuple[int, int], padding: float) -> list[tuple[int, int, int, int] | None]:
    """Per mask (n, h, w): the (y0, x0, y1, x1) box in image pixels, or None for an empty mask."""
    n, h, w = masks.shape
    H, W = image_hw
    boxes: list[tuple[int, int, int, int] | None] = []
    for i in range(n):
        support = masks[i] >= 0.5
        if not support.any():
            support = masks[i] > 0
        rows = np.flatnonzero(support.any(axis=1))
        if rows.size == 0:
            boxes.append(None)
            continue
        cols = np.flatnonzero(support.any(axis=0))
        y0, y1 = rows[0] * H / h, (rows[-1] + 1) * H / h
        x0, x1 = cols[0] * W / w, (cols[-1] + 1) * W / w
        pad = padding * max(y1 - y0, x1 - x0)
        boxes.append(
            (
                max(0, int(np.floor(y0 - pad))),
                max(0, int(np.floor(x0 - pad))),
                min(H, int(np.ceil(y1 + pad))),
                min(W, int(np.ceil(x1 + pad))),
            )
        )
    return boxes


def region_crops(color: np.ndarray, masks: np.ndarray, spec: CropSpec) -> tuple[np.ndarray, np.ndarray]:
    """Crops of ``color`` (HxWx3 uint8) around each of ``masks`` (n, h, w).

    Returns ``(crops (m, 3, S, S) float32, kept (m,) int64)``: ``kept`` lists the mask indices that
    produced a crop (an all-zero mask produces none).
    """
    check_rgb(color)
    if masks.ndim != 3:
        raise EncoderError(f"masks must be (n, h, w), got shape {masks.shape}")
    H, W = color.shape[:2]
    n, h, w = masks.shape
    s = spec.size
    fill = spec.mean_rgb_u8
    out = np.empty((n, s, s, 3), np.uint8)
    kept: list[int] = []
    inside: list[np.ndarray] = []
    for i, box in enumerate(region_boxes(masks, (H, W), spec.padding)):
        if box is None:
            continue
        y0, x0, y1, x1 = box
        ph, pw = y1 - y0, x1 - x0
        side = max(ph, pw)
        oy, ox = (side - ph) // 2, (side - pw) // 2
        canvas = Image.new("RGB", (side, side), fill)
        canvas.paste(Image.fromarray(np.ascontiguousarray(color[y0:y1, x0:x1])), (ox, oy))
        crop = np.asarray(canvas.resize((s, s), Image.Resampling.BICUBIC, reducing_gap=2.0))
        if spec.mask_background:
            # mask the resized crop: each crop pixel -> image pixel -> mask cell (cheap at S x S)
            pos = (np.arange(s) + 0.5) * side / s
            py = np.floor(pos - oy).astype(np.int64)
            px = np.floor(pos - ox).astype(np.int64)
            in_y = (py >= 0) & (py < ph)
            in_x = (px >= 0) & (px < pw)
            cell_y = np.minimum(((y0 + np.clip(py, 0, ph - 1) + 0.5) * h / H).astype(np.int64), h - 1)
            cell_x = np.minimum(((x0 + np.clip(px, 0, pw - 1) + 0.5) * w / W).astype(np.int64), w - 1)
            inside.append((masks[i][cell_y[:, None], cell_x[None, :]] >= 0.5) & in_y[:, None] & in_x[None, :])
        out[len(kept)] = crop
        kept.append(i)
    normalised = _normalise(out[: len(kept)], spec)
    if spec.mask_background and kept:
        # outside the mask -> exactly the normalised mean color, 0
        normalised *= np.stack(inside)[:, None, :, :]
    return normalised, np.asarray(kept, np.int64)
