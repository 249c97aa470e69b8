"""From a saved map to a picture: open the map, colour its mesh, frame it, render, caption.

:func:`open_map` turns every way a map folder can be unusable into one :class:`VizError` line;
:func:`colour_mesh` applies a colour mode (``rgb``, ``region``, ``label``) or a query highlight;
:func:`picture_of_map` does the whole job for ``openfusion render``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from openfusion.mapping import (
    LoadedMap,
    MapFormatError,
    RegionDictionary,
    SurfaceMesh,
    SurfacePoints,
    load_map,
)
from openfusion.mapping.mapfile import MAP_FILE_NAME, resolve_map_path
from openfusion.viz.camera import VirtualCamera, check_image_size, overview_camera
from openfusion.viz.colouring import (
    Colouring,
    QueryHit,
    assign_classes,
    colour_by_label,
    colour_by_query,
    colour_by_region,
    colour_by_rgb,
)
from openfusion.viz.errors import VizError
from openfusion.viz.query import query_text
from openfusion.viz.render import CaptionLine, RenderedImage, draw_caption, outline, render_mesh

logger = logging.getLogger(__name__)

BASE_COLOUR_MODES = ("rgb", "region", "label")
MAX_LEGEND_LINES = 12
#: Front faces closer than this many truncation distances behind a back face are TSDF noise inside
#: a wall (see openfusion.viz.render); skipping them opens the near walls of a room seen from outside.
PEEL_GAP_TRUNCATIONS = 1.25


def open_map(map_dir: str | os.PathLike[str]) -> LoadedMap:
    """Load the map in ``map_dir`` (a map folder: its tile store ``map.ofz/`` or an older
    ``map.ofz.npz``, or that file itself).

    Raises VizError naming the path for: nothing there, a folder without a map file, a file that
    is not an OpenFusion-Z map or is corrupt.
    """
    path = Path(map_dir)
    if not path.exists():
        raise VizError(f"map folder {path} does not exist")
    target = resolve_map_path(path)
    if path.is_dir() and not target.exists():
        raise VizError(f"{path} is not a map folder: it has no {MAP_FILE_NAME} (write one with `openfusion run`)")
    if path.is_file() and path.suffix != ".npz":
        raise VizError(f"{path} is not a map: give the map folder (holding {MAP_FILE_NAME}) or the .npz file")
    try:
        return load_map(path)
    except MapFormatError as exc:
        raise VizError(f"cannot read the map: {exc}") from exc


def region_labels(dictionary: RegionDictionary) -> dict[int, str | None]:
    """key -> label text of every region in the dictionary."""
    return {int(k): dictionary.label(int(k)) for k in dictionary.keys}


def colour_mesh(
    mesh: SurfaceMesh | SurfacePoints,
    dictionary: RegionDictionary,
    *,
    colour: str = "rgb",
    hits: Sequence[QueryHit] | None = None,
    query: str = "",
    class_names: Sequence[str] | None = None,
    text_encoder=None,  # noqa: ANN001 - needed only with class_names
) -> Colouring:
    """The vertex (or point) colours for ``colour`` (``rgb``/``region``/``label``), or, with ``hits``,
    the query highlight over the greyed ``colour`` mode.

    ``class_names`` (with the map's ``text_encoder``) colours by the best-matching class instead
    of the dictionary's label text.
    """
    if colour not in BASE_COLOUR_MODES:
        raise VizError(f"unknown colour mode {colour!r}; use one of {', '.join(BASE_COLOUR_MODES)}")
    if colour == "rgb":
        base = colour_by_rgb(mesh.colors)
    elif colour == "region":
        base = colour_by_region(mesh.keys, labels=region_labels(dictionary))
    else:
        if class_names:
            if text_encoder is None:
                raise VizError("colouring by class needs the map's text encoder")
            names = [str(c).strip() for c in class_names if str(c).strip()]
            if not names:
                raise VizError("the class list is empty")
            class_emb = text_encoder.encode(names)
            labels = assign_classes(dictionary.keys, dictionary.unit_embeddings(), class_emb, names)
            base = colour_by_label(mesh.keys, labels, label_order=names)
            base.title = "best-matching class"
        else:
            base = colour_by_label(mesh.keys, region_labels(dictionary))
    if hits is None:
        return base
    return colour_by_query(mesh.keys, base.colors, hits, query_text=query)


def caption_for(colouring: Colouring, *, map_name: str, mesh: SurfaceMesh, num_regions: int, space: str) -> list[CaptionLine]:
    """Caption lines: the query and its matches, or the legend of the colour mode, or map facts."""
    if colouring.mode == "query":
        text = colouring.title.removeprefix("query: ")
        lines = [CaptionLine(f'"{text}" in {map_name} ({space})')]
        if not colouring.legend:
            lines.append(CaptionLine("no region in this map"))
        for e in colouring.legend:
            label = e.label or "(no label)"
            seen = "" if e.count else "  (not on the mesh)"
            lines.append(CaptionLine(f"#{(e.rank or 0) + 1} {label}  score {e.score:.2f}  key {e.key}{seen}", e.color_rgb))
        return lines
    if colouring.mode == "rgb":
        return [CaptionLine(f"{map_name}: {len(mesh.vertices):,} vertices, {num_regions} regions ({space})")]
    lines = [CaptionLine(f"{map_name}: {colouring.title}")]
    entries = sorted(
        (e for e in colouring.legend if e.count > 0),
        key=lambda e: (e.key is None and e.label in ("(no label)", "(no region)"), -e.count),
    )
    for e in entries[:MAX_LEGEND_LINES]:
        name = e.label or "(no label)"
        if colouring.mode == "region" and e.key is not None:
            name = f"key {e.key} {e.label or ''}".rstrip()
        lines.append(CaptionLine(name, e.color_rgb))
    if len(entries) > MAX_LEGEND_LINES:
        lines.append(CaptionLine(f"... {len(entries) - MAX_LEGEND_LINES} more"))
    return lines


@dataclass
class MapPicture:
    """A rendered picture of a map and what went into it."""

    image: Image.Image
    rendered: RenderedImage
    colouring: Colouring
    mesh: SurfaceMesh
    hits: list[QueryHit] = field(default_factory=list)
    highlight_mask: np.ndarray | None = None  # (h, w) bool: pixels showing a matched region


@dataclass(frozen=True)
class ViewOptions:
    """Where the overview camera stands (see :func:`openfusion.viz.camera.overview_camera`)."""

    width_px: int = 1024
    height_px: int = 768
    up: str = "+z"
    azimuth_deg: float = 235.0
    elevation_deg: float = 55.0
    fov_deg: float = 45.0
    supersample: int = 1


def picture_of_map(
    loaded: LoadedMap,
    *,
    view: ViewOptions | None = None,
    colour: str = "rgb",
    query: str | None = None,
    top_k: int = 1,
    text_encoder=None,  # noqa: ANN001 - a TextEncoder of the map's space (needed for query / classes)
    class_names: Sequence[str] | None = None,
    caption: bool = True,
    map_name: str = "map",
    camera: VirtualCamera | None = None,
) -> MapPicture:
    """Render ``loaded``'s mesh in colour mode ``colour``; with ``query``, highlight its ``top_k`` matches."""
    view = view or ViewOptions()
    check_image_size(view.width_px, view.height_px)
    mesh = loaded.volume.extract_mesh()
    if len(mesh.triangles) == 0:
        raise VizError(f"{map_name} has no surface to render (no integrated geometry)")
    dictionary = loaded.dictionary
    hits: list[QueryHit] | None = None
    if query is not None:
        if text_encoder is None:
            raise VizError("a query needs the map's text encoder")
        if len(dictionary) == 0:
            raise VizError(f"{map_name} has no regions to query (it was mapped without semantics)")
        hits = query_text(dictionary, query, top_k=top_k, text_encoder=text_encoder)
    colouring = colour_mesh(
        mesh, dictionary, colour=colour, hits=hits, query=query or "", class_names=class_names, text_encoder=text_encoder
    )
    if camera is None:
        camera = overview_camera(
            mesh.vertices,
            width_px=view.width_px,
            height_px=view.height_px,
            up=view.up,
            azimuth_deg=view.azimuth_deg,
            elevation_deg=view.elevation_deg,
            fov_deg=view.fov_deg,
        )
    params = loaded.volume.params
    rendered = render_mesh(
        mesh.vertices,
        mesh.triangles,
        colouring.colors,
        camera,
        vertex_normals=mesh.normals,
        supersample=view.supersample,
        peel_gap_m=PEEL_GAP_TRUNCATIONS * params.trunc_voxels * params.voxel_size_m,
    )
    rgb = rendered.rgb
    highlight = None
    if hits:
        hit_keys = np.asarray([h.key for h in hits], np.int64)
        tri_sel = np.isin(mesh.keys, hit_keys)[mesh.triangles].all(axis=1)
        highlight = rendered.mask_of_triangles(tri_sel)
        rgb = outline(rgb, highlight)
        logger.info("query %r: %d highlighted pixels (%.2f%% of the image)", query, int(highlight.sum()), 100 * highlight.mean())
    image = Image.fromarray(rgb, "RGB")
    if caption:
        lines = caption_for(
            colouring, map_name=map_name, mesh=mesh, num_regions=len(dictionary), space=dictionary.embedding_space
        )
        image = draw_caption(image, lines)
    return MapPicture(image, rendered, colouring, mesh, list(hits or []), highlight)
