"""Small synthetic inputs for encoder tests and benchmarks (no downloads, no datasets).

``make_box_frame`` draws axis-aligned boxes into color, depth and instance images so the expected
regions are known exactly. Tiny random-weight models live in :mod:`openfusion.testing.models`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame


@dataclass(frozen=True)
class PixelRect:
    """A box of pixels [y0, y1) x [x0, x1) with one instance id, category, color and depth."""

    instance_id: int
    category: str
    y0: int
    x0: int
    y1: int
    x1: int
    rgb: tuple[int, int, int] = (200, 60, 60)
    depth_m: float = 2.0


def make_box_frame(
    boxes: list[PixelRect],
    *,
    height_px: int = 480,
    width_px: int = 640,
    frame_id: int = 0,
    background_rgb: tuple[int, int, int] = (90, 90, 90),
    background_depth_m: float = 3.0,
    with_instances: bool = True,
    source: str = "test-boxes",
) -> Frame:
    """A valid :class:`Frame` whose instance image holds ``boxes`` (later boxes paint over earlier)."""
    color = np.empty((height_px, width_px, 3), np.uint8)
    color[:] = background_rgb
    depth = np.full((height_px, width_px), background_depth_m, np.float32)
    instance = np.zeros((height_px, width_px), np.int32)
    for b in boxes:
        color[b.y0 : b.y1, b.x0 : b.x1] = b.rgb
        depth[b.y0 : b.y1, b.x0 : b.x1] = b.depth_m
        instance[b.y0 : b.y1, b.x0 : b.x1] = b.instance_id
    f = 0.8 * width_px
    frame = Frame(
        frame_id=frame_id,
        stamp_ns=1_000_000 * frame_id,
        color=color,
        depth=depth,
        depth_scale=1.0,
        intrinsics=CameraIntrinsics(width_px, height_px, f, f, width_px / 2 - 0.5, height_px / 2 - 0.5),
        T_world_cam=np.eye(4),
        instance=instance if with_instances else None,
        instance_categories={b.instance_id: b.category for b in boxes} if with_instances else {},
        source=source,
    )
    frame.validate()
    return frame


def grid_boxes(
    *, height_px: int, width_px: int, rows: int, cols: int, categories: list[str], gap_px: int = 0, seed: int = 0
) -> list[PixelRect]:
    """rows x cols boxes tiling the image (optionally with gaps), cycling through ``categories``."""
    rng = np.random.default_rng(seed)
    boxes = []
    cell_h, cell_w = height_px // rows, width_px // cols
    k = 0
    for r in range(rows):
        for c in range(cols):
            rgb = tuple(int(v) for v in rng.integers(0, 256, 3))
            boxes.append(
                PixelRect(
                    instance_id=k + 1,
                    category=categories[k % len(categories)],
                    y0=r * cell_h + gap_px,
                    x0=c * cell_w + gap_px,
                    y1=(r + 1) * cell_h - gap_px,
                    x1=(c + 1) * cell_w - gap_px,
                    rgb=rgb,  # type: ignore[arg-type]
                    depth_m=float(1.0 + 0.5 * (k % 4)),
                )
            )
            k += 1
    return boxes
