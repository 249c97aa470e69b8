"""Map files: one self-describing, versioned map: volume blocks, dictionary, embedding space, parameters.

Format version 2 (written by default since the tile store): a map *folder* holding a tile store,
``DIR/map.ofz/`` -- :mod:`openfusion.mapping.mapstore` describes it (tiles of compact voxels,
compressed, incremental checkpoints, crash-safe by LMDB's transactions). :func:`save_map`,
:func:`load_map`, :func:`load_latest_map` and :func:`load_map_summary` take either version:
a path ending in ``.npz`` (or a folder holding ``map.ofz.npz`` and no store) is version 1,
described below, and still loads; ``save_map`` to a ``.npz`` path still writes version 1.
Version 2 keeps no ``.prev`` copy: an LMDB commit is atomic and its two meta pages already keep
the previous transaction, and an incremental store has no second full copy to keep.

Format (``FORMAT_VERSION`` 1): an uncompressed ``.npz`` (zip of ``.npy`` arrays, no pickles) with

- ``format`` (the string ``openfusion-z-map``), ``format_version`` (int),
- ``meta_json``: JSON with the volume parameters, the dictionary's embedding space, dimension,
  version, next key and labels, the caller's ``meta``, the relevancy calibration of the space
  (``relevancy``: method, temperature, threshold, negatives, query categories, head rule;
  :mod:`openfusion.mapping.relevancy`; absent in files saved before it, and without ``method`` in
  files saved before the query categories: both then use the library's table, the latter with a
  logged reason), and shape/dtype/CRC-32 of every array,
- ``volume_block_coords`` (N, 3) int32, ``volume_tsdf`` / ``volume_weight`` / ``volume_conf``
  (N, r, r, r) float32, ``volume_color`` (N, r, r, r, 3) float32, ``volume_key`` (N, r, r, r)
  int32 (-1 = none),
- ``dict_keys`` (k,) int64, ``dict_mean_embeddings`` (k, d) float32, ``dict_counts`` (k,) int64,
- region summaries (:class:`~openfusion.mapping.queries.RegionTable` of the saved surface, one row
  per region with surface points, sorted by key): ``summary_keys`` (n,) int32,
  ``summary_num_points`` (n,) int64, ``summary_centroid`` / ``summary_bbox_min`` /
  ``summary_bbox_max`` (n, 3) float32 (the 1st-99th percentile box of every query path).

The summaries let a text query skip the volume: :func:`load_map_summary` opens the archive and
reads only ``format``, ``format_version``, ``meta_json``, the ``dict_*`` and the ``summary_*``
members (an ``.npz`` is a zip of separately stored members, read one by one; a few kB for a room),
each checked against its CRC-32, and builds the dictionary and the table without Open3D.
``save_map`` computes them from one surface read-out of the volume it saves (the file holds the
volume and its summaries from the same moment). They were added within format version 1 as
optional members: files saved before them (no ``summary_*``) still load with :func:`load_map`,
and :func:`load_map_summary` returns None for them, so a query falls back to reading the whole
map; builds that predate them ignore the extra members.

Writing (:func:`save_map`) keeps the last two checkpoints, the newest (``map.ofz.npz``) and the
one before it (``map.ofz.prev.npz``, :func:`previous_map_path`), in this order:

1. the new map is written to a temporary file in the target folder (``.map.ofz.npz.*.tmp``) and
   fsynced: a crash here leaves the newest and the previous file untouched (the temporary file
   is never read; a later save removes it once it is :data:`STALE_TEMP_S` old);
2. the newest file is renamed to the ``.prev`` name (replacing the older one) and the folder
   fsynced, so this rename reaches the disk before the next one;
3. the temporary file is renamed to the target name (``os.replace``) and the folder fsynced.

At every instant one complete file exists: the target until step 2, the ``.prev`` between 2 and
3, both after 3. Renaming the old file instead of keeping it under a hard link works on every
file system; the price is the moment between 2 and 3 when only the ``.prev`` exists, which
:func:`load_latest_map` covers (a failed step 3 also renames it back). Keeping the older file
means a checkpoint that is corrupted later (a bad sector, a copy cut short) still leaves one to
load: :func:`load_latest_map` tries the newest file and falls back to the ``.prev`` with one log
line. ``keep_previous=False`` skips step 2 (one file, replaced in place).

No whole-file checksum: the header cannot hold the checksum of the file it is part of (a sidecar
file would be one more file to keep in step with every rename), and it would add nothing: every
array is checked against its CRC-32 in the header, the zip members carry their own CRC-32 (also
checked by ``np.load``) and the zip directory sits at the end of the file, so a torn or
truncated file fails to open and flipped bytes fail a CRC; what is left unchecked (zip local
headers) holds no map data. Loading checks every array and builds fresh objects; any problem
raises one :class:`MapFormatError` and nothing is returned.
"""

from __future__ import annotations

import glob
import json
import logging
import os
import tempfile
import time
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from openfusion.mapping import shardmaps
from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.errors import MapFormatError
from openfusion.mapping.mapstore import header_meta
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.queries import RegionTable
from openfusion.mapping.relevancy import calibration_for
from openfusion.mapping.tilestore import STORE_DIR_NAME, TileStore, find_store, fsync_dir
from openfusion.wire.schemas import DictionarySnapshot

if TYPE_CHECKING:  # Open3D: imported only where a volume is built (load_map), not for summaries
    from openfusion.mapping.volume import SemanticVolume

logger = logging.getLogger(__name__)

FORMAT_NAME = "openfusion-z-map"
FORMAT_VERSION = 1
MAP_FILE_NAME = "map.ofz.npz"
PREVIOUS_TAG = ".prev"  # map.ofz.npz -> map.ofz.prev.npz
#: A temporary file this old (seconds since its last write) was left by a killed writer: the next
#: save of the same map removes it. A younger one may belong to a save still writing.
STALE_TEMP_S = 300.0

_VOLUME_ARRAYS = ("block_coords", "tsdf", "weight", "color", "key", "conf")
_DICT_ARRAYS = ("keys", "mean_embeddings", "counts")
_SUMMARY_ARRAYS = ("keys", "num_points", "centroid", "bbox_min", "bbox_max")  # RegionTable's fields


@dataclass
class LoadedMap:
    volume: SemanticVolume
    dictionary: RegionDictionary
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None  # the file it was read from (the ``.prev`` one after a fallback)
    relevancy: dict[str, Any] | None = None  # the relevancy calibration saved with the map (None: older file)


@dataclass
class MapSummary:
    """What a text query needs from a saved map, read without the volume (:func:`load_map_summary`)."""

    dictionary: RegionDictionary
    regions: RegionTable
    volume_params: VolumeParams
    meta: dict[str, Any] = field(default_factory=dict)
    relevancy: dict[str, Any] | None = None  # the relevancy calibration saved with the map (None: older file)


def resolve_map_path(path: str | os.PathLike[str]) -> Path:
    """A path ending in ``.npz`` is a version-1 map file; a folder holds a tile store
    (``map.ofz/``, version 2, where a new map goes) or an older ``map.ofz.npz``."""
    p = Path(path)
    if p.suffix == ".npz":
        return p
    store = find_store(p)
    if store is not None:
        return store
    if (p / MAP_FILE_NAME).exists() or previous_map_path_v1(p).exists():
        return p / MAP_FILE_NAME
    return p / STORE_DIR_NAME


def _is_store_path(path: str | os.PathLike[str]) -> Path | None:
    p = Path(path)
    return None if p.suffix == ".npz" else find_store(p)


def previous_map_path_v1(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    target = p if p.suffix == ".npz" else p / MAP_FILE_NAME
    return target.with_name(target.name[: -len(".npz")] + PREVIOUS_TAG + ".npz")


def previous_map_path(path: str | os.PathLike[str]) -> Path:
    """Where :func:`save_map` keeps the version-1 map it replaced: ``map.ofz.npz`` -> ``map.ofz.prev.npz``."""
    return previous_map_path_v1(path)


def _crc(arr: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(arr).view(np.uint8).reshape(-1)) & 0xFFFFFFFF


def save_map(
    path: str | os.PathLike[str],
    volume: SemanticVolume,
    dictionary: RegionDictionary,
    meta: dict[str, Any] | None = None,
    *,
    regions: RegionTable | None = None,
    keep_previous: bool = True,
    summary: bool = True,
) -> Path:
    """Write the map atomically; returns the file written. ``meta`` must be JSON-serialisable.

    ``regions``: the region summaries of ``volume`` as it is now, when the caller has them;
    by default they are computed here (one surface read-out, about 1.3 s for a furnished room at
    2 cm on two CPU cores). ``summary=False`` stores none (a crash-recovery checkpoint: the
    surface read-out is most of a save's cost; :func:`load_map_summary` then answers None and
    readers load the volume, as for a map saved before summaries existed). ``keep_previous``: a file already at the target is kept as its
    ``.prev`` sibling (module docstring: the order of the renames). An ``OSError`` (disk full,
    read-only folder) propagates with the files as they were and no temporary file left."""
    user_meta = dict(meta or {})
    try:
        json.dumps(user_meta)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"meta must be JSON-serialisable: {exc}") from exc
    if Path(path).suffix != ".npz":
        from openfusion.mapping.mapstore import save_store

        written = save_store(path, volume, dictionary, user_meta, regions=regions, summary=summary)
        logger.info("saved map %s: %d blocks, %d regions", written, volume.num_blocks_total, len(dictionary))
        return written
    target = resolve_map_path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {f"volume_{k}": v for k, v in volume.to_arrays().items()}
    snap = dictionary.snapshot()
    arrays["dict_keys"] = snap.keys.astype(np.int64)
    arrays["dict_mean_embeddings"] = snap.embeddings.astype(np.float32)
    arrays["dict_counts"] = snap.counts.astype(np.int64)
    if regions is None and summary:
        regions = volume.region_table()  # per tile (bounded memory; equal to the whole surface's table)
    if summary and regions is not None:
        for name in _SUMMARY_ARRAYS:
            arrays[f"summary_{name}"] = np.ascontiguousarray(getattr(regions, name))
    header = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "created_unix_s": time.time(),
        "volume_params": volume.params.to_dict(),
        "dictionary": {
            "embedding_space": snap.embedding_space,
            "dim": snap.dim,
            "version": snap.version,
            "next_key": snap.next_key,
            "labels": [label or None for label in snap.labels],  # JSON null = no label
        },
        "meta": user_meta,
        # How relevancy and match are computed in the map's space (openfusion.mapping.relevancy),
        # so the map answers with the calibration it was made with.
        "relevancy": calibration_for(snap.embedding_space).to_dict(),
        "arrays": {
            name: {"shape": list(a.shape), "dtype": a.dtype.str, "crc32": _crc(a)}
            for name, a in arrays.items()
        },
    }
    payload = {
        "format": np.array(FORMAT_NAME),
        "format_version": np.array(FORMAT_VERSION, np.int64),
        "meta_json": np.array(json.dumps(header)),
        **arrays,
    }
    _remove_stale_temps(target)
    fd, tmp_name = tempfile.mkstemp(prefix=_temp_prefix(target), suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **payload)
            fh.flush()
            os.fsync(fh.fileno())
        _install(Path(tmp_name), target, keep_previous=keep_previous)
    except BaseException:
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        except OSError as exc:
            logger.warning("could not remove the temporary map file %s: %s", tmp_name, exc)
        raise
    logger.info(
        "saved map %s: %d blocks, %d regions (%.1f MB)",
        target,
        len(arrays["volume_block_coords"]),
        len(snap.keys),
        target.stat().st_size / 1e6,
    )
    return target


def _temp_prefix(target: Path) -> str:
    return f".{target.name}."


def _install(tmp: Path, target: Path, *, keep_previous: bool) -> None:
    """Steps 2 and 3 of the module docstring: the newest file becomes ``.prev``, ``tmp`` the newest."""
    previous = previous_map_path(target) if keep_previous and target.is_file() else None
    if previous is not None:
        os.replace(target, previous)
        fsync_dir(target.parent)
    try:
        os.replace(tmp, target)
    except BaseException:
        if previous is not None:  # put the newest file back where strict readers look for it
            try:
                os.replace(previous, target)
            except OSError as exc:
                logger.warning("could not rename %s back to %s: %s", previous, target, exc)
        raise
    fsync_dir(target.parent)


def _remove_stale_temps(target: Path) -> None:
    """Remove temporary files of ``target`` left by a writer that was killed mid-save."""
    now = time.time()
    for leftover in target.parent.glob(f"{glob.escape(_temp_prefix(target))}*.tmp"):
        try:
            if now - leftover.stat().st_mtime >= STALE_TEMP_S:
                leftover.unlink()
                logger.info("removed %s, left by an interrupted save", leftover)
        except OSError as exc:  # gone meanwhile, or not ours to remove: not this save's problem
            logger.debug("leftover %s not removed: %s", leftover, exc)


def load_map(
    path: str | os.PathLike[str],
    *,
    device: str | None = None,
    writable: bool = False,
    memory_budget_mb: float | None | str = "map",
) -> LoadedMap:
    """Read a map written by :func:`save_map` (optionally onto another ``device``).

    Version 2 (a tile store): ``writable`` makes the store the volume's own (the geometry service
    checkpoints into the store it loaded); ``memory_budget_mb`` (``"map"``: the map's own) pages
    tiles in on demand instead of reading them all (:mod:`openfusion.mapping.mapstore`).

    Raises :class:`MapFormatError` for a missing, truncated, corrupt, unknown-version or
    inconsistent file; nothing is half-loaded.
    """
    store_path = _is_store_path(path)
    if store_path is not None:
        return _load_store(store_path, device=device, writable=writable, memory_budget_mb=memory_budget_mb)
    parts = shardmaps.shard_parts(path) if not writable else None  # saved by geometry shards: merged
    if parts is not None:
        return shardmaps.load_sharded(parts, load_map, device=device, memory_budget_mb=memory_budget_mb)
    target = resolve_map_path(path)
    return _guarded(target, lambda npz: _load_archive(target, npz, device))


def _load_store(path: Path, *, device: str | None, writable: bool, memory_budget_mb: Any) -> LoadedMap:
    from openfusion.mapping.mapstore import load_store

    store = TileStore(path, readonly=not writable)
    try:
        volume, header, arrays = load_store(store, device=device, memory_budget_mb=memory_budget_mb)
    except BaseException:
        store.close()
        raise
    if not writable and volume.pager.base is None:
        store.close()  # every tile was read: the store is not needed any more
    dictionary = _dictionary(header, arrays)
    logger.info("loaded map %s: %d blocks (%d resident), %d regions", path, volume.num_blocks_total,
                volume.num_blocks, len(dictionary))
    return LoadedMap(volume, dictionary, header_meta(header), path, header.get("relevancy"))


def load_latest_map(path: str | os.PathLike[str], *, device: str | None = None, writable: bool = False) -> LoadedMap:
    """The newest checkpoint at ``path``, or the one before it when the newest is corrupt or missing.

    Tries :func:`load_map` on the file; on a :class:`MapFormatError` logs one warning
    (``checkpoint X is corrupt (reason); loading the previous one Y``) and loads the ``.prev``
    file that :func:`save_map` kept (``LoadedMap.path`` says which one was read). Raises
    :class:`MapFormatError` naming both files and both reasons when neither loads. For
    checkpoints a service writes and reads back itself; a map a user names is read strictly with
    :func:`load_map`.
    """
    store_path = _is_store_path(path)
    if store_path is not None:  # version 2: no .prev (module docstring)
        return load_map(path, device=device, writable=writable)
    newest = resolve_map_path(path)
    previous = previous_map_path(newest)
    try:
        return load_map(newest, device=device)
    except MapFormatError as exc:
        first = _reason(newest, exc)
        state = "corrupt" if newest.exists() else "missing"
        if not previous.is_file():
            if state == "missing":
                raise
            raise MapFormatError(f"{newest}: {first}; there is no previous checkpoint {previous.name}") from exc
    try:
        loaded = load_map(previous, device=device)
    except MapFormatError as exc:
        raise MapFormatError(
            f"no loadable checkpoint: {newest} is {state} ({first}) and the previous one {previous} "
            f"is corrupt ({_reason(previous, exc)})"
        ) from exc
    aside = ""
    if state == "corrupt":
        # Set the corrupt file aside (kept for a post-mortem), so the next save does not demote it
        # to .prev over the good checkpoint just loaded: after that save there are two good ones.
        kept = newest.with_name(newest.name.removesuffix(".npz") + ".corrupt.npz")
        try:
            os.replace(newest, kept)
            aside = f" (the corrupt file is kept as {kept.name})"
        except OSError as exc:
            aside = f" (could not move the corrupt file aside: {exc})"
    logger.warning("checkpoint %s is %s (%s); loading the previous one %s%s", newest, state, first, previous, aside)
    return loaded


def _reason(target: Path, exc: MapFormatError) -> str:
    """The message of ``exc`` without the leading ``{target}: `` every message here starts with."""
    text = str(exc)
    prefix = f"{target}: "
    return text[len(prefix) :] if text.startswith(prefix) else text


def load_map_summary(path: str | os.PathLike[str]) -> MapSummary | None:
    """The dictionary and region summaries of a saved map without its volume (no Open3D); None
    for a map saved before summaries were stored (read it with :func:`load_map`).

    Reads and CRC-checks only the header, dictionary and summary members. Raises
    :class:`MapFormatError` as :func:`load_map` does.
    """
    store_path = _is_store_path(path)
    if store_path is not None:
        return _load_store_summary(store_path)
    parts = shardmaps.shard_parts(path)  # saved by geometry shards: the parts' summaries merged
    if parts is not None:
        return shardmaps.load_sharded_summary(parts, load_map_summary)
    target = resolve_map_path(path)
    return _guarded(target, lambda npz: _load_summary(target, npz))


def _load_store_summary(path: Path) -> MapSummary | None:
    from openfusion.mapping.mapstore import check_header, dict_names, summary_names

    with TileStore(path, readonly=True) as store:
        # Header and arrays from one read transaction (a running geometry may commit meanwhile).
        header, arrays, tiles = store.read_committed(
            lambda h: dict_names() + summary_names(check_header(store, h)) if summary_names(check_header(store, h)) else [])
        tiles.close()
        header = check_header(store, header)
        if not summary_names(header):
            return None
    dictionary = _dictionary(header, arrays)
    regions = _region_table(path, arrays)
    params = VolumeParams.from_dict(header["volume_params"])
    logger.info("read map summary %s: %d regions, %d with surface points", path, len(dictionary), len(regions))
    return MapSummary(dictionary, regions, params, header_meta(header), header.get("relevancy"))


def _guarded(target: Path, read: Any) -> Any:
    if not target.is_file():
        raise MapFormatError(f"{target}: no map file there")
    try:
        # Open the file ourselves: np.load leaks its own handle when the zip directory is unreadable.
        with open(target, "rb") as fh:
            loaded = np.load(fh, allow_pickle=False)
            if not isinstance(loaded, np.lib.npyio.NpzFile):
                raise MapFormatError(f"{target}: not an OpenFusion-Z map (a single array, not an archive)")
            with loaded as npz:
                return read(npz)
    except MapFormatError:
        raise
    except (
        OSError,
        EOFError,
        zipfile.BadZipFile,
        ValueError,
        KeyError,
        TypeError,
        json.JSONDecodeError,
    ) as exc:
        raise MapFormatError(f"{target}: unreadable map file ({type(exc).__name__}: {exc})") from exc


def _header(target: Path, npz: np.lib.npyio.NpzFile) -> dict[str, Any]:
    names = set(npz.files)
    for required in ("format", "format_version", "meta_json"):
        if required not in names:
            raise MapFormatError(f"{target}: not an OpenFusion-Z map (missing {required!r})")
    fmt = str(npz["format"][()])
    if fmt != FORMAT_NAME:
        raise MapFormatError(f"{target}: format {fmt!r} is not {FORMAT_NAME!r}")
    version = int(npz["format_version"][()])
    if version != FORMAT_VERSION:
        raise MapFormatError(
            f"{target}: map format version {version} is not supported (this build reads {FORMAT_VERSION})"
        )
    return json.loads(str(npz["meta_json"][()]))


def _read_arrays(
    target: Path, npz: np.lib.npyio.NpzFile, header: dict[str, Any], expected: list[str]
) -> dict[str, np.ndarray]:
    """The ``expected`` members, each checked against the header's shape, dtype and CRC-32."""
    names = set(npz.files)
    specs = header["arrays"]
    arrays: dict[str, np.ndarray] = {}
    for name in expected:
        if name not in names or name not in specs:
            raise MapFormatError(f"{target}: array {name!r} is missing")
        arr = npz[name]
        spec = specs[name]
        if list(arr.shape) != list(spec["shape"]) or arr.dtype.str != spec["dtype"]:
            raise MapFormatError(
                f"{target}: array {name!r} is {arr.dtype.str} {arr.shape}, header says "
                f"{spec['dtype']} {tuple(spec['shape'])}"
            )
        if _crc(arr) != int(spec["crc32"]):
            raise MapFormatError(f"{target}: array {name!r} fails its CRC-32 check (corrupt file)")
        arrays[name] = arr
    return arrays


def _summary_names(npz: np.lib.npyio.NpzFile, header: dict[str, Any]) -> list[str]:
    """The summary members to read: all of them, or none for a map saved before they existed
    (a file that lists only some is refused by :func:`_read_arrays` as missing one)."""
    names = [f"summary_{n}" for n in _SUMMARY_ARRAYS]
    present = set(npz.files) | set(header["arrays"])
    return names if any(n in present for n in names) else []


def _dictionary(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> RegionDictionary:
    d = header["dictionary"]
    snapshot = DictionarySnapshot(
        embedding_space=str(d["embedding_space"]),
        dim=int(d["dim"]),
        version=int(d["version"]),
        next_key=int(d["next_key"]),
        keys=arrays["dict_keys"].astype(np.int32),
        embeddings=arrays["dict_mean_embeddings"],
        counts=arrays["dict_counts"],
        labels=[label or "" for label in d["labels"]],
    )
    return RegionDictionary.from_snapshot(snapshot)


def _region_table(target: Path, arrays: dict[str, np.ndarray]) -> RegionTable:
    table = RegionTable(**{n: arrays[f"summary_{n}"] for n in _SUMMARY_ARRAYS})
    n = len(table.keys)
    if any(len(getattr(table, f)) != n for f in _SUMMARY_ARRAYS) or (n > 1 and (np.diff(table.keys) <= 0).any()):
        raise MapFormatError(f"{target}: inconsistent region summaries")
    return table


def _load_summary(target: Path, npz: np.lib.npyio.NpzFile) -> MapSummary | None:
    header = _header(target, npz)
    summary = _summary_names(npz, header)
    if not summary:
        return None
    arrays = _read_arrays(target, npz, header, [f"dict_{n}" for n in _DICT_ARRAYS] + summary)
    dictionary = _dictionary(header, arrays)
    regions = _region_table(target, arrays)
    params = VolumeParams.from_dict(header["volume_params"])
    logger.info("read map summary %s: %d regions, %d with surface points", target, len(dictionary), len(regions))
    return MapSummary(dictionary, regions, params, header_meta(header), header.get("relevancy"))


def _load_archive(target: Path, npz: np.lib.npyio.NpzFile, device: str | None) -> LoadedMap:
    from openfusion.mapping.volume import SemanticVolume

    header = _header(target, npz)
    expected = (
        [f"volume_{n}" for n in _VOLUME_ARRAYS]
        + [f"dict_{n}" for n in _DICT_ARRAYS]
        + _summary_names(npz, header)  # checked too, so a corrupt file is refused whole
    )
    arrays = _read_arrays(target, npz, header, expected)
    params = VolumeParams.from_dict(header["volume_params"])
    if device is not None:
        params = params.with_changes(device=device)
    volume = SemanticVolume.from_arrays(params, {n: arrays[f"volume_{n}"] for n in _VOLUME_ARRAYS})
    dictionary = _dictionary(header, arrays)
    used = arrays["volume_key"]
    unknown = np.setdiff1d(np.unique(used[used >= 0]), arrays["dict_keys"].astype(np.int32))
    if len(unknown):
        logger.warning(
            "%s: %d voxel keys have no dictionary entry (e.g. %s)", target, len(unknown), unknown[:5]
        )
    logger.info("loaded map %s: %d blocks, %d regions", target, volume.num_blocks, len(dictionary))
    return LoadedMap(volume, dictionary, header_meta(header), target, header.get("relevancy"))
