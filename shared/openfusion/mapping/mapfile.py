"""One self-describing, versioned map file: volume blocks, dictionary, embedding space, parameters.

Format (``FORMAT_VERSION`` 1): an uncompressed ``.npz`` (zip of ``.npy`` arrays, no pickles) with

- ``format`` (the string ``openfusion-z-map``), ``format_version`` (int),
- ``meta_json``: JSON with the volume parameters, the dictionary's embedding space, dimension,
  version, next key and labels, the caller's ``meta``, and shape/dtype/CRC-32 of every array,
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

Writing goes to a temporary file in the target folder, is fsynced and then renamed over the
target (``os.replace``), so a crash leaves the old map or the new one, never half of one. Loading
checks every array against the CRC-32 in the metadata and builds fresh objects; any problem
raises one :class:`MapFormatError` and nothing is returned.
"""

from __future__ import annotations

import contextlib
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

from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.errors import MapFormatError
from openfusion.mapping.params import VolumeParams
from openfusion.mapping.queries import RegionTable
from openfusion.wire.schemas import DictionarySnapshot

if TYPE_CHECKING:  # Open3D: imported only where a volume is built (load_map), not for summaries
    from openfusion.mapping.volume import SemanticVolume

logger = logging.getLogger(__name__)

FORMAT_NAME = "openfusion-z-map"
FORMAT_VERSION = 1
MAP_FILE_NAME = "map.ofz.npz"

_VOLUME_ARRAYS = ("block_coords", "tsdf", "weight", "color", "key", "conf")
_DICT_ARRAYS = ("keys", "mean_embeddings", "counts")
_SUMMARY_ARRAYS = ("keys", "num_points", "centroid", "bbox_min", "bbox_max")  # RegionTable's fields


@dataclass
class LoadedMap:
    volume: SemanticVolume
    dictionary: RegionDictionary
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class MapSummary:
    """What a text query needs from a saved map, read without the volume (:func:`load_map_summary`)."""

    dictionary: RegionDictionary
    regions: RegionTable
    volume_params: VolumeParams
    meta: dict[str, Any] = field(default_factory=dict)


def resolve_map_path(path: str | os.PathLike[str]) -> Path:
    """A path ending in ``.npz`` is the map file; anything else is a folder holding ``map.ofz.npz``."""
    p = Path(path)
    return p if p.suffix == ".npz" else p / MAP_FILE_NAME


def _crc(arr: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(arr).view(np.uint8).reshape(-1)) & 0xFFFFFFFF


def save_map(
    path: str | os.PathLike[str],
    volume: SemanticVolume,
    dictionary: RegionDictionary,
    meta: dict[str, Any] | None = None,
    *,
    regions: RegionTable | None = None,
) -> Path:
    """Write the map atomically; returns the file written. ``meta`` must be JSON-serialisable.

    ``regions``: the region summaries of ``volume`` as it is now, when the caller has them;
    by default they are computed here (one surface read-out, about 1.3 s for a furnished room at
    2 cm on two CPU cores)."""
    user_meta = dict(meta or {})
    try:
        json.dumps(user_meta)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"meta must be JSON-serialisable: {exc}") from exc
    target = resolve_map_path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {f"volume_{k}": v for k, v in volume.to_arrays().items()}
    snap = dictionary.snapshot()
    arrays["dict_keys"] = snap.keys.astype(np.int64)
    arrays["dict_mean_embeddings"] = snap.embeddings.astype(np.float32)
    arrays["dict_counts"] = snap.counts.astype(np.int64)
    if regions is None:
        surface = volume.extract_points()
        regions = RegionTable.of_points(surface.keys, surface.points)
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
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise
    _fsync_dir(target.parent)
    logger.info(
        "saved map %s: %d blocks, %d regions (%.1f MB)",
        target,
        len(arrays["volume_block_coords"]),
        len(snap.keys),
        target.stat().st_size / 1e6,
    )
    return target


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        logger.debug("fsync of folder %s not supported", folder)
    finally:
        os.close(fd)


def load_map(path: str | os.PathLike[str], *, device: str | None = None) -> LoadedMap:
    """Read a map written by :func:`save_map` (optionally onto another ``device``).

    Raises :class:`MapFormatError` for a missing, truncated, corrupt, unknown-version or
    inconsistent file; nothing is half-loaded.
    """
    target = resolve_map_path(path)
    return _guarded(target, lambda npz: _load_archive(target, npz, device))


def load_map_summary(path: str | os.PathLike[str]) -> MapSummary | None:
    """The dictionary and region summaries of a saved map without its volume (no Open3D); None
    for a map saved before summaries were stored (read it with :func:`load_map`).

    Reads and CRC-checks only the header, dictionary and summary members. Raises
    :class:`MapFormatError` as :func:`load_map` does.
    """
    target = resolve_map_path(path)
    return _guarded(target, lambda npz: _load_summary(target, npz))


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


def _meta(header: dict[str, Any]) -> dict[str, Any]:
    meta = dict(header.get("meta", {}))
    meta.setdefault("created_unix_s", header.get("created_unix_s"))
    return meta


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
    return MapSummary(dictionary, regions, params, _meta(header))


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
    return LoadedMap(volume, dictionary, _meta(header))
