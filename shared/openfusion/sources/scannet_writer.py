"""Write any frame source to disk in the ScanNet export layout (``ScanNetSource`` reads it back).

Written per frame ``i`` (the frame's ``frame_id``)::

    color/<i>.jpg|png      at the depth size (not ScanNet's 1296x968: the frames are already
                           registered at one resolution, so intrinsic_color == intrinsic_depth
                           and no resampling happens on the way back)
    depth/<i>.png          uint16 millimetres (float or other-scale depth is converted, rounded)
    pose/<i>.txt           4x4 camera-to-world, written with 17 significant digits (exact)
    instance-filt/<i>.png  8-bit when every id < 256, else 16-bit (only when frames carry instances)
    label-filt/<i>.png     16-bit label ids of each instance's category (the tsv ``id``)

plus ``intrinsic/intrinsic_{color,depth}.txt``, ``extrinsic_{color,depth}.txt`` (identity),
``<scene>.txt`` metadata (with the source's own ``metadata`` as ``openfusion.<key> = value`` lines,
e.g. a synthetic building's ``openfusion.floor_area_m2``; ``ScanNetSource.metadata`` reads them back), ``scannetv2-labels.combined.tsv`` (ScanNet's 16 columns; ``id``,
``raw_category``, ``category``, ``count``, ``nyu40id``, ``nyu40class`` filled) and, for a
synthetic source, ``<scene>_vh_clean_2.labels.ply``: the ground-truth surface as labelled
points (vertex ``x y z red green blue alpha label instance``, ``label`` = NYU40 id as in
ScanNet, ``instance`` = the world's instance id).

Round trip: depth, pose, intrinsics and instances read back exactly; color exactly with
``color_format="png"``, and within JPEG loss with ``"jpg"`` (quality 100 by default: mean
absolute error well under 1 level, see tests/test_sources_scannet.py).

The scene is written into a temporary sibling folder and renamed into place at the end, so a
failure never leaves a half-written scene behind.

Command: ``python -m openfusion.sources.record_scannet SPEC OUT_DIR`` writes any source spec this way
(:mod:`openfusion.sources.record_scannet`).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.sources.base import FrameSource, SourceStats
from openfusion.sources.scannet import LABEL_TSV_COLUMNS, LABEL_TSV_NAME, META_PREFIX, SCANNET_DEPTH_SCALE

logger = logging.getLogger(__name__)

#: raw category -> (NYU40 id, NYU40 class), as ScanNet's label table maps these names.
NYU40_OF_CATEGORY: dict[str, tuple[int, str]] = {
    "wall": (1, "wall"),
    "floor": (2, "floor"),
    "cabinet": (3, "cabinet"),
    "bed": (4, "bed"),
    "chair": (5, "chair"),
    "office chair": (5, "chair"),
    "sofa": (6, "sofa"),
    "table": (7, "table"),
    "door": (8, "door"),
    "window": (9, "window"),
    "bookshelf": (10, "bookshelf"),
    "picture": (11, "picture"),
    "desk": (14, "desk"),
    "pillow": (18, "pillow"),
    "ceiling": (22, "ceiling"),
    "lamp": (35, "lamp"),
    "trash can": (39, "otherfurniture"),
    "monitor": (40, "otherprop"),
    "plant": (40, "otherprop"),
}
#: raw category -> ScanNet's cleaned ``category`` column where it differs.
_CLEAN_CATEGORY = {"office chair": "chair"}


@dataclass(frozen=True)
class WrittenScene:
    """What ``write_scannet_layout`` wrote."""

    path: Path
    num_frames: int
    label_ids: dict[str, int]  # raw category -> label id (tsv ``id``)
    source_stats: SourceStats
    ground_truth_points: int


def _fmt_matrix(M: np.ndarray) -> str:
    return "\n".join(" ".join(f"{v:.17g}" for v in row) for row in np.asarray(M, dtype=np.float64)) + "\n"


def _K4(intr: CameraIntrinsics) -> np.ndarray:
    K = np.eye(4)
    K[:3, :3] = intr.K
    return K


def _depth_mm(frame: Frame) -> np.ndarray:
    if frame.depth.dtype == np.uint16 and frame.depth_scale == SCANNET_DEPTH_SCALE:
        return frame.depth
    mm = np.round(frame.depth_m().astype(np.float64) * SCANNET_DEPTH_SCALE)
    return np.clip(mm, 0, 65535).astype(np.uint16)


def write_scannet_layout(
    source: FrameSource,
    out_dir: str | Path,
    *,
    color_format: str = "jpg",
    jpeg_quality: int = 100,
    ground_truth_spacing_m: float | None = 0.02,
    overwrite: bool = False,
) -> WrittenScene:
    """Write every frame of ``source`` into ``out_dir`` in the ScanNet export layout.

    ``out_dir``'s name is the scene name (ScanNet style, e.g. ``scene0000_00``). Raises
    FileExistsError when ``out_dir`` exists and ``overwrite`` is False, ValueError when frames
    disagree on intrinsics (ScanNet has one intrinsic file per scene).
    """
    if color_format not in ("jpg", "png"):
        raise ValueError(f"color_format must be 'jpg' or 'png', got {color_format!r}")
    if not 1 <= jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise FileExistsError(f"{out_dir} exists; pass overwrite=True to replace it")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))
    try:
        written = _write(source, tmp, out_dir.name, color_format, jpeg_quality, ground_truth_spacing_m)
        if out_dir.exists():
            trash = out_dir.with_name(f".{out_dir.name}.old")
            if trash.exists():
                shutil.rmtree(trash)
            out_dir.rename(trash)
            tmp.rename(out_dir)
            shutil.rmtree(trash)
        else:
            tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    logger.info("wrote %d frames of %s to %s (ScanNet layout)", written[0], source.name, out_dir)
    return WrittenScene(out_dir, written[0], written[1], source.stats, written[2])


def _write(
    source: FrameSource, root: Path, scene: str, color_format: str, jpeg_quality: int, gt_spacing: float | None
) -> tuple[int, dict[str, int], int]:
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir()
    label_ids: dict[str, int] = {}
    label_pixels: dict[str, int] = {}
    intrinsics: CameraIntrinsics | None = None
    n = 0
    has_instances = False
    for frame in source:
        frame.validate()
        if intrinsics is None:
            intrinsics = frame.intrinsics
        elif frame.intrinsics != intrinsics:
            raise ValueError(
                f"frame {frame.frame_id} has intrinsics {frame.intrinsics}, earlier frames {intrinsics}: "
                "the ScanNet layout holds one camera per scene"
            )
        i = frame.frame_id
        color = Image.fromarray(frame.color)
        if color_format == "jpg":
            color.save(root / "color" / f"{i}.jpg", quality=jpeg_quality, subsampling=0)
        else:
            color.save(root / "color" / f"{i}.png", compress_level=1)
        Image.fromarray(_depth_mm(frame)).save(root / "depth" / f"{i}.png", compress_level=1)
        (root / "pose" / f"{i}.txt").write_text(_fmt_matrix(frame.T_world_cam))
        if frame.instance is not None:
            if not has_instances:
                (root / "instance-filt").mkdir()
                (root / "label-filt").mkdir()
                has_instances = True
            inst = frame.instance
            if inst.min() < 0 or inst.max() > 65535:
                raise ValueError(f"frame {i}: instance ids must be in 0..65535 for the ScanNet layout")
            lut = np.zeros(int(inst.max()) + 1, dtype=np.uint16)
            for inst_id, cat in frame.instance_categories.items():
                if 0 < inst_id < lut.size:
                    lut[inst_id] = _label_id(cat, label_ids)
            label = lut[inst]
            per_label = np.bincount(label.ravel())
            for cat, lid in label_ids.items():
                if lid < per_label.size:
                    label_pixels[cat] = label_pixels.get(cat, 0) + int(per_label[lid])
            inst_img = inst.astype(np.uint8) if inst.max() < 256 else inst.astype(np.uint16)
            Image.fromarray(inst_img).save(root / "instance-filt" / f"{i}.png", compress_level=1)
            Image.fromarray(label).save(root / "label-filt" / f"{i}.png", compress_level=1)
        n += 1
    if intrinsics is None:
        raise ValueError(f"source {source.name!r} yielded no frames; nothing to write")
    K = _fmt_matrix(_K4(intrinsics))
    for name in ("intrinsic_color.txt", "intrinsic_depth.txt"):
        (root / "intrinsic" / name).write_text(K)
    for name in ("extrinsic_color.txt", "extrinsic_depth.txt"):
        (root / "intrinsic" / name).write_text(_fmt_matrix(np.eye(4)))
    meta = {
        "axisAlignment": " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1"]),
        "colorHeight": intrinsics.height_px,
        "colorWidth": intrinsics.width_px,
        "depthHeight": intrinsics.height_px,
        "depthWidth": intrinsics.width_px,
        "fx_color": f"{intrinsics.fx:.17g}",
        "fx_depth": f"{intrinsics.fx:.17g}",
        "fy_color": f"{intrinsics.fy:.17g}",
        "fy_depth": f"{intrinsics.fy:.17g}",
        "mx_color": f"{intrinsics.cx:.17g}",
        "mx_depth": f"{intrinsics.cx:.17g}",
        "my_color": f"{intrinsics.cy:.17g}",
        "my_depth": f"{intrinsics.cy:.17g}",
        "numColorFrames": n,
        "numDepthFrames": n,
        "numIMUmeasurements": 0,
        "sceneType": "Synthetic" if hasattr(source, "world") else "Unknown",
    }
    for key, value in (getattr(source, "metadata", None) or {}).items():  # e.g. a building's floor area
        text = " ".join(str(v) for v in value) if isinstance(value, (list, tuple)) else str(value)
        meta[f"{META_PREFIX}{key}"] = text
    (root / f"{scene}.txt").write_text("".join(f"{k} = {v}\n" for k, v in meta.items()))
    world = getattr(source, "world", None)
    if world is not None:
        for cat in world.categories.values():
            _label_id(cat, label_ids)
    _write_label_tsv(root / LABEL_TSV_NAME, label_ids, label_pixels)
    gt_points = 0
    if world is not None and gt_spacing is not None:
        gt_points = _write_ground_truth(root / f"{scene}_vh_clean_2.labels.ply", world, gt_spacing)
    return n, label_ids, gt_points


def _label_id(category: str, label_ids: dict[str, int]) -> int:
    """Stable label id: 1.. in ``NYU40_OF_CATEGORY`` order for known categories, 1000+ for others
    (in order of appearance)."""
    lid = label_ids.get(category)
    if lid is None:
        if category in NYU40_OF_CATEGORY:
            lid = list(NYU40_OF_CATEGORY).index(category) + 1
        else:
            lid = 1000 + sum(1 for c in label_ids if c not in NYU40_OF_CATEGORY)
        label_ids[category] = lid
    return lid


def _write_label_tsv(path: Path, label_ids: dict[str, int], counts: dict[str, int]) -> None:
    rows = ["\t".join(LABEL_TSV_COLUMNS)]
    for cat, lid in sorted(label_ids.items(), key=lambda kv: kv[1]):
        nyu_id, nyu_class = NYU40_OF_CATEGORY.get(cat, (40, "otherprop"))
        values = {
            "id": str(lid),
            "raw_category": cat,
            "category": _CLEAN_CATEGORY.get(cat, cat),
            "count": str(counts.get(cat, 0)),
            "nyu40id": str(nyu_id),
            "nyu40class": nyu_class,
        }
        rows.append("\t".join(values.get(col, "") for col in LABEL_TSV_COLUMNS))
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")


def _write_ground_truth(path: Path, world, spacing_m: float) -> int:  # noqa: ANN001 - a SyntheticWorld
    from openfusion.io.ply import write_ply_vertices

    gt = world.ground_truth_surface(spacing_m)
    nyu = np.array([NYU40_OF_CATEGORY.get(gt.categories[int(i)], (40, ""))[0] for i in gt.instance_ids], dtype=np.uint16)
    palette = np.array(
        [(37 * k % 255, 91 * k % 255, 157 * k % 255) for k in range(int(gt.instance_ids.max()) + 1)], dtype=np.uint8
    )
    rgb = palette[gt.instance_ids]
    write_ply_vertices(
        path,
        {
            "x": gt.points[:, 0].astype(np.float32),
            "y": gt.points[:, 1].astype(np.float32),
            "z": gt.points[:, 2].astype(np.float32),
            "red": rgb[:, 0],
            "green": rgb[:, 1],
            "blue": rgb[:, 2],
            "alpha": np.full(len(rgb), 255, dtype=np.uint8),
            "label": nyu,
            "instance": gt.instance_ids.astype(np.int32),
        },
    )
    return len(gt.points)

