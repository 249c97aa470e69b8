"""Optional live view with the rerun viewer (``pip install 'openfusion-z[viz]'`` for rerun-sdk).

A :class:`RerunLogger` sends what the pipeline sees to one sink:

- ``save:FILE.rrd``  write a recording file (open it later with ``rerun FILE.rrd``);
- ``spawn``          start a local viewer window and stream to it (needs a display);
- ``serve`` / ``serve:PORT``  host a gRPC server in this process; a viewer elsewhere connects with
  ``rerun --connect rerun+http://HOST:PORT/proxy`` (default port 9876);
- ``connect:URL``    push to a viewer that is already running (``rerun+http://host:9876/proxy``).

Entities (world frame = the map's frame, metres; timeline ``frame`` = frame id, ``time`` = stamp):

- ``world/camera``: the camera pose (``Transform3D`` of ``T_world_cam``), with ``Pinhole`` (OpenCV
  axes, RDF), ``image`` (RGB), ``depth`` (``DepthImage``, metres) and ``instances`` (when the frame
  has a ground-truth instance image);
- ``world/trajectory``: the camera path so far;
- ``world/map/mesh``: the mesh (:meth:`RerunLogger.log_mesh`), camera colours or per-region colours;
- ``world/map/regions``: surface points coloured by region key, labelled through an annotation
  context (hover shows key and label);
- ``world/query/...``: query matches (:meth:`RerunLogger.log_query`) in the highlight colours, with
  bounding boxes; the query text goes to ``log/queries``.

Pipeline hooks: ``log_frame(frame)``, ``log_mesh(mesh)``, ``log_query(reply)`` (or ``(text, results)``);
:meth:`RerunLogger.frame_hook` returns an ``on_frame(frame, stats)`` callback for
``openfusion.mapping.pipeline.map_scene`` that logs every frame and, every ``mesh_every`` frames, the mesh.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from openfusion.frame import Frame
from openfusion.mapping import SurfaceMesh, SurfacePoints
from openfusion.viz.errors import MissingDependencyError, VizError
from openfusion.viz.palette import highlight_color, key_colors

logger = logging.getLogger(__name__)

DEFAULT_SERVE_PORT = 9876
MAX_TRAJECTORY_POINTS = 4000
MAX_CLASS_ID = 65535  # rerun class ids are uint16


@dataclass(frozen=True)
class RerunSink:
    """A parsed ``--rerun`` value."""

    kind: str  # "save" | "spawn" | "serve" | "connect"
    path: Path | None = None
    port: int | None = None
    url: str | None = None


def parse_sink(spec: str) -> RerunSink:
    """Parse ``save:FILE.rrd``, ``spawn``, ``serve[:PORT]`` or ``connect:URL``; VizError otherwise."""
    text = str(spec).strip()
    kind, sep, arg = text.partition(":")
    kind = kind.lower()
    if kind == "save":
        if not arg:
            raise VizError("rerun sink save:FILE needs a file name, e.g. save:run.rrd")
        path = Path(arg)
        if path.suffix != ".rrd":
            raise VizError(f"rerun recordings are .rrd files, got {arg!r}")
        if not path.parent.is_dir():
            raise VizError(f"cannot write the rerun recording {path}: folder {path.parent} does not exist")
        return RerunSink("save", path=path)
    if kind == "spawn" and not sep:
        return RerunSink("spawn")
    if kind == "serve":
        if not sep:
            return RerunSink("serve", port=DEFAULT_SERVE_PORT)
        try:
            port = int(arg)
        except ValueError:
            port = -1
        if not 1 <= port <= 65535:
            raise VizError(f"rerun sink serve:PORT needs a port 1-65535, got {arg!r}")
        return RerunSink("serve", port=port)
    if kind == "connect" and arg:
        return RerunSink("connect", url=arg)
    raise VizError(f"unknown rerun sink {spec!r}; use save:FILE.rrd, spawn, serve[:PORT] or connect:URL")


def _import_rerun() -> Any:
    try:
        import rerun
    except ImportError as exc:
        raise MissingDependencyError("rerun-sdk", "rerun logging") from exc
    return rerun


def rerun_available() -> bool:
    """True when rerun-sdk can be imported."""
    try:
        _import_rerun()
    except MissingDependencyError:
        return False
    return True


class RerunLogger:
    """Logs frames, trajectory, mesh, regions and queries to a rerun sink (module docstring).

    ``image_every`` logs the RGB/depth images of every k-th frame only (poses are always logged).
    Use as a context manager or call :meth:`close` so a ``save:`` recording is complete on disk.
    """

    def __init__(
        self,
        sink: str | RerunSink,
        *,
        application_id: str = "openfusion-z",
        recording_id: str | None = None,
        image_every: int = 1,
        log_depth: bool = True,
    ) -> None:
        if image_every < 1:
            raise VizError(f"image_every must be >= 1, got {image_every}")
        self.sink = sink if isinstance(sink, RerunSink) else parse_sink(sink)
        rr = _import_rerun()
        self._rr = rr
        self.image_every = int(image_every)
        self.log_depth = log_depth
        self.stream = rr.RecordingStream(application_id, recording_id=recording_id)
        self.server_url: str | None = None
        self._open_sink()
        self._positions: list[np.ndarray] = []
        self._frames = 0
        self._closed = False
        self.stream.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    def _open_sink(self) -> None:
        s = self.sink
        try:
            if s.kind == "save":
                self.stream.save(str(s.path))
            elif s.kind == "spawn":
                self.stream.spawn()
            elif s.kind == "serve":
                self.server_url = self.stream.serve_grpc(grpc_port=s.port)
                logger.info("rerun: serving at %s (connect a viewer with: rerun --connect %s)", self.server_url, self.server_url)
            else:
                self.stream.connect_grpc(s.url)
        except (RuntimeError, OSError, ValueError) as exc:
            first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise VizError(f"cannot open the rerun sink {s.kind}: {first_line}") from exc

    # ------------------------------------------------------------------ context
    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Flush everything to the sink (the .rrd file is complete afterwards) and disconnect."""
        if self._closed:
            return
        self._closed = True
        self._log_trajectory()
        self.stream.flush()
        self.stream.disconnect()

    def _check_open(self) -> None:
        if self._closed:
            raise VizError("this RerunLogger is closed")

    # ------------------------------------------------------------------ frames
    def set_frame_time(self, frame_id: int, stamp_ns: int | None = None) -> None:
        self.stream.set_time("frame", sequence=int(frame_id))
        if stamp_ns is not None:
            self.stream.set_time("time", duration=int(stamp_ns) * 1e-9)

    def log_frame(self, frame: Frame) -> None:
        """Camera pose, pinhole, images (every ``image_every``-th frame) and the trajectory."""
        self._check_open()
        rr = self._rr
        self.set_frame_time(frame.frame_id, frame.stamp_ns)
        T = np.asarray(frame.T_world_cam, np.float64)
        self.stream.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        intr = frame.intrinsics
        self.stream.log(
            "world/camera",
            rr.Pinhole(
                image_from_camera=intr.K,
                resolution=[intr.width_px, intr.height_px],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.3,
            ),
        )
        if self._frames % self.image_every == 0:
            self.stream.log("world/camera/image", rr.Image(np.ascontiguousarray(frame.color)))
            if self.log_depth:
                self.stream.log("world/camera/depth", rr.DepthImage(frame.depth_m(), meter=1.0))
            if frame.instance is not None:
                self.stream.log("world/camera/instances", rr.SegmentationImage(np.asarray(frame.instance, np.int32)))
        self._positions.append(T[:3, 3].copy())
        self._frames += 1
        if self._frames % 10 == 0:
            self._log_trajectory()

    def _log_trajectory(self) -> None:
        if len(self._positions) < 2:
            return
        pts = np.asarray(self._positions)
        if len(pts) > MAX_TRAJECTORY_POINTS:
            pts = pts[np.linspace(0, len(pts) - 1, MAX_TRAJECTORY_POINTS).round().astype(int)]
        self.stream.log("world/trajectory", self._rr.LineStrips3D([pts], colors=[(255, 140, 0)], radii=0.01))

    # ------------------------------------------------------------------ map
    def log_mesh(self, mesh: SurfaceMesh, *, colour: str = "rgb", entity: str = "world/map/mesh") -> None:
        """The map's mesh with camera colours (``rgb``) or one colour per region key (``region``)."""
        self._check_open()
        if colour not in ("rgb", "region"):
            raise VizError(f"rerun mesh colour must be 'rgb' or 'region', got {colour!r}")
        if len(mesh.triangles) == 0:
            logger.debug("rerun: empty mesh not logged")
            return
        colors = mesh.colors if colour == "rgb" else key_colors(mesh.keys)
        self.stream.log(
            entity,
            self._rr.Mesh3D(
                vertex_positions=np.asarray(mesh.vertices, np.float32),
                triangle_indices=np.asarray(mesh.triangles, np.uint32),
                vertex_normals=np.asarray(mesh.normals, np.float32),
                vertex_colors=np.asarray(colors, np.uint8),
            ),
        )

    def log_regions(
        self, points: SurfacePoints, *, labels: dict[int, str | None] | None = None, entity: str = "world/map/regions"
    ) -> None:
        """Surface points coloured by region key; keys and labels shown on hover (annotation context)."""
        self._check_open()
        rr = self._rr
        keys = np.asarray(points.keys, np.int64)
        labelled = keys >= 0
        pts = np.asarray(points.points, np.float32)[labelled]
        keys = keys[labelled]
        if len(pts) == 0:
            return
        uniq = np.unique(keys)
        colors = key_colors(keys)
        if uniq.max() <= MAX_CLASS_ID:
            labels = labels or {}
            infos = []
            for k, rgb in zip(uniq, key_colors(uniq), strict=True):
                text = f"key {int(k)}" + (f": {labels[int(k)]}" if labels.get(int(k)) else "")
                infos.append(rr.AnnotationInfo(id=int(k), label=text, color=tuple(int(c) for c in rgb)))
            self.stream.log(entity, rr.AnnotationContext(infos), static=True)
            self.stream.log(entity, rr.Points3D(pts, class_ids=keys.astype(np.uint16), colors=colors, radii=0.01))
        else:
            self.stream.log(entity, rr.Points3D(pts, colors=colors, radii=0.01))

    def log_query(
        self,
        query: Any,
        results: Sequence[Any] | None = None,
        *,
        points: SurfacePoints | None = None,
        entity: str = "world/query",
    ) -> None:
        """Matches of a query: each region's points in its rank's highlight colour, its bounding box,
        and a text log line; the previous query's entities are cleared.

        Call as ``log_query(reply)`` with a :class:`openfusion.wire.schemas.QueryReply` (``.query``,
        ``.regions``) or ``log_query(text, results)`` with :class:`openfusion.mapping.RegionResult`
        or :class:`~openfusion.viz.colouring.QueryHit` items. A region's points come from
        ``result.points`` when present, else from ``points`` (the map's surface points); its box
        from ``bbox_min``/``bbox_max`` when finite, else from its points.
        """
        self._check_open()
        if results is None:
            if not hasattr(query, "regions"):
                raise VizError("log_query needs a QueryReply, or the query text and its results")
            text, results = str(getattr(query, "query", "")), list(query.regions)
        else:
            text = str(query)
        rr = self._rr
        self.stream.log(entity, rr.Clear(recursive=True))
        lines = []
        for rank, res in enumerate(results):
            key, score, label = int(res.key), float(res.score), getattr(res, "label", None)
            rgb = highlight_color(rank)
            pts = getattr(res, "points", None)
            if pts is None and points is not None:
                pts = np.asarray(points.points)[np.asarray(points.keys) == key]
            name = f"{entity}/{rank + 1}"
            caption = f"#{rank + 1} {label or '(no label)'} {score:.2f}"
            lo = np.asarray(getattr(res, "bbox_min", np.full(3, np.nan)), np.float32)
            hi = np.asarray(getattr(res, "bbox_max", np.full(3, np.nan)), np.float32)
            if pts is not None and len(pts):
                pts = np.asarray(pts, np.float32)
                self.stream.log(f"{name}/points", rr.Points3D(pts, colors=[rgb], radii=0.015))
                if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
                    lo, hi = pts.min(axis=0), pts.max(axis=0)
            if np.isfinite(lo).all() and np.isfinite(hi).all():
                self.stream.log(f"{name}/box", rr.Boxes3D(mins=[lo], sizes=[hi - lo], colors=[rgb], labels=[caption]))
            lines.append(f"{caption} (key {key})")
        summary = f"query {text!r}: " + ("; ".join(lines) if lines else "no region")
        self.stream.log("log/queries", rr.TextLog(summary, level="INFO"))

    def log_map(self, volume: Any, dictionary: Any, *, mesh_colour: str = "rgb", max_points: int = 200_000) -> None:
        """A whole map: its mesh and its region points (labels from the dictionary)."""
        self.log_mesh(volume.extract_mesh(), colour=mesh_colour)
        labels = {int(k): dictionary.label(int(k)) for k in dictionary.keys}
        self.log_regions(volume.extract_points(max_points=max_points), labels=labels)

    # ------------------------------------------------------------------ pipeline hook
    def frame_hook(
        self, *, mesh_source: Callable[[], SurfaceMesh] | None = None, mesh_every: int = 0
    ) -> Callable[[Frame, Any], None]:
        """An ``on_frame(frame, stats)`` callback: logs each frame and, every ``mesh_every`` frames
        (0 = never), the mesh returned by ``mesh_source``."""
        if mesh_every < 0:
            raise VizError(f"mesh_every must be >= 0, got {mesh_every}")
        if mesh_every and mesh_source is None:
            raise VizError("mesh_every needs a mesh_source")
        count = 0

        def on_frame(frame: Frame, _stats: Any = None) -> None:
            nonlocal count
            self.log_frame(frame)
            count += 1
            if mesh_every and count % mesh_every == 0 and mesh_source is not None:
                self.log_mesh(mesh_source())

        return on_frame


__all__ = [
    "DEFAULT_SERVE_PORT",
    "RerunLogger",
    "RerunSink",
    "parse_sink",
    "rerun_available",
]
