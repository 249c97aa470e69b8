"""The frames the shard benches integrate (``bench_shards.py``, ``bench_shard_seams.py``): each frame of
a synthetic scene as one volume prepares it for Open3D's ``integrate``, with the blocks it touches."""

from __future__ import annotations


def frame_inputs(width: int, height: int, frames: int, scene: str = "room"):  # noqa: ANN202
    """Per frame of the synthetic room (or ``scene`` "building": the building's walk), what Open3D's
    ``integrate`` takes, as one volume prepares it: ``(depth image, color image, depth scale, K,
    extrinsic, touched block coords int64 (N, 3))``."""
    import numpy as np
    import open3d.core as o3c

    from openfusion.mapping import SemanticVolume, VolumeParams, integration
    from openfusion.poses import invert_pose
    from openfusion.sources import open_source

    vol = SemanticVolume(VolumeParams())
    p, vbg = vol.params, vol._storage.vbg
    world = "building," if scene == "building" else "seed=1,"
    for f in open_source(f"synthetic:{world}width={width},height={height},frames={frames}"):
        depth, color, scale = integration.frame_images(vol._storage, f)
        K = o3c.Tensor(f.intrinsics.K, o3c.float64)
        extrinsic = o3c.Tensor(invert_pose(np.asarray(f.T_world_cam, np.float64)))
        coords = vbg.compute_unique_block_coordinates(depth, K, extrinsic, scale, p.depth_max_m, p.trunc_voxels)
        yield depth, color, scale, K, extrinsic, coords.cpu().numpy().astype(np.int64)
