"""Small maps of the synthetic scene for viz tests, benchmarks and documentation pictures.

:func:`build_synthetic_map` maps one lap of the built-in synthetic room in this process (no bus)
with the ground-truth region encoder and saves it; the defaults make a tiny map in a few seconds
(160x120 frames, 16 frames, 4 cm voxels). ``text_encoder="hash"`` avoids loading MiniLM (the
query "chair" still finds the region labelled "chair", since ground-truth regions embed their
category name with the same encoder).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from openfusion.mapping import SemanticVolume, VolumeParams, save_map

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SyntheticMapSpec:
    """How a synthetic test map is made."""

    seed: int = 1
    frames: int = 16
    width_px: int = 160
    height_px: int = 120
    voxel_size_m: float = 0.04
    text_encoder: str = "hash"

    @property
    def source_spec(self) -> str:
        # lap = frames: the camera goes once round the room, so the map covers all of it
        return (
            f"synthetic:seed={self.seed},frames={self.frames},width={self.width_px},"
            f"height={self.height_px},lap={self.frames}"
        )


def build_synthetic_map(out_dir: str | os.PathLike[str], spec: SyntheticMapSpec | None = None) -> Path:
    """Map the synthetic room as ``spec`` says and save it into ``out_dir``; returns the map file."""
    from openfusion.encoders import make_region_encoder
    from openfusion.mapping.pipeline import map_scene
    from openfusion.sources import open_source

    spec = spec or SyntheticMapSpec()
    encoder = make_region_encoder("gt", text_encoder=spec.text_encoder)
    result = map_scene(
        open_source(spec.source_spec),
        region_encoder=encoder,
        volume_params=VolumeParams(voxel_size_m=spec.voxel_size_m),
    )
    meta = {"source": spec.source_spec, "encoder": "gt", "text_encoder": spec.text_encoder}
    path = save_map(out_dir, result.volume, result.dictionary, meta=meta)
    logger.info("synthetic test map %s: %d regions", path, len(result.dictionary))
    return path


def volume_with_every_tile(frames: Iterable[Any]) -> tuple[SemanticVolume, dict[Any, tuple[np.ndarray, dict[str, np.ndarray]]]]:
    """``frames`` integrated into a new volume (default parameters) and a copy of every tile of it,
    ``{tile: (block coords, attribute arrays)}`` as a full checkpoint writes them (for the benches
    of the tile codec and store)."""
    volume = SemanticVolume(VolumeParams())
    for frame in frames:
        volume.integrate(frame)
    tiles = {}
    for part in volume.checkpoint_plan(every_tile=True):
        tiles.update(volume.pager.copy_tiles(part, every_tile=True)[0])
    return volume, tiles


def plant_small_region(volume, dictionary, *, like_key: int, label: str, voxels: int = 16):  # noqa: ANN001, ANN201
    """A copy of the map with a new region of a few surface points: a dictionary entry with region
    ``like_key``'s embedding (so it ties with it in every query) that takes over a compact patch
    of ``like_key``'s surface voxels: the one nearest the zero crossing and the ``voxels - 1``
    nearest it. Returns (volume, dictionary, new key). The stray fragments a query must not return
    look like this: a patch (a single stray voxel is voted away by the read-out, so it never
    reaches an answer; :func:`openfusion.mapping.readout.vote_labels`)."""
    from openfusion.mapping import RegionDictionary, SemanticVolume
    from openfusion.mapping.voxel_arrays import voxels_of_labelled

    dictionary = RegionDictionary.from_snapshot(dictionary.snapshot())
    key = dictionary.add(dictionary.embedding(like_key), label=label)
    arrays = volume.to_arrays()
    surface = (arrays["key"] == like_key) & (arrays["weight"] >= volume.params.min_weight) & (np.abs(arrays["tsdf"]) < 0.5)
    candidates = np.flatnonzero(surface.reshape(-1))
    if len(candidates) < voxels:
        raise ValueError(f"region {like_key} has {len(candidates)} surface voxels, fewer than {voxels}")
    # Voxel coordinates of the candidates, in the same (flat) order.
    position, _ = voxels_of_labelled(arrays["block_coords"], np.where(surface, 0, -1), volume.params.block_resolution)
    seed = int(np.argmin(np.abs(arrays["tsdf"].reshape(-1)[candidates])))
    d2 = ((position - position[seed]) ** 2).sum(axis=1)
    patch = candidates[np.argsort(d2, kind="stable")[:voxels]]
    arrays["key"].reshape(-1)[patch] = key
    arrays["conf"].reshape(-1)[patch] = 1.0
    return SemanticVolume.from_arrays(volume.params, arrays), dictionary, key


def strip_region_summaries(map_path: str | os.PathLike[str], out_path: str | os.PathLike[str] | None = None) -> Path:
    """Rewrite a saved map as maps were saved before region summaries were stored: the same
    archive without the ``summary_*`` members and their header entries (in place, or to
    ``out_path``: a file, or a folder that gets ``map.ofz.npz``). Returns the file written."""
    import io
    import json
    import shutil
    import zipfile

    from openfusion.mapping import load_map
    from openfusion.mapping.mapfile import MAP_FILE_NAME, resolve_map_path

    source = resolve_map_path(map_path)
    if source.is_dir():  # a tile store (format 2): written as an old, summary-less version-1 file
        loaded = load_map(source.parent)
        dest = Path(out_path) if out_path is not None else source.parent
        dest = dest if dest.suffix == ".npz" else dest / MAP_FILE_NAME
        written = save_map(dest, loaded.volume, loaded.dictionary, loaded.meta, summary=False, keep_previous=False)
        loaded.volume.close()
        if out_path is None:
            shutil.rmtree(source)
        return written
    target = resolve_map_path(out_path) if out_path is not None else source
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.strip.tmp")
    with zipfile.ZipFile(source) as src, zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as dst:
        for info in src.infolist():
            if info.filename.startswith("summary_"):
                continue
            if info.filename == "meta_json.npy":
                header = json.loads(str(np.load(io.BytesIO(src.read(info)), allow_pickle=False)[()]))
                header["arrays"] = {k: v for k, v in header["arrays"].items() if not k.startswith("summary_")}
                buf = io.BytesIO()
                np.save(buf, np.array(json.dumps(header)), allow_pickle=False)
                dst.writestr(info.filename, buf.getvalue())
                continue
            with src.open(info) as fin, dst.open(info.filename, "w", force_zip64=True) as fout:
                while chunk := fin.read(1 << 22):
                    fout.write(chunk)
    os.replace(tmp, target)
    return target


def sample_instance_points(world, category: str, *, spacing_m: float = 0.005, seed: int = 0) -> np.ndarray:  # noqa: ANN001
    """(N, 3) points sampled uniformly (about one per ``spacing_m``^2) on every instance of
    ``category`` in a :class:`~openfusion.sources.synthetic.SyntheticWorld` (hidden faces included)."""
    rng = np.random.default_rng(seed)
    out = []
    for obj in world.objects:
        if obj.category != category:
            continue
        for part in obj.parts:
            v = np.asarray(part.vertices, np.float64)
            tri = v[np.asarray(part.triangles)]
            area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            n = rng.poisson(area / spacing_m**2)
            idx = np.repeat(np.arange(len(tri)), n)
            if len(idx) == 0:
                continue
            r1, r2 = rng.random(len(idx)), rng.random(len(idx))
            s = np.sqrt(r1)
            a, b, c = tri[idx, 0], tri[idx, 1], tri[idx, 2]
            out.append((1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c)
    if not out:
        raise ValueError(f"the world has no instance of category {category!r}")
    return np.concatenate(out).astype(np.float64)


def project_points(points: np.ndarray, T_world_cam: np.ndarray, intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # noqa: ANN001
    """(u, v) integer pixel of each world point (pixel centres at integer coordinates), its z depth,
    and a mask of points in front of the camera and inside the image."""
    T_cam_world = np.linalg.inv(np.asarray(T_world_cam, np.float64))
    pc = np.asarray(points, np.float64) @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.round(intrinsics.fx * pc[:, 0] / z + intrinsics.cx)
        v = np.round(intrinsics.fy * pc[:, 1] / z + intrinsics.cy)
    ok = (z > 1e-6) & (u >= 0) & (u < intrinsics.width_px) & (v >= 0) & (v < intrinsics.height_px)
    u = np.where(ok, u, 0).astype(np.int64)
    v = np.where(ok, v, 0).astype(np.int64)
    return np.stack([u, v], axis=1), z, ok


def cached_synthetic_map(root_dir: str | os.PathLike[str], spec: SyntheticMapSpec | None = None) -> Path:
    """The map folder for ``spec`` under ``root_dir``, built on first use (tests share it per session)."""
    spec = spec or SyntheticMapSpec()
    name = (
        f"synthetic-s{spec.seed}-f{spec.frames}-{spec.width_px}x{spec.height_px}"
        f"-v{round(spec.voxel_size_m * 1000)}mm-{spec.text_encoder}"
    )
    folder = Path(root_dir) / name
    from openfusion.mapping.mapfile import resolve_map_path

    if not resolve_map_path(folder).exists():
        build_synthetic_map(folder, spec)
    return folder
