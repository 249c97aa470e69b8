"""Two robots against one, on the synthetic building: the walks, recorded as ScanNet-layout scenes
(replayable playbacks with instance images), and what a map made of them is worth against the
ground truth. Shared by tests/process/test_several_robots.py (slow) and bench/bench_robots.py."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from openfusion.frame import Frame
from openfusion.mapping import SemanticVolume, VolumeParams
from openfusion.mapping.robot_streams import yaw_transform
from openfusion.sources.base import IndexedFrameSource

#: Robot 1's odometry against the map's frame in the offset runs: 0.30 m and 5 degrees (issue 31).
T_MAP_ODOM = yaw_transform(0.25, -0.15, 0.05, 5.0)
T_ODOM_MAP = np.linalg.inv(T_MAP_ODOM)


def offset(frames: list[Frame], T_odom_map: np.ndarray = T_ODOM_MAP) -> list[Frame]:
    """The frames as a robot whose odometry frame is ``inv(T_odom_map)`` from the map's reports them."""
    return [dataclasses.replace(f, T_world_cam=T_odom_map @ f.T_world_cam) for f in frames]


def one_after_the_other(first: list[Frame], second: list[Frame]) -> list[Frame]:
    """One robot walking ``first`` then ``second`` (ids and stamps go on)."""
    shift_ns = first[-1].stamp_ns + 33_333_333
    return first + [dataclasses.replace(f, frame_id=f.frame_id + len(first), stamp_ns=f.stamp_ns + shift_ns)
                    for f in second]


class _Frames(IndexedFrameSource):
    """Frames in memory as an indexed source (what the ScanNet writer records)."""

    def __init__(self, frames: list[Frame]) -> None:
        super().__init__("frames")
        self.frames = frames

    def _num_items(self) -> int:
        return len(self.frames)

    def _load(self, index: int) -> Frame:
        return self.frames[index]


def record_scene(frames: list[Frame], path: Path) -> str:
    """The frames as a ScanNet-layout scene (a playback the bridge can replay from any frame, with
    instance images for the gt encoder); its source spec."""
    from openfusion.sources.scannet_writer import write_scannet_layout

    write_scannet_layout(_Frames(frames), path, color_format="png", ground_truth_spacing_m=None)
    return f"scannet:{path}"


def building_map_quality(map_dir: Path, building: object) -> dict:
    """``points``, ``f_mIoU``, ``mAcc``, ``regions_per_object`` of a saved map of ``building``."""
    from openfusion.encoders import make_text_encoder
    from openfusion.eval.ground_truth import synthetic_ground_truth
    from openfusion.eval.metrics import compute_metrics
    from openfusion.eval.point_labels import region_counts
    from openfusion.eval.protocol import (
        classify_embeddings,
        confusion_for_points,
        ground_truth_labels_for,
        labels_from_region_keys,
    )
    from openfusion.mapping import load_map

    loaded = load_map(map_dir)
    gt = synthetic_ground_truth(building, spacing_m=0.05)
    surface = loaded.volume.extract_points()
    points = np.asarray(surface.points, np.float64)
    class_emb = np.asarray(make_text_encoder("minilm").encode(list(gt.class_names)), np.float32)
    region_cls = classify_embeddings(np.asarray(loaded.dictionary.unit_embeddings(), np.float32), class_emb)
    pred = labels_from_region_keys(np.asarray(surface.keys, np.int64), np.asarray(loaded.dictionary.keys, np.int64),
                                   region_cls)
    gt_labels, _ = ground_truth_labels_for(points, gt)
    metrics = compute_metrics(confusion_for_points(pred, gt_labels, gt.class_names))
    counts = region_counts(np.asarray(surface.keys), gt, None)
    loaded.volume.close()
    return {"points": len(points), "f_mIoU": float(metrics.f_mIoU), "mAcc": float(metrics.mAcc),
            "regions_per_object": counts["regions_100_per_object"]}


def off_surface_share(frames: list[Frame], T_map_odom: np.ndarray, building: object, voxel_m: float) -> float:
    """Share of the surface of ``frames`` (fused alone through ``T_map_odom``, as geometry fuses
    them) farther than two voxels from the building's true surface: a wall fused twice shows here."""
    from openfusion.eval.geometry import mesh_distances

    volume = SemanticVolume(VolumeParams(voxel_size_m=voxel_m, initial_block_count=16384))
    for f in frames:
        volume.integrate(dataclasses.replace(f, T_world_cam=T_map_odom @ f.T_world_cam))
    points = volume.extract_points().points.astype(np.float64)
    mesh = building.to_mesh()  # type: ignore[attr-defined]
    distances = mesh_distances(points, np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    return float((distances > 2 * voxel_m).mean())
