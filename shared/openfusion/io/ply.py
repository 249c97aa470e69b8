"""Minimal PLY vertex reader (numpy only) for ground-truth meshes with custom vertex properties.

ScanNet's ``<scene>_vh_clean_2.labels.ply`` stores a per-vertex ``label`` (NYU40 id) that
Open3D does not expose, so the header is parsed here and the vertex element read with a numpy
structured dtype. Supports ``binary_little_endian``, ``binary_big_endian`` and ``ascii``; only
the vertex element is read (elements before it must be fixed-size in binary files; faces after
it are skipped).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from openfusion.errors import UserError

logger = logging.getLogger(__name__)

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip

_MAX_HEADER_BYTES = 64 * 1024


class PlyError(UserError, ValueError):
    """The file is not a PLY this reader understands (message names the file and the problem)."""


@dataclass(frozen=True)
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type code) of scalar properties
    lists: list[tuple[str, str, str]]  # (name, count type code, item type code) of list properties

    @property
    def has_list(self) -> bool:
        return bool(self.lists)


@dataclass(frozen=True)
class PlyData:
    """Vertex properties and, when the file has a plain triangle face element, the triangles."""

    vertices: dict[str, np.ndarray]
    triangles: np.ndarray | None  # (M, 3) int64 vertex indices


def read_ply_vertices(path: str | Path) -> dict[str, np.ndarray]:
    """Return the vertex properties of a PLY file as ``{name: (N,) array}``."""
    return read_ply(path, with_faces=False).vertices


def read_ply(path: str | Path, *, with_faces: bool = True) -> PlyData:
    """Vertex properties and triangles (``None`` when absent, not all triangles, or unsupported)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise PlyError(f"{path}: cannot read PLY file: {exc}") from exc
    end = raw.find(b"end_header", 0, _MAX_HEADER_BYTES)
    if not raw.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header' in the first 64 KiB)")
    nl = raw.find(b"\n", end)
    if nl < 0:
        raise PlyError(f"{path}: header is not terminated by a newline")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    body_offset = nl + 1
    fmt, elements = _parse_header(path, header)
    vertex_pos = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if vertex_pos is None:
        raise PlyError(f"{path}: no 'vertex' element")
    vertex = elements[vertex_pos]
    if vertex.has_list:
        raise PlyError(f"{path}: list properties in the vertex element are not supported")
    if fmt == "ascii":
        return _read_ascii(path, raw[body_offset:], elements, vertex_pos, with_faces=with_faces)
    endian = "<" if fmt == "binary_little_endian" else ">"
    offset = body_offset
    for e in elements[:vertex_pos]:
        if e.has_list:
            raise PlyError(
                f"{path}: element '{e.name}' with list properties precedes 'vertex'; not supported"
            )
        offset += e.count * np.dtype([(n, endian + t) for n, t in e.properties]).itemsize
    dtype = np.dtype([(n, endian + t) for n, t in vertex.properties])
    need = vertex.count * dtype.itemsize
    if len(raw) - offset < need:
        raise PlyError(
            f"{path}: truncated: header declares {vertex.count} vertices ({need} bytes), "
            f"file has {len(raw) - offset} bytes after the header"
        )
    arr = np.frombuffer(raw, dtype=dtype, count=vertex.count, offset=offset)
    vertices = {n: arr[n].astype(arr[n].dtype.newbyteorder("="), copy=True) for n, _ in vertex.properties}
    triangles = None
    if with_faces and vertex_pos + 1 < len(elements) and elements[vertex_pos + 1].name == "face":
        face = elements[vertex_pos + 1]
        if face.properties or len(face.lists) != 1:
            logger.info("%s: face element is not a single index list; faces not read", path)
        else:
            _, count_t, item_t = face.lists[0]
            fdt = np.dtype([("n", endian + count_t), ("v", endian + item_t, (3,))])
            avail = (len(raw) - offset - need) // fdt.itemsize
            rec = np.frombuffer(raw, dtype=fdt, count=min(face.count, avail), offset=offset + need)
            if avail < face.count or not np.all(rec["n"] == 3):
                logger.info("%s: faces are not all triangles (or truncated); faces not read", path)
            else:
                triangles = rec["v"].astype(np.int64)
    return PlyData(vertices, _checked_triangles(path, triangles, vertex.count))


def _checked_triangles(path: Path, triangles: np.ndarray | None, num_vertices: int) -> np.ndarray | None:
    if triangles is not None and triangles.size and (triangles.min() < 0 or triangles.max() >= num_vertices):
        raise PlyError(f"{path}: face indices out of range for {num_vertices} vertices")
    return triangles


def _parse_header(path: Path, lines: list[str]) -> tuple[str, list[_Element]]:
    fmt = None
    elements: list[_Element] = []
    for ln, line in enumerate(lines, start=1):
        parts = line.split()
        if not parts or parts[0] in ("ply", "comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2 or parts[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise PlyError(f"{path}: header line {ln}: unknown format {line!r}")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise PlyError(f"{path}: header line {ln}: bad element line {line!r}")
            elements.append(_Element(parts[1], int(parts[2]), [], []))
        elif parts[0] == "property":
            if not elements:
                raise PlyError(f"{path}: header line {ln}: property before any element")
            e = elements[-1]
            if len(parts) == 5 and parts[1] == "list":
                if parts[2] not in _PLY_TYPES or parts[3] not in _PLY_TYPES:
                    raise PlyError(f"{path}: header line {ln}: unsupported list property {line!r}")
                e.lists.append((parts[4], _PLY_TYPES[parts[2]], _PLY_TYPES[parts[3]]))
                continue
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                raise PlyError(f"{path}: header line {ln}: unsupported property {line!r}")
            e.properties.append((parts[2], _PLY_TYPES[parts[1]]))
        else:
            raise PlyError(f"{path}: header line {ln}: unexpected {line!r}")
    if fmt is None:
        raise PlyError(f"{path}: header has no 'format' line")
    return fmt, elements


def _read_ascii(
    path: Path, body: bytes, elements: list[_Element], vertex_pos: int, *, with_faces: bool
) -> PlyData:
    lines = body.decode("ascii", errors="replace").splitlines()
    start = sum(e.count for e in elements[:vertex_pos])
    vertex = elements[vertex_pos]
    rows = lines[start : start + vertex.count]
    if len(rows) < vertex.count:
        raise PlyError(f"{path}: truncated: {vertex.count} vertices declared, {len(rows)} lines found")
    try:
        table = np.array([r.split() for r in rows], dtype=np.float64).reshape(vertex.count, -1)
    except ValueError as exc:
        raise PlyError(f"{path}: bad vertex line in ASCII body: {exc}") from exc
    if table.shape[1] != len(vertex.properties):
        raise PlyError(
            f"{path}: vertex lines have {table.shape[1]} values, header declares {len(vertex.properties)}"
        )
    vertices = {n: table[:, i].astype(t) for i, (n, t) in enumerate(vertex.properties)}
    triangles = None
    if with_faces and vertex_pos + 1 < len(elements) and elements[vertex_pos + 1].name == "face":
        face = elements[vertex_pos + 1]
        frows = lines[start + vertex.count : start + vertex.count + face.count]
        try:
            ftab = [list(map(int, r.split())) for r in frows]
        except ValueError as exc:
            raise PlyError(f"{path}: bad face line in ASCII body: {exc}") from exc
        if len(ftab) == face.count and all(len(r) == 4 and r[0] == 3 for r in ftab):
            triangles = np.array([r[1:] for r in ftab], dtype=np.int64).reshape(-1, 3)
    return PlyData(vertices, _checked_triangles(path, triangles, vertex.count))


def write_ply_vertices(
    path: str | Path, properties: dict[str, np.ndarray], *, faces: np.ndarray | None = None
) -> None:
    """Write a binary little-endian PLY with the given vertex properties (and optional triangles).

    Used by tests and by tools that export labelled point clouds; property types follow the
    arrays' dtypes.
    """
    path = Path(path)
    names = list(properties)
    if not names:
        raise ValueError("need at least one vertex property")
    n = len(properties[names[0]])
    inv = {
        "i1": "char",
        "u1": "uchar",
        "i2": "short",
        "u2": "ushort",
        "i4": "int",
        "u4": "uint",
        "f4": "float",
        "f8": "double",
    }
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    fields = []
    for name in names:
        arr = np.asarray(properties[name])
        if arr.shape != (n,):
            raise ValueError(f"vertex property {name!r} must have shape ({n},), got {arr.shape}")
        code = arr.dtype.str[1:]
        if code not in inv:
            raise ValueError(f"vertex property {name!r} has unsupported dtype {arr.dtype}")
        lines.append(f"property {inv[code]} {name}")
        fields.append((name, "<" + code))
    if faces is not None:
        faces = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    lines.append("end_header")
    rec = np.empty(n, dtype=np.dtype(fields))
    for name in names:
        rec[name] = properties[name]
    body = rec.tobytes()
    if faces is not None:
        frec = np.empty(len(faces), dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
        frec["n"] = 3
        frec["v"] = faces
        body += frec.tobytes()
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(("\n".join(lines) + "\n").encode("ascii") + body)
    tmp.replace(path)
