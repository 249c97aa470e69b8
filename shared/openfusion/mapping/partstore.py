"""The read-out parts of paged-out tiles, kept on disk beside the tile store instead of in memory.

:mod:`openfusion.mapping.tilereadouts` keeps a region-summary part and a region-contacts part per
tile. Kept in memory for every tile of a floor they grow with the area mapped (15-20 MiB on the
10-room building), which a memory budget cannot allow: a paged-out tile's parts go to disk with
it (:meth:`~openfusion.mapping.tilereadouts.TileReadouts.paged_out`) and are read back when a read-out
adds the parts up, so a merge pass or a save's summaries read a stored tile's small parts, never
decode the tile again, while nothing changed around it.

Where: an LMDB file (``parts-<pid>-<n>.mdb``, ``subdir=False``) in the tile store's folder, the
disk the map is on. It is a cache of this process's state, not part of the map: never committed,
never copied by a save (``Environment.copy`` copies the store's own environment only), removed when
the volume closes; files of processes that died are removed by the next one that opens a part
store there. Writes are not synced (a crash loses only the cache). A part store that cannot be
opened (a read-only folder) leaves the parts in memory (:class:`MemoryParts`).

Encoding: each part is a handful of numpy arrays (:func:`openfusion.mapping.tilereadouts.part_arrays`),
written as one ``.npz`` (no pickle, no compression: a few KiB each).
"""

from __future__ import annotations

import io
import itertools
import logging
import os
import re
from pathlib import Path

import lmdb
import numpy as np

logger = logging.getLogger(__name__)

_MAP_SIZE = 1 << 36  # address space only (64 GiB); the file grows with what is written
_counter = itertools.count()
_NAME = re.compile(r"^parts-(\d+)-\d+\.mdb$")


def _key(kind: str, tile: tuple[int, int, int]) -> bytes:
    return f"{kind}:{tile[0]},{tile[1]},{tile[2]}".encode()


def encode_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def decode_arrays(blob: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


class MemoryParts:
    """The fallback when no part store can be opened: the same interface, in memory."""

    def __init__(self) -> None:
        self._parts: dict[bytes, bytes] = {}

    def put(self, kind: str, tile: tuple[int, int, int], arrays: dict[str, np.ndarray]) -> None:
        self._parts[_key(kind, tile)] = encode_arrays(arrays)

    def get(self, kind: str, tile: tuple[int, int, int]) -> dict[str, np.ndarray] | None:
        blob = self._parts.get(_key(kind, tile))
        return None if blob is None else decode_arrays(blob)

    def delete(self, kind: str, tile: tuple[int, int, int]) -> None:
        self._parts.pop(_key(kind, tile), None)

    def clear(self) -> None:
        self._parts.clear()

    def close(self) -> None:
        self._parts.clear()


class PartStore(MemoryParts):
    """Parts by (kind, tile) in an LMDB file in ``folder`` (module docstring)."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        super().__init__()
        folder = Path(folder)
        _remove_orphans(folder)
        self.path = folder / f"parts-{os.getpid()}-{next(_counter)}.mdb"
        self.env = lmdb.open(str(self.path), subdir=False, map_size=_MAP_SIZE, sync=False, metasync=False,
                             lock=True, max_dbs=0, readahead=False)

    def put(self, kind: str, tile: tuple[int, int, int], arrays: dict[str, np.ndarray]) -> None:
        with self.env.begin(write=True) as txn:
            txn.put(_key(kind, tile), encode_arrays(arrays))

    def get(self, kind: str, tile: tuple[int, int, int]) -> dict[str, np.ndarray] | None:
        with self.env.begin() as txn:
            blob = txn.get(_key(kind, tile))
            return None if blob is None else decode_arrays(bytes(blob))

    def delete(self, kind: str, tile: tuple[int, int, int]) -> None:
        with self.env.begin(write=True) as txn:
            txn.delete(_key(kind, tile))

    def clear(self) -> None:
        with self.env.begin(write=True) as txn:
            txn.drop(self.env.open_db(txn=txn), delete=False)

    def close(self) -> None:
        env, self.env = self.env, None  # type: ignore[assignment]
        if env is None:
            return
        env.close()
        for p in (self.path, Path(f"{self.path}-lock")):
            try:
                p.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:
                logger.warning("could not remove the read-out part store %s: %s", p, exc)


def open_part_store(folder: str | os.PathLike[str] | None) -> MemoryParts:
    """A :class:`PartStore` in ``folder``, else (no folder, or it cannot be opened) :class:`MemoryParts`."""
    if folder is None:
        return MemoryParts()
    try:
        return PartStore(folder)
    except (lmdb.Error, OSError) as exc:
        logger.warning("read-out parts of paged-out tiles stay in memory: no part store in %s (%s)", folder, exc)
        return MemoryParts()


def _remove_orphans(folder: Path) -> None:
    """Remove part stores of processes that no longer exist (a crash left them)."""
    try:
        names = os.listdir(folder)
    except OSError:
        return
    for name in names:
        m = _NAME.match(name)
        if m is None or _alive(int(m.group(1))):
            continue
        for p in (folder / name, folder / f"{name}-lock"):
            try:
                p.unlink()
            except OSError:
                pass


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
