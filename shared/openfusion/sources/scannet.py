"""ScanNet export reader (the SensReader output layout).

Layout of a scene folder::

    color/<i>.jpg            1296 x 968 RGB (any size and .png accepted)
    depth/<i>.png            640 x 480 uint16 millimetres
    pose/<i>.txt             4x4 camera-to-world, OpenCV camera axes
    intrinsic/intrinsic_depth.txt, intrinsic_color.txt   4x4 (K in the top-left 3x3)
    <scene>.txt              optional metadata (depthWidth/depthHeight are used when present)
    label-filt/<i>.png       optional, ScanNet label ids (the tsv ``id``), color resolution
    instance-filt/<i>.png    optional, instance ids (0 = none), color resolution
    scannetv2-labels.combined.tsv   here or one/two folders up: id -> raw_category

What is converted: nothing in the pose (ScanNet poses are already camera-to-world with OpenCV
axes, metres); frames whose pose has inf/NaN (ScanNet marks tracking failures so) are skipped
as ``invalid_pose``. Color, labels and instances are resized to the depth size (bilinear for
color, nearest for labels), and the frame intrinsics are the *depth* intrinsics, so color and
depth are treated as registered (as ScanNet-based mapping code does; the ~1 cm colour/depth
baseline of the sensor is ignored). Depth stays uint16 with ``depth_scale = 1000``.
ScanNet has no timestamps: ``stamp_ns = index * 1e9 / 30``.

Instance categories: each instance's label is the majority ``label-filt`` value over its pixels
in that frame (unannotated 0 ignored when anything else is present), named by the tsv's
``raw_category`` column (``category`` when raw is empty).
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.sources.base import NOMINAL_FPS, IndexedFrameSource, SkipFrame
from openfusion.sources.files import (
    image_size,
    numeric_key,
    pose_or_skip,
    read_color,
    read_depth_u16,
    read_label_image,
    read_matrix,
)

logger = logging.getLogger(__name__)

SCANNET_DEPTH_SCALE = 1000.0
LABEL_TSV_NAME = "scannetv2-labels.combined.tsv"
LABEL_TSV_COLUMNS: tuple[str, ...] = (
    "id", "raw_category", "category", "count", "nyu40id", "eigen13id", "nyu40class", "eigen13class",
    "ModelNet40", "ModelNet10", "ShapeNetCore55", "synsetoffset", "wnsynsetid", "wnsynsetkey",
    "mpcat40index", "mpcat40",
)  # fmt: skip
_COLOR_EXTS = (".jpg", ".jpeg", ".png")


def read_label_tsv(path: Path) -> dict[int, str]:
    """ScanNet label id -> raw category name from ``scannetv2-labels.combined.tsv``.

    Raises ValueError naming the file when the ``id``/``raw_category`` columns are missing.
    """
    path = Path(path)
    out: dict[int, str] = {}
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh, delimiter="\t")
            fields = set(reader.fieldnames or ())
            if not {"id", "raw_category"} <= fields:
                raise ValueError(f"{path}: not a ScanNet label table (needs columns id and raw_category, has {sorted(fields)})")
            for line_no, row in enumerate(reader, start=2):
                try:
                    label_id = int(row["id"])
                except (TypeError, ValueError) as exc:
                    raise ValueError(f"{path}:{line_no}: id {row.get('id')!r} is not an integer") from exc
                name = (row.get("raw_category") or "").strip() or (row.get("category") or "").strip()
                if name:
                    out[label_id] = name
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"cannot read ScanNet label table {path}: {exc}") from exc
    return out


def find_label_tsv(scene_dir: Path) -> Path | None:
    """The label table in the scene folder or one or two folders up (ScanNet's release layout)."""
    for d in (scene_dir, scene_dir.parent, scene_dir.parent.parent):
        p = d / LABEL_TSV_NAME
        if p.is_file():
            return p
    return None


def majority_labels(instance: np.ndarray, label: np.ndarray) -> dict[int, int]:
    """Instance id -> most frequent label over its pixels (label 0 only if nothing else)."""
    inst = instance.ravel()
    lab = label.ravel()
    if inst.size == 0 or inst.max() <= 0:
        return {}
    if inst.min() < 0 or lab.min() < 0:
        raise ValueError("instance and label ids must be >= 0")
    # dense index per instance id present (no sort: bincount + look-up table)
    present = np.flatnonzero(np.bincount(inst))
    present = present[present > 0]
    dense = np.full(int(inst.max()) + 1, -1, dtype=np.int64)
    dense[present] = np.arange(present.size)
    idx = dense[inst]
    mask = idx >= 0
    n_labels = int(lab.max()) + 1
    counts = np.bincount(idx[mask] * n_labels + lab[mask], minlength=present.size * n_labels)
    counts = counts.reshape(present.size, n_labels)
    if n_labels > 1:
        annotated = counts[:, 1:]
        best = np.where(annotated.max(axis=1) > 0, annotated.argmax(axis=1) + 1, 0)
    else:
        best = np.zeros(present.size, dtype=np.int64)
    return {int(i): int(b) for i, b in zip(present, best, strict=True)}


#: Prefix of the lines the ScanNet writer adds to ``<scene>.txt`` (``openfusion.floor_area_m2 = 412.3``).
META_PREFIX = "openfusion."


def _stems(folder: Path, exts: tuple[str, ...]) -> dict[int, Path]:
    out: dict[int, Path] = {}
    if not folder.is_dir():
        return out
    for p in folder.iterdir():
        if p.suffix.lower() in exts:
            key = numeric_key(p)
            if key is not None:
                out.setdefault(key, p)
    return out


class ScanNetSource(IndexedFrameSource):
    """Frames of one exported ScanNet scene folder (see module docstring for the layout)."""

    def __init__(
        self,
        scene_dir: str | Path,
        *,
        labels_tsv: str | Path | None = None,
        load_instances: bool = True,
        fps: float = NOMINAL_FPS,
        stride: int = 1,
        max_frames: int | None = None,
    ) -> None:
        scene_dir = Path(scene_dir)
        if not scene_dir.is_dir():
            raise FileNotFoundError(f"ScanNet scene folder {scene_dir} does not exist")
        missing = [d for d in ("color", "depth", "pose") if not (scene_dir / d).is_dir()]
        if missing:
            raise FileNotFoundError(
                f"{scene_dir} is not a ScanNet export: missing folder(s) {missing} "
                "(expected color/, depth/, pose/, intrinsic/ as written by ScanNet's SensReader)"
            )
        super().__init__(f"scannet:{scene_dir.name}", stride=stride, max_frames=max_frames)
        self.scene_dir = scene_dir
        self.fps = float(fps)
        K_path = scene_dir / "intrinsic" / "intrinsic_depth.txt"
        try:
            K = read_matrix(K_path, what="intrinsics")
        except SkipFrame as exc:
            raise FileNotFoundError(f"{scene_dir}: cannot read depth intrinsics: {exc.detail}") from None
        self._color = _stems(scene_dir / "color", _COLOR_EXTS)
        self._depth = _stems(scene_dir / "depth", (".png",))
        self._pose = _stems(scene_dir / "pose", (".txt",))
        self._indices = sorted(set(self._color) | set(self._depth) | set(self._pose))
        if not self._indices:
            raise FileNotFoundError(f"{scene_dir}: no frames found in color/, depth/, pose/")
        width, height = self._depth_size()
        self.intrinsics = CameraIntrinsics.from_matrix(K[:3, :3], width, height)
        self._instances = load_instances and (scene_dir / "instance-filt").is_dir()
        self._labels = load_instances and (scene_dir / "label-filt").is_dir()
        self.label_names: dict[int, str] = {}
        if self._instances and self._labels:
            tsv = Path(labels_tsv) if labels_tsv is not None else find_label_tsv(scene_dir)
            if tsv is None:
                logger.warning(
                    "%s: no %s found (scene folder or up to two folders up); instance categories will be "
                    "named 'label_<id>'",
                    scene_dir,
                    LABEL_TSV_NAME,
                )
            else:
                self.label_names = read_label_tsv(tsv)
        elif self._instances:
            logger.warning("%s: instance-filt/ without label-filt/: instance categories are unknown", scene_dir)

    def _meta(self) -> dict[str, str]:
        """``key = value`` lines of ``<scene>.txt`` (empty when there is none)."""
        meta = self.scene_dir / f"{self.scene_dir.name}.txt"
        values: dict[str, str] = {}
        if meta.is_file():
            for line in meta.read_text(errors="replace").splitlines():
                if "=" in line:
                    k, v = line.split("=", 1)
                    values[k.strip()] = v.strip()
        return values

    @property
    def metadata(self) -> dict[str, object]:
        """What the writer of the scene recorded about it (``openfusion.*`` lines of ``<scene>.txt``,
        e.g. a synthetic building's ``floor_area_m2``), numbers as floats; empty for a real scan."""
        out: dict[str, object] = {}
        for key, value in self._meta().items():
            if key.startswith(META_PREFIX):
                try:
                    out[key[len(META_PREFIX):]] = float(value)
                except ValueError:
                    out[key[len(META_PREFIX):]] = value
        return out

    def _depth_size(self) -> tuple[int, int]:
        meta = self.scene_dir / f"{self.scene_dir.name}.txt"
        if meta.is_file():
            values = self._meta()
            try:
                return int(values["depthWidth"]), int(values["depthHeight"])
            except (KeyError, ValueError):
                logger.info("%s has no usable depthWidth/depthHeight; using the first depth image", meta)
        for idx in sorted(self._depth):
            try:
                return image_size(self._depth[idx])
            except (OSError, ValueError, SyntaxError) as exc:
                logger.debug("cannot read header of %s: %s", self._depth[idx], exc)
        raise FileNotFoundError(f"{self.scene_dir}: no readable depth image to take the depth size from")

    def _num_items(self) -> int:
        return len(self._indices)

    def _load(self, index: int) -> Frame:
        idx = self._indices[index]
        d = self.scene_dir
        size = (self.intrinsics.width_px, self.intrinsics.height_px)
        ctx = f"{d.name} frame {idx}"
        pose_path = self._pose.get(idx, d / "pose" / f"{idx}.txt")
        T = pose_or_skip(read_matrix(pose_path, what="pose"), context=f"{ctx} ({pose_path})")
        depth = read_depth_u16(self._depth.get(idx, d / "depth" / f"{idx}.png"), size=size)
        color = read_color(self._color.get(idx, d / "color" / f"{idx}.jpg"), size=size)
        instance = None
        categories: dict[int, str] = {}
        if self._instances:
            instance = read_label_image(d / "instance-filt" / f"{idx}.png", what="instance", size=size)
            if self._labels:
                label = read_label_image(d / "label-filt" / f"{idx}.png", what="label", size=size)
                for inst_id, label_id in majority_labels(instance, label).items():
                    if label_id != 0:  # 0 = unannotated: the instance keeps no category
                        categories[inst_id] = self.label_names.get(label_id, f"label_{label_id}")
        return Frame(
            frame_id=idx,
            stamp_ns=int(round(idx * 1e9 / self.fps)),
            color=color,
            depth=depth,
            depth_scale=SCANNET_DEPTH_SCALE,
            intrinsics=self.intrinsics,
            T_world_cam=T,
            instance=instance,
            instance_categories=categories,
            source=self.name,
        )
