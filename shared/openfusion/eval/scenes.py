"""Scene specs of the evaluation (``synthetic:seed=1``, ``synthetic:building,rooms=3``, ``scannet:PATH``)
and their sources + ground truth.

A building scene (``synthetic:building[,seed=N,rooms=N,route=A-B,revisit=N,frames=N,width=W,height=H,
noise=0|1]``) walks its route at its own frame density unless the scene sets ``frames=``: the
evaluation's ``--frames`` (frames of one lap of a room) does not apply to it."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from openfusion.errors import UserError
from openfusion.eval.ground_truth import GroundTruth, load_scannet_ground_truth, synthetic_ground_truth

logger = logging.getLogger(__name__)

SCENE_KINDS = ("synthetic", "scannet")
_SYNTHETIC_OPTIONS = {"seed", "frames", "width", "height", "noise"}
_BUILDING_OPTIONS = _SYNTHETIC_OPTIONS | {"rooms", "route", "revisit"}
#: The options key that marks a building scene (``synthetic:building``).
_WORLD = "world"



class SceneError(UserError, ValueError):
    """A scene spec that cannot be evaluated: unknown kind, bad options, a missing folder or mesh."""


@dataclass(frozen=True)
class SceneSpec:
    """One scene to evaluate. ``options`` are per-scene overrides (``frames``, ``width``, ...)."""

    kind: str
    seed: int = 0
    path: str | None = None
    options: dict[str, str] = field(default_factory=dict)

    @property
    def is_building(self) -> bool:
        return self.kind == "synthetic" and self.options.get(_WORLD) == "building"

    @property
    def name(self) -> str:
        if self.is_building:
            extra = "".join(f",{k}={self.options[k]}" for k in ("rooms", "route", "revisit") if k in self.options)
            return f"synthetic:building,seed={self.seed}{extra}"
        if self.kind == "synthetic":
            return f"synthetic:seed={self.seed}"
        return f"scannet:{Path(self.path or '').name}"


def parse_scene_specs(texts: Iterable[str]) -> list[SceneSpec]:
    """Parse ``synthetic:seed=1,synthetic:seed=2`` / ``scannet:PATH`` lists.

    Items are separated by commas or given as separate arguments; a comma item without a
    ``kind:`` prefix (``frames=20``) is one more option of the synthetic scene before it.
    Raises ValueError naming the bad item.
    """
    raw: list[tuple[str, str, dict[str, str]]] = []
    for text in texts:
        for item in (t.strip() for t in str(text).split(",")):
            if not item:
                continue
            kind, sep, rest = item.partition(":")
            if sep and kind in SCENE_KINDS:
                if kind == "scannet":
                    if not rest:
                        raise SceneError(
                            "scene 'scannet:' needs a path: scannet:/data/scannet/scans/scene0000_00"
                        )
                    raw.append((kind, rest, {}))
                elif rest.strip().lower() == "building":
                    raw.append((kind, "", {_WORLD: "building"}))
                else:
                    raw.append((kind, "", _parse_options(item, rest)))
            elif kind == "synthetic" and not sep:
                raw.append(("synthetic", "", {}))
            elif "=" in item and not sep and raw and raw[-1][0] == "synthetic":
                raw[-1][2].update(_parse_options(item, item))
            else:
                raise SceneError(
                    f"bad scene {item!r}: expected synthetic[:seed=N] or scannet:PATH (known kinds: {', '.join(SCENE_KINDS)})"
                )
    specs = []
    for kind, path, opts in raw:
        if kind == "synthetic" and opts.get(_WORLD) == "building":
            specs.append(_building_spec(opts))
        elif kind == "synthetic":
            unknown = set(opts) - _SYNTHETIC_OPTIONS
            if unknown:
                raise SceneError(
                    f"unknown synthetic scene option(s) {sorted(unknown)}; known: {sorted(_SYNTHETIC_OPTIONS)}"
                )
            try:
                seed = int(opts.pop("seed", "0"))
                for k in ("frames", "width", "height"):
                    if k in opts and int(opts[k]) <= 0:
                        raise SceneError(f"{k} must be positive")
            except ValueError as exc:
                raise SceneError(f"bad synthetic scene options {opts}: {exc}") from exc
            specs.append(SceneSpec("synthetic", seed=seed, options=opts))
        else:
            specs.append(SceneSpec("scannet", path=path))
    if not specs:
        raise SceneError("no scenes given")
    names = [s.name for s in specs]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise SceneError(f"scene(s) given twice: {dupes}")
    return specs


def _building_spec(opts: dict[str, str]) -> SceneSpec:
    from openfusion.sources.synthetic_spec import synthetic_options  # light: not the world

    given = {k: v for k, v in opts.items() if k != _WORLD}
    unknown = set(given) - _BUILDING_OPTIONS
    if unknown:
        raise SceneError(f"unknown synthetic:building scene option(s) {sorted(unknown)}; known: {sorted(_BUILDING_OPTIONS)}")
    try:
        synthetic_options(given, world="building")
    except ValueError as exc:
        raise SceneError(f"bad synthetic:building scene options: {exc}") from None
    return SceneSpec("synthetic", seed=int(given.pop("seed", "0")), options={_WORLD: "building", **given})


def _parse_options(item: str, text: str) -> dict[str, str]:
    out = {}
    for part in (p for p in text.split(",") if p):
        key, eq, value = part.partition("=")
        if not eq or not key.strip() or not value.strip():
            raise SceneError(f"bad scene option {part!r} in {item!r}: expected key=value")
        out[key.strip()] = value.strip()
    return out


def check_scene_inputs(specs: Iterable[SceneSpec]) -> None:
    """Cheap up-front checks (before any model loads): ScanNet folders exist and hold their GT mesh."""
    for spec in specs:
        if spec.kind != "scannet":
            continue
        path = Path(spec.path or "")
        if not path.is_dir():
            raise SceneError(f"{spec.name}: scene folder {path} does not exist")
        if not list(path.glob("*_vh_clean_2.labels.ply")):
            raise SceneError(
                f"{spec.name}: no <scene>_vh_clean_2.labels.ply ground-truth mesh in {path} "
                "(copy it from the ScanNet release next to the exported frames)"
            )


@dataclass
class OpenedScene:
    """A scene's frame source and its ground truth."""

    spec: SceneSpec
    source: object  # openfusion.sources FrameSource
    ground_truth: GroundTruth
    depth_min_m: float


def open_scene(
    spec: SceneSpec,
    *,
    frames: int,
    width_px: int,
    height_px: int,
    gt_spacing_m: float,
) -> OpenedScene:
    """Build the scene's frame source (at most ``frames`` frames) and load its ground truth.

    Synthetic scenes render one full camera lap in ``frames`` frames at ``width_px`` x
    ``height_px`` with Kinect-like depth noise (``noise=0`` turns depth noise off). ScanNet
    scenes use every k-th frame so that ``frames`` frames span the whole scan.
    """
    if spec.is_building:
        from openfusion.sources.synthetic import DEPTH_MIN_M, BuildingSource, SyntheticBuilding
        from openfusion.sources.synthetic_spec import DEFAULT_ROOMS, synthetic_options

        opts = synthetic_options({k: v for k, v in spec.options.items() if k != _WORLD}, world="building")
        building = SyntheticBuilding(spec.seed, rooms=opts.get("rooms", DEFAULT_ROOMS))
        source = BuildingSource(
            building,
            opts.get("num_frames"),
            opts.get("width_px", width_px),
            opts.get("height_px", height_px),
            route=opts.get("route"),
            revisit=opts.get("revisit"),
            depth_noise=opts.get("depth_noise", True),
        )
        gt = synthetic_ground_truth(building, spacing_m=gt_spacing_m, source=spec.name)
        logger.info("%s: %d frames over %.0f m^2 of floor", spec.name, len(source), building.floor_area_m2)
        return OpenedScene(spec, source, gt, depth_min_m=DEPTH_MIN_M)
    if spec.kind == "synthetic":
        from openfusion.sources.synthetic import DEPTH_MIN_M, SyntheticSource, SyntheticWorld

        n = int(spec.options.get("frames", frames))
        w = int(spec.options.get("width", width_px))
        h = int(spec.options.get("height", height_px))
        depth_noise = spec.options.get("noise", "1") not in ("0", "false")
        world = SyntheticWorld(spec.seed)
        source = SyntheticSource(world, n, w, h, depth_noise=depth_noise, frames_per_lap=max(n, 2))
        gt = synthetic_ground_truth(world, spacing_m=gt_spacing_m, source=spec.name)
        return OpenedScene(spec, source, gt, depth_min_m=DEPTH_MIN_M)
    if spec.kind == "scannet":
        from openfusion.sources.scannet import ScanNetSource

        path = Path(spec.path or "")
        gt = load_scannet_ground_truth(path)  # fails first and clearly when the GT mesh is missing
        total = len(ScanNetSource(path))
        stride = max(1, math.ceil(total / max(frames, 1)))  # spread the frames over the whole scan
        source = ScanNetSource(path, stride=stride, max_frames=frames)
        logger.info(
            "%s: %d frames in the scan, using every %d-th (at most %d)", spec.name, total, stride, frames
        )
        return OpenedScene(spec, source, gt, depth_min_m=0.1)
    raise SceneError(f"unknown scene kind {spec.kind!r}")
