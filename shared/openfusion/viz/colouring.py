"""Colour the vertices (or points) of a map by what they are: camera colour, region, label, query.

Every function returns a :class:`Colouring`: one RGB per element plus the legend that says what
each colour means (colour -> region key / label / query rank, with element counts). The same
colouring feeds PLY/GLB export, the headless render and the rerun logger, so a colour in a picture
means the same thing as in an exported file.

Modes
    ``rgb``     the fused camera colour of the TSDF.
    ``region``  one colour per region key (:func:`openfusion.viz.palette.key_colors`), grey where none.
    ``label``   one colour per region label (the dictionary's label text, or a class assigned by
                :func:`assign_classes`); regions without a label are grey.
    ``query``   the matched regions in strong colours (best match red) over a grey scene.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from openfusion.viz.palette import (
    UNLABELLED_RGB,
    greyed,
    hex_color,
    highlight_color,
    index_colors,
    key_colors,
)

logger = logging.getLogger(__name__)

COLOUR_MODES = ("rgb", "region", "label", "query")


@dataclass(frozen=True)
class LegendEntry:
    """What one colour means: a region (``key``), a label, or a query rank; ``count`` elements."""

    color_rgb: tuple[int, int, int]
    count: int
    key: int | None = None
    label: str | None = None
    keys: tuple[int, ...] = ()
    rank: int | None = None
    score: float | None = None

    @property
    def color_hex(self) -> str:
        return hex_color(self.color_rgb)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["color_rgb"] = list(self.color_rgb)
        d["color_hex"] = self.color_hex
        d["keys"] = list(self.keys)
        return {k: v for k, v in d.items() if v is not None and v != []}


@dataclass
class Colouring:
    """Per-element colours (N, 3) uint8 and their legend."""

    mode: str
    colors: np.ndarray
    legend: list[LegendEntry] = field(default_factory=list)
    title: str = ""

    def __post_init__(self) -> None:
        if self.mode not in COLOUR_MODES:
            raise ValueError(f"unknown colour mode {self.mode!r}; known: {', '.join(COLOUR_MODES)}")
        colors = np.asarray(self.colors)
        if colors.ndim != 2 or colors.shape[1] != 3 or colors.dtype != np.uint8:
            raise ValueError(f"colors must be (N, 3) uint8, got {colors.dtype} {colors.shape}")

    def to_dict(self) -> dict:
        return {"mode": self.mode, "title": self.title, "entries": [e.to_dict() for e in self.legend]}


@dataclass(frozen=True)
class QueryHit:
    """One ranked region of a query (rank 0 = best)."""

    key: int
    score: float
    label: str | None = None


def _check_keys(keys: np.ndarray) -> np.ndarray:
    keys = np.asarray(keys)
    if keys.ndim != 1 or not np.issubdtype(keys.dtype, np.integer):
        raise ValueError(f"keys must be a 1-D integer array, got {keys.dtype} {keys.shape}")
    return keys.astype(np.int64, copy=False)


def _counts(keys: np.ndarray) -> dict[int, int]:
    uniq, counts = np.unique(keys, return_counts=True)
    return {int(k): int(c) for k, c in zip(uniq, counts, strict=True)}


def colour_by_rgb(colors: np.ndarray) -> Colouring:
    """The TSDF's fused camera colours, unchanged."""
    colors = np.ascontiguousarray(colors, dtype=np.uint8)
    return Colouring("rgb", colors, [], title="camera colour")


def colour_by_region(keys: np.ndarray, *, labels: Mapping[int, str | None] | None = None) -> Colouring:
    """One colour per region key; legend sorted by element count (largest first), then key."""
    keys = _check_keys(keys)
    colors = key_colors(keys)
    counts = _counts(keys)
    labels = labels or {}
    entries = []
    for key, count in sorted(counts.items(), key=lambda kc: (-kc[1], kc[0])):
        if key < 0:
            entries.append(LegendEntry(UNLABELLED_RGB, count, label="(no region)"))
        else:
            rgb = tuple(int(c) for c in key_colors([key])[0])
            entries.append(LegendEntry(rgb, count, key=key, label=labels.get(key)))  # type: ignore[arg-type]
    return Colouring("region", colors, entries, title="region keys")


def colour_by_label(
    keys: np.ndarray,
    region_labels: Mapping[int, str | None],
    *,
    label_order: Sequence[str] | None = None,
) -> Colouring:
    """One colour per label; a region's label comes from ``region_labels`` (key -> label).

    Colours follow ``label_order`` (e.g. the class list given by the user), else the labels sorted
    alphabetically, so the same label set always gets the same colours.
    """
    keys = _check_keys(keys)
    present = sorted({lab for lab in region_labels.values() if lab})
    if label_order is not None:
        order = list(dict.fromkeys(str(x) for x in label_order))
        order += [lab for lab in present if lab not in order]
    else:
        order = present
    label_index = {lab: i for i, lab in enumerate(order)}
    palette = index_colors(np.arange(len(order))) if order else np.zeros((0, 3), np.uint8)
    key_list = sorted(int(k) for k in region_labels)
    # element -> label index via a sorted key table (-1 = no label)
    table_keys = np.asarray(key_list, np.int64)
    table_idx = np.asarray([label_index.get(region_labels[k] or "", -1) for k in key_list], np.int64)
    elem_idx = np.full(len(keys), -1, np.int64)
    if len(table_keys):
        pos = np.clip(np.searchsorted(table_keys, keys), 0, len(table_keys) - 1)
        known = table_keys[pos] == keys
        elem_idx[known] = table_idx[pos[known]]
    colors = np.empty((len(keys), 3), np.uint8)
    colors[:] = UNLABELLED_RGB
    has = elem_idx >= 0
    colors[has] = palette[elem_idx[has]]
    entries = []
    counts = np.bincount(elem_idx[has], minlength=len(order)) if len(order) else np.zeros(0, np.int64)
    for i, lab in enumerate(order):
        region_keys = tuple(k for k in key_list if region_labels[k] == lab)
        entries.append(
            LegendEntry(tuple(int(c) for c in palette[i]), int(counts[i]), label=lab, keys=region_keys)  # type: ignore[arg-type]
        )
    unlabelled = int((~has).sum())
    if unlabelled:
        entries.append(LegendEntry(UNLABELLED_RGB, unlabelled, label="(no label)"))
    return Colouring("label", colors, entries, title="labels")


def colour_by_query(
    keys: np.ndarray,
    base_colors: np.ndarray,
    hits: Sequence[QueryHit],
    *,
    query_text: str = "",
) -> Colouring:
    """Matched regions in strong colours (rank 0 red, then orange, yellow, ...) over a grey scene."""
    keys = _check_keys(keys)
    base_colors = np.asarray(base_colors, dtype=np.uint8)
    if base_colors.shape != (len(keys), 3):
        raise ValueError(f"base_colors must be ({len(keys)}, 3), got {base_colors.shape}")
    colors = greyed(base_colors)
    entries = []
    for rank, hit in enumerate(hits):
        sel = keys == int(hit.key)
        rgb = highlight_color(rank)
        colors[sel] = rgb
        entries.append(
            LegendEntry(rgb, int(sel.sum()), key=int(hit.key), label=hit.label, rank=rank, score=float(hit.score))
        )
        if not sel.any():
            logger.info("query %r: region %d (rank %d) has no surface in this geometry", query_text, hit.key, rank)
    title = f"query: {query_text}" if query_text else "query"
    return Colouring("query", colors, entries, title=title)


def assign_classes(
    region_keys: np.ndarray, region_embeddings: np.ndarray, class_embeddings: np.ndarray, class_names: Sequence[str]
) -> dict[int, str]:
    """Each region's best-matching class name by cosine similarity (all inputs unit-norm rows)."""
    region_embeddings = np.asarray(region_embeddings, np.float32)
    class_embeddings = np.asarray(class_embeddings, np.float32)
    if len(class_names) != len(class_embeddings):
        raise ValueError(f"{len(class_names)} class names but {len(class_embeddings)} class embeddings")
    if len(region_keys) == 0:
        return {}
    if len(class_names) == 0:
        raise ValueError("need at least one class name")
    if region_embeddings.shape[1] != class_embeddings.shape[1]:
        raise ValueError(
            f"region embeddings have dimension {region_embeddings.shape[1]}, classes {class_embeddings.shape[1]}"
        )
    best = (region_embeddings @ class_embeddings.T).argmax(axis=1)
    return {int(k): str(class_names[int(b)]) for k, b in zip(region_keys, best, strict=True)}


def legend_markdown(colouring: Colouring) -> str:
    """The legend as a markdown table (colour, key, label, rank/score, count)."""
    lines = [f"# Legend: {colouring.title or colouring.mode}", ""]
    if not colouring.legend:
        lines.append("Colours are the fused camera colours (no legend).")
        return "\n".join(lines) + "\n"
    lines += ["| colour | key(s) | label | rank | score | elements |", "|---|---|---|---|---|---|"]
    for e in colouring.legend:
        keys = str(e.key) if e.key is not None else ", ".join(str(k) for k in e.keys)
        rank = "" if e.rank is None else str(e.rank + 1)
        score = "" if e.score is None else f"{e.score:.3f}"
        label = (e.label or "").replace("|", "\\|")
        lines.append(f"| `{e.color_hex}` | {keys} | {label} | {rank} | {score} | {e.count} |")
    return "\n".join(lines) + "\n"
