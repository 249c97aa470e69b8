"""Read-outs of the semantic volume: surface points, meshes, labelled voxels, region summaries and
contacts (a part of :class:`~openfusion.mapping.volume.SemanticVolume`, split from ``volume.py``;
the state it reads, ``_storage``, ``_pager``, ``_readouts``, ``_shard``..., is the volume's).

Whole-map read-outs run as jobs of the read-out worker (:func:`.volume_locks.read_out`); region
summaries and contacts are kept per tile (:mod:`.tilereadouts`); a geometry shard keeps only what
its own tiles own (:func:`openfusion.mapping.shards.own_points`)."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from openfusion.mapping import readout, shards, tilereadouts
from openfusion.mapping.merging import RegionContacts
from openfusion.mapping.paging import TilePager
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.readout import SurfaceMesh, SurfacePoints
from openfusion.mapping.storage import VoxelStorage
from openfusion.mapping.summaries import RegionTable
from openfusion.mapping.tilereadouts import TileReadouts
from openfusion.mapping.volume_locks import read_out as _read_out
from openfusion.mapping.voxel_arrays import labelled_of, voxels_of_labelled
from openfusion.wire.keys import ShardId


class VolumeReadOuts:
    """The read-out half of the volume (mixed into it)."""

    params: VolumeParams
    _lock: threading.RLock
    _storage: VoxelStorage
    _pager: TilePager
    _readouts: TileReadouts
    _shard: ShardId
    # and the volume's _settle_growth() (its grid's background growth settled)

    @_read_out
    def labelled_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """(integer voxel coordinates (n, 3) int64, keys (n,) int64) of every voxel carrying a key."""
        coords, keys = self.labelled_blocks()
        return voxels_of_labelled(coords, keys, self.params.block_resolution)

    @_read_out
    def labelled_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """(block coordinates (N, 3), keys (N, R, R, R) [z, y, x], -1 = none) of the blocks holding a key."""
        coords, keys = self._storage.labelled_blocks()
        if not self._pager.stored_blocks:
            return coords, keys
        parts_c, parts_k = [coords], [keys]
        res = self.params.block_resolution
        for _, tc, raw in self._pager.iter_stored():
            c, k = labelled_of(tc, self._storage.slots.key1_of(raw["key"].reshape(len(tc), -1)), res)
            parts_c.append(c)
            parts_k.append(k)
        return np.concatenate(parts_c), np.concatenate(parts_k)

    def region_contacts(self, *, radius_vox: int = 1, lock: Any = None) -> RegionContacts:
        """Which regions' labelled voxels touch, how much, and each region's labelled voxel count
        (what a merge pass decides on; equal to :func:`openfusion.mapping.merging.block_contacts`
        of every labelled block). Kept per tile (:mod:`.tilereadouts`): only tiles whose
        neighbourhood changed since the last call are counted again, a chunk at a time, copied
        holding ``lock`` (a caller's reentrant lock, e.g. a service's) and the volume's lock."""
        for _ in range(3):
            tilereadouts.refresh(self._lock, self._readouts, what="contacts", lock=lock, radius_vox=radius_vox)
            with self._lock:
                missing = self._readouts.missing
                parts = self._readouts.contact_parts()
                if self._readouts.missing == missing:
                    break  # else a stored part had gone missing: its tile is read out again
        return tilereadouts.combine_contacts(parts)

    def region_table(self, *, lock: Any = None) -> RegionTable:
        """Per-region surface summaries of the whole map (equal to ``RegionTable.of_points`` of
        :meth:`extract_points`), kept per tile (:mod:`.tilereadouts`): only the tiles whose
        neighbourhood changed since the last call are read out again, a chunk at a time, copied
        holding ``lock`` and the volume's lock and read out holding neither. A map that changes
        meanwhile gives a table of the tiles as each was read; when the parts kept too few values
        for an exact box, those tiles are read again (the last try holds the locks throughout)."""
        for attempt in range(6):
            hold = attempt >= 3
            tilereadouts.refresh(self._lock, self._readouts, what="summaries", lock=lock, hold=hold)
            with tilereadouts.both(lock, self._lock) if hold else self._lock:
                missing = self._readouts.missing
                # Streamed: stored parts are read from the part store one at a time, never all at once.
                table, failing = tilereadouts.combine_summaries(
                    self._readouts.iter_summary_parts, self._storage.slots.key1, index=self._readouts.summary_index())
                if self._readouts.missing != missing:
                    continue  # a stored part had gone missing: its tile is read out again
                if not failing:
                    return table
                for (tile, slot), want in failing.items():
                    self._readouts.keep[(tile, slot)] = max(self._readouts.keep.get((tile, slot), 0), want)
                    self._readouts.summaries.pop(tile, None)
        raise RuntimeError("region summaries did not settle: the parts kept too few values six times")

    def refresh_region_table(self, *, settled_clock: int | None = None, lock: Any = None,
                             max_s: float | None = None) -> int:
        """Read out the stale summary parts of tiles whose neighbourhood last changed at or before
        ``settled_clock`` (a service's idle work, so a save has little left), for at most about
        ``max_s`` seconds; returns the tiles read."""
        return tilereadouts.refresh(self._lock, self._readouts, what="summaries", lock=lock,
                                    settled_clock=settled_clock, max_s=max_s)

    @property
    def readout_stats(self) -> dict[str, int]:
        """Tiles read out for region summaries and contacts so far (:mod:`.tilereadouts`)."""
        return dict(self._readouts.stats)

    @property
    def change_clock(self) -> int:
        """The tile versions' clock (grows with every change of the map's voxels)."""
        return self._pager.versions.clock

    # ------------------------------------------------------------------ read-out
    @_read_out
    def extract_points(
        self,
        keys: np.ndarray | list[int] | None = None,
        max_points: int | None = None,
        *,
        seed: int = 0,
    ) -> SurfacePoints:
        """The map's surface points with keys, as :func:`openfusion.mapping.readout.extract_points`
        gives them (which points, their order, ``keys``, ``max_points`` and ``seed``), tiles paged out
        included; a geometry shard's: those its own tiles own."""
        self._settle_growth()
        if self._shard.sharded:  # only the points its own tiles own, then the cap
            pts = self._extract_points(keys, None, seed)
            p = self.params
            keep = shards.own_points(pts.points, p.voxel_size_m, p.block_resolution, p.tile_blocks, self._shard)
            pts = SurfacePoints(pts.points[keep], pts.colors[keep], pts.keys[keep], pts.conf[keep])
            if max_points is not None and len(pts) > max_points:
                sel = np.sort(np.random.default_rng(seed).choice(len(pts), size=max_points, replace=False))
                pts = SurfacePoints(pts.points[sel], pts.colors[sel], pts.keys[sel], pts.conf[sel])
            return pts
        return self._extract_points(keys, max_points, seed)

    def _extract_points(self, keys: np.ndarray | list[int] | None, max_points: int | None, seed: int) -> SurfacePoints:
        if self._pager.stored_blocks:
            from openfusion.mapping import wholemap

            return wholemap.extract_points(self._storage, self._pager, keys, max_points, seed=seed)
        return readout.extract_points(self._storage, keys, max_points, seed=seed)

    @_read_out
    def extract_mesh(self, keys: np.ndarray | list[int] | None = None) -> SurfaceMesh:
        """Surface mesh (marching cubes); with ``keys``, only triangles whose 3 vertices carry one of
        those keys (unreferenced vertices dropped)."""
        if self._pager.stored_blocks:
            from openfusion.mapping import wholemap

            return self._own_mesh(wholemap.extract_mesh(self._storage, self._pager, keys))
        return self._own_mesh(readout.extract_mesh(self._storage, keys))

    def _own_mesh(self, mesh: SurfaceMesh) -> SurfaceMesh:
        """A shard's mesh: the triangles whose cube its own tiles own (unreferenced vertices dropped)."""
        if not self._shard.sharded or len(mesh.triangles) == 0:
            return mesh
        p = self.params
        keep = shards.own_points(mesh.vertices[mesh.triangles].mean(axis=1), p.voxel_size_m, p.block_resolution,
                                 p.tile_blocks, self._shard)
        tris = mesh.triangles[keep]
        used = np.zeros(len(mesh.vertices), bool)
        used[tris.reshape(-1)] = True
        remap = np.full(len(mesh.vertices), -1, np.int64)
        remap[used] = np.arange(int(used.sum()))
        return SurfaceMesh(mesh.vertices[used], remap[tris].astype(np.int32), mesh.colors[used], mesh.normals[used],
                           mesh.keys[used], mesh.conf[used])

    @_read_out
    def mesh_parts(self, keys: np.ndarray | list[int] | None = None) -> list[SurfaceMesh]:
        """The mesh in parts of at most ``wholemap.CHUNK_BLOCKS`` blocks each (a large map's mesh
        written or sent part by part; one part for a map with nothing paged out)."""
        from openfusion.mapping import wholemap

        if not self._pager.stored_blocks and self._storage.num_blocks <= wholemap.CHUNK_BLOCKS:
            return [self._own_mesh(readout.extract_mesh(self._storage, keys))]
        return [self._own_mesh(m) for m in wholemap.iter_mesh_parts(self._storage, self._pager, keys)]
