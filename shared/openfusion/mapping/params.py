"""Parameters of the map core, each declared once: default, unit (in the name), limits and help.

:class:`VolumeParams` (the semantic TSDF volume and its update rule) and :class:`MatchParams`
(region matching and the planned update) are config sections (:class:`openfusion.config.ConfigSection`):
the geometry service's config section *is* a ``VolumeParams`` plus its own service settings, the
semantic service's *is* a ``MatchParams`` plus its own, and the in-process pipeline and the
evaluation build the same models. So a parameter's default, limits and help text exist in one
place, and config files (``[geometry] voxel_size_m = 0.02``), ``OPENFUSION_GEOMETRY__VOXEL_SIZE_M``,
command-line flags (``--voxel-size-m``) and ``openfusion config --show geometry`` all derive from
these fields. :class:`MergeParams` (when regions that are one object merge) extends the semantic
service's section too. :class:`QueryParams` (how ranked regions are chosen) is the query service's section
base and what ``openfusion query --map-dir`` and the in-process run use, so a saved map and a
running map leave out the same regions.
"""

from __future__ import annotations

import re
from typing import Any, Literal, Self

from pydantic import ConfigDict, Field, field_validator, model_validator

from openfusion.config import ConfigSection
from openfusion.wire.keys import ShardId

_DEVICE_RE = re.compile(r"^(CPU|CUDA):(\d+)$")

WhenFull = Literal["raise", "drop_new"]


def normalise_device(device: str) -> str:
    """Return an Open3D device string ``"CPU:0"`` / ``"CUDA:n"``; accepts ``cpu``, ``cuda``, ``cuda:1``."""
    text = str(device).strip().upper()
    if text in ("CPU", "CUDA"):
        text += ":0"
    if not _DEVICE_RE.match(text):
        raise ValueError(f"device must be 'CPU:0' or 'CUDA:<n>', got {device!r}")
    return text


class SectionParams(ConfigSection):
    """Base of a parameter model that a service's config section extends (the volume's and the
    join's the geometry service's, matching, merging and selection the semantic service's, the
    query's the query service's): the section carries them, the library takes the model."""

    @classmethod
    def from_section(cls, section: ConfigSection) -> Self:
        """This model's parameters of a config section that extends it."""
        return cls.model_validate({name: getattr(section, name) for name in cls.model_fields})

    @classmethod
    def from_pairs(cls, pairs: list[str]) -> Self:
        """This model from ``FIELD=VALUE`` strings (a bench's command line), each value parsed as
        the field declares it; an empty value is none, as with ``--set``. ValueError for a pair
        without ``=``; pydantic's ValidationError names a bad field or value."""
        values: dict[str, str | None] = {}
        for pair in pairs:
            if "=" not in pair:
                raise ValueError(f"expected FIELD=VALUE, got {pair!r}")
            name, value = pair.split("=", 1)
            values[name.strip()] = value.strip() or None
        return cls.model_validate(values)


class VolumeParams(SectionParams):
    """Geometry and semantic-fusion parameters of a :class:`~openfusion.mapping.SemanticVolume`."""

    model_config = ConfigDict(allow_inf_nan=False)

    voxel_size_m: float = Field(0.02, gt=0, le=1.0, description="voxel edge length")
    block_resolution: int = Field(8, ge=2, le=32, description="voxels per block edge (Open3D blocks of resolution^3)")
    trunc_voxels: float = Field(
        4.0, gt=0, description="TSDF truncation distance in voxels (paper: 4; Open3D's own default is 8)"
    )
    depth_min_m: float = Field(0.1, ge=0, description="depth below this is ignored")
    depth_max_m: float = Field(6.0, gt=0, description="depth beyond this is ignored")
    initial_block_count: int = Field(
        16384,
        ge=1,
        description=(
            "blocks allocated at start without a memory budget: 16384 blocks of 8^3 voxels x 16 B = 128 MiB, a "
            "furnished room at 2 cm (the grid doubles when full)"
        ),
    )
    memory_budget_mb: float | None = Field(
        None,
        gt=0,
        description="resident voxel memory in MiB (none = everything stays resident): the grid is allocated once at "
        "this size and the least recently observed tiles are paged out to the tile store, and back in when seen again",
    )
    tile_blocks: int = Field(
        8, ge=1, le=64, description="blocks per tile edge: tiles are what is paged, checkpointed and stored (8: 1.28 m)"
    )
    max_blocks: int | None = Field(
        None, ge=1, description="block budget; none = grow. A frame needing more is refused or clipped (when_full)"
    )
    when_full: WhenFull = Field(
        "raise",
        description="over max_blocks: 'raise' refuses the frame (nothing written, counted), "
        "'drop_new' integrates into already allocated blocks only",
    )
    min_weight: float = Field(
        1.0, gt=0, description="depth observations a voxel needs to count as surface (render, update, read-out)"
    )
    conf_history_weight: float = Field(
        3.0,
        ge=0,
        description="weight w of a voxel's stored confidence against one new observation (update rule): same key "
        "(w*conf + c)/(w+1); another key removes c/(w+1) and takes the voxel when that uses it up",
    )
    update_min_width_px: int = Field(
        160,
        ge=0,
        le=4096,
        description="semantic update: key and confidence maps narrower than this are enlarged by the smallest whole "
        "factor that reaches it (nearest neighbour) before the update's rays are cast, so that each voxel of the "
        "surface in view gets a ray (an encoder's quarter-size maps of a 320x240 frame are 80 wide, one ray per "
        "1.5 voxels at 2 m with 2 cm voxels); 0 = the maps' own size",
    )
    label_fill_radius_m: float = Field(
        0.06,
        ge=0,
        description="read-out: an unlabelled surface point takes the key of the nearest same-facing labelled point "
        "within this distance (thin structures the encoder-sized view misses); 0 = off",
    )
    label_vote_radius_m: float = Field(
        0.045,
        ge=0,
        description="read-out: a labelled surface point takes the key most of the same-facing labelled points "
        "within this distance hold (itself included) when more of them hold it than hold its own; 0 = off",
    )
    device: str = Field("CPU:0", description="Open3D device of the volume: CPU:0 or CUDA:<n>")
    shard: str = Field(
        "0/1", description="geometry shard I/N: this volume integrates only the blocks of the tiles shard I of N owns "
        "(docs/SHARDS.md); 0/1 = the whole map"
    )

    @field_validator("device")
    @classmethod
    def _device(cls, value: str) -> str:
        return normalise_device(value)

    @field_validator("shard")
    @classmethod
    def _shard(cls, value: str) -> str:
        try:
            return str(ShardId.parse(value))
        except ValueError as exc:
            raise ValueError(str(exc)) from None

    @model_validator(mode="after")
    def _depth_range(self) -> VolumeParams:
        if self.depth_max_m <= self.depth_min_m:
            raise ValueError(f"depth_max_m ({self.depth_max_m}) must exceed depth_min_m ({self.depth_min_m})")
        return self

    @model_validator(mode="after")
    def _readout_fits_the_halo(self) -> VolumeParams:
        # Read-outs go chunk by chunk with a one-block halo (tile summaries, paged maps, queries).
        # A point's key depends on its vote neighbours within the vote radius, each of whose keys
        # depends on the fill within the fill radius; the halo's outermost voxel layer lacks the
        # neighbours Open3D reads. So the two radii and one voxel must fit in one block, or the
        # chunked read-outs differ from the whole map's near tile borders (measured at 8 cm
        # blocks with the default radii: 3 points of 255,033 in another region).
        reach_m = self.label_fill_radius_m + self.label_vote_radius_m + self.voxel_size_m
        if reach_m > self.block_size_m + 1e-9:
            raise ValueError(
                f"label_fill_radius_m ({self.label_fill_radius_m}) + label_vote_radius_m "
                f"({self.label_vote_radius_m}) + voxel_size_m ({self.voxel_size_m}) = {reach_m:.4g} m exceeds one "
                f"block ({self.block_resolution} voxels x {self.voxel_size_m} m = {self.block_size_m:.4g} m): "
                "read-outs chunk by chunk (region summaries, paged maps) would differ from the whole map's near "
                "tile borders; lower the radii or raise block_resolution"
            )
        return self

    @property
    def shard_id(self) -> ShardId:
        """:attr:`shard` parsed (:class:`~openfusion.wire.keys.ShardId`)."""
        return ShardId.parse(self.shard)

    @property
    def trunc_m(self) -> float:
        """TSDF truncation distance in metres."""
        return self.trunc_voxels * self.voxel_size_m

    @property
    def block_size_m(self) -> float:
        """Edge length of one block in metres."""
        return self.block_resolution * self.voxel_size_m

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form (for map files)."""
        return {name: getattr(self, name) for name in VolumeParams.model_fields}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> VolumeParams:
        """Inverse of :meth:`to_dict`; unknown keys are refused so a typo is not silently ignored."""
        return cls.model_validate(data)

    def with_changes(self, **changes: Any) -> VolumeParams:
        """A validated copy with ``changes`` (e.g. another ``device`` for a loaded map)."""
        return VolumeParams.model_validate({**self.to_dict(), **changes})


class MatchParams(SectionParams):
    """How a frame's regions are matched to the map's and turned into a planned update
    (:func:`openfusion.mapping.matching.plan_update`; the soft IoU, the assignment and the
    mask-edge weighting are described in that module)."""

    model_config = ConfigDict(allow_inf_nan=False)

    min_iou: float = Field(0.10, ge=0, le=1, description="assigned pairs below this soft IoU count as new regions")
    min_pixel_conf: float = Field(
        0.05, ge=0, le=1, description="a pixel whose best region confidence is below this takes no region"
    )
    # A settled key refuses a region it disagrees with (docs/EVAL.md, "A settled key refuses"): under
    # noisy masks a floor key that spilled onto a wall went on matching the wall's masks by overlap and
    # took the wall (45,685 points on bench room 2); gating every key, young ones too, cost 0.001-0.033.
    min_embedding_cos: float | None = Field(
        0.6, ge=-1, le=1, description="a pair may match only when its embeddings agree this much, for keys settled "
        "by min_embedding_cos_views views (a cosine in the encoder's space; none = geometry only, as in the paper)"
    )
    min_embedding_cos_views: int = Field(
        3, ge=0, le=1000, description="min_embedding_cos judges only keys whose embedding averages at least this many "
        "views; a younger key is matched by geometry alone (0 = every key)"
    )
    mask_edge_px: float = Field(
        2.0, ge=0, description="planned confidences fall off within this many pixels of a region border (0 = off)"
    )
    depth_cut_rel: float = Field(
        0.05,
        ge=0,
        description="depth-edge cut: rendered neighbours whose depths differ by more than this share of the nearer "
        "lie on different surfaces; a pixel within mask_edge_px of its region's border that such an edge (or a "
        "crease, crease_rel) cuts off from the region's interior fuses nothing where the map holds another region "
        "(a mask spilled over an occlusion edge or around a corner); 0 = off",
    )
    crease_rel: float = Field(
        0.01,
        ge=0,
        description="depth-edge cut: also a crease where the rendered inverse depth's slope changes across a pixel "
        "pair by more than this share of the inverse depth (planes have linear inverse depth); 0 = jumps only",
    )
    depth_cut_new_rel: float = Field(
        0.10,
        ge=0,
        description="depth-edge cut on surface the map has not labelled yet: a cut-off border pixel fuses nothing "
        "there when it lies behind its mask's body across an occlusion edge, farther than the body's surface "
        "(extrapolated) predicts by more than this share (a foreground mask dilated over the background behind "
        "it); 0 = cut only where the map holds another region",
    )
    split_min_share: float | None = Field(
        0.15,
        ge=0,
        le=1,
        description="split a frame region along the map: where it covers most (split_min_cover) of a map region no "
        "frame region matched, over at least this share of its own pixels, and that region's embedding disagrees "
        "with the key it matched (cosine below split_max_cos), those pixels fuse that region's key (a mask that "
        "merged two objects); none = off",
    )
    split_min_cover: float = Field(
        0.5, ge=0, le=1, description="split: share of the unmatched map region's rendered pixels the frame region covers"
    )
    split_max_cos: float = Field(
        0.85, ge=-1, le=1, description="split: the two map regions' embeddings must agree less than this (other objects)"
    )
    contested_margin: bool = Field(
        True,
        description="a pixel's planned confidence is its best region's minus the runner-up's there (pixels two "
        "frame regions both claim fuse nothing)",
    )
    rendered_conf_weighted: bool = Field(
        True, description="match against the rendered confidences (the paper) instead of the rendered key masks"
    )
    join_min_coverage: float | None = Field(
        0.5,
        ge=0,
        le=1,
        description="a frame region the assignment leaves unmatched joins the rendered region covering this share "
        "of its pixels when their embeddings agree (join_min_cos), instead of starting a new region (none = off)",
    )
    join_min_cos: float = Field(0.9, ge=-1, le=1, description="embedding cosine a joining frame region needs")
    step_probe_blocks: int | None = Field(
        None, ge=0, description="the semantic step reads the map's view of an encoded frame by a probe at the "
        "frame's own depth (openfusion.mapping.surface_probe) instead of a ray cast once the map (a geometry shard's "
        "own blocks) holds more than this many blocks: Open3D's CPU ray cast costs in proportion to the blocks held "
        "(at 160x120 31 ms at 2,000 blocks, 86 ms at 90,000), a probe in proportion to the pixels (30-46 ms), so it "
        "pays past about 40,000. Not the default: probed, the bench rooms map 0.006 (median) worse under the "
        "standard encoder noise, alike without noise (docs/EVAL.md, 'The step's view on a large map'); none = "
        "always ray-cast"
    )


class MergeParams(SectionParams):
    """When two regions are one object and merge (:mod:`openfusion.mapping.merging`): their labelled
    voxels touch in 3D over a substantial part of the smaller one and their embeddings agree. The
    semantic service's section extends this model (it decides merges); the in-process pipeline and
    the evaluation use the same declaration."""

    model_config = ConfigDict(allow_inf_nan=False)

    merge_every: int = Field(
        10, ge=0, description="look for regions to merge every this many semantic frames, and at the end (0 = never)"
    )
    merge_min_cos: float = Field(
        0.85, ge=-1, le=1, description="two touching regions merge only when their embeddings' cosine is at least this"
    )
    merge_min_contact_fraction: float = Field(
        0.05,
        ge=0,
        le=1,
        description="...and at least this share of the smaller region's labelled voxels lies next to the other's",
    )
    merge_min_contact_voxels: int = Field(
        8, ge=1, description="...and at least this many of its voxels do (a touch of a few voxels is not contact)"
    )
    merge_contact_radius_vox: int = Field(
        1, ge=1, le=3, description="voxels within this many voxels (per axis) of another region's touch it"
    )
    merge_prune_empty: bool = Field(
        True,
        description="remove regions that hold no labelled voxel in two merge passes in a row (seen, then taken over "
        "by other regions: never rendered again, so never matched again)",
    )
    merge_embedding: Literal["weighted", "mean", "first"] = Field(
        "weighted",
        description="merged embedding: observation-weighted mean (measured best), plain mean of the two, or the "
        "surviving region's",
    )


class QueryParams(SectionParams):
    """How a query turns ranked regions into answers (the query service's section extends this;
    :func:`openfusion.mapping.queries.query_regions`, ``openfusion query --map-dir`` and the
    in-process run use the same declaration)."""

    min_region_points: int = Field(
        50,
        ge=1,
        description="regions with fewer surface points than this are not answers (stray fragments of a few "
        "voxels, regions whose voxels other regions took over); 1 = leave out only regions without points",
    )
    up_axis: str = Field(
        "+z",
        pattern=r"^[+-][xyz]$",
        description="the map's up axis in world coordinates (+z: the synthetic world, ScanNet); relations "
        "(on, under, above, next to) are computed with it",
    )


def default_min_region_points() -> int:
    """The declared default of :attr:`QueryParams.min_region_points`."""
    return int(QueryParams.model_fields["min_region_points"].default)


SelectMode = Literal["coverage", "every", "latest"]


class SelectParams(SectionParams):
    """Which frames the region encoder sees (:mod:`openfusion.mapping.selection`; the reasoning
    behind each rule and default is written down in :mod:`openfusion.mapping.coverage`). The semantic service's section extends
    this model; ``openfusion run --in-process`` and ``openfusion eval`` build the same one, so a
    result measured in-process is what the services do.

    ``coverage`` scores each candidate frame by what the encoder would add (surface the map holds no
    confident region for, a region seen from a viewing direction it was not encoded from, a region
    not encoded for ``select_stale_s``) and encodes the best one, and only one whose gain reaches
    ``select_min_gain``; ``latest`` encodes the newest frame whenever the encoder is free (the
    services' behaviour before selection); ``every`` encodes every frame, in order. In one process
    the encoder is free for every frame, so there ``latest`` is ``every``."""

    model_config = ConfigDict(allow_inf_nan=False)

    select: SelectMode = Field(
        "coverage", description="which frames are encoded: coverage (the ones that add something, best first), "
        "latest (the newest whenever the encoder is free), every (all, in order)")
    select_min_gain: float = Field(
        0.1, ge=0, le=10, description="coverage: a frame is encoded only when its gain (shares of its view: new "
        "surface + select_direction_weight x new directions + stale regions) reaches this; 0 = any frame with "
        "something new")
    select_patience_s: float | None = Field(
        0.1, gt=0, description="coverage: the gain a frame needs falls with the frame time t to the nearest encoded "
        "frame, select_min_gain / (1 + t / this): new surface that has waited a while is encoded even when it is "
        "little (a glimpse behind an object), a frame with nothing new never is; none = a fixed threshold")
    select_window: int = Field(
        64, ge=1, le=256, description="coverage, services: candidate frames held while the encoder is busy (and the "
        "frames the subscription queues for scoring); a full window lets its lowest-scoring frame go (~3 MB per "
        "640x480 frame with its instance image). 64 holds a first sweep's backlog behind a 150 ms encoder (2 s at "
        "30 fps); 32 let 1-11 chosen frames go on the 90-frame bench scene")
    select_width_px: int = Field(
        32, ge=8, le=640, description="coverage: width of the view a candidate is scored at (height from the "
        "frame's aspect ratio); reading the map's view at that size is the scoring's main cost. 32 px probed maps "
        "the bench rooms as well per encoder call as 64 px ray-cast, at a third of the scoring time (docs/EVAL.md, "
        "'Scored at 32 px')")
    select_view: Literal["auto", "probe", "render"] = Field(
        "probe", description="coverage: how a candidate's view of the map is read. probe: the map's region keys at "
        "the surface the frame's own depth sees, a few lookups per scored pixel whatever the map's size "
        "(openfusion.mapping.surface_probe); render: a ray cast of the map at the candidate's pose, whose cost grows "
        "with the blocks the map holds (Open3D's CPU ray cast copies its block hash map per call: 11 ms at 2,000 "
        "blocks, 45-76 ms at 67,000-90,000 on a 2-core box; at 64 px on the bench rooms 0.001-0.003 f-mIoU over a "
        "64 px probe at the same calls); auto: render while the map holds at most select_probe_blocks blocks, "
        "probe above")
    select_probe_blocks: int = Field(
        20000, ge=0, description="coverage, select_view=auto: the map's blocks (a geometry shard's own) above which "
        "a candidate is probed instead of rendered (20,000 blocks of 8^3 voxels at 2 cm: two furnished rooms; a "
        "render there costs about twice a probe)")
    select_low_conf: float = Field(
        0.2, ge=0, le=1, description="coverage: a surface pixel whose rendered region confidence is below this "
        "counts as unlabelled")
    select_cell_m: float = Field(
        0.1, gt=0, le=10, description="coverage: unlabelled surface is remembered per cube of this edge: surface an "
        "encoded frame showed from the same direction bin is not new again")
    select_tries: int = Field(
        2, ge=1, le=4, description="coverage: unlabelled surface counts as new until this many encoded frames "
        "showed it from the same direction bin (an encoder may miss a region once; what it never labels is not "
        "tried forever)")
    select_min_views: int = Field(
        0, ge=0, le=100, description="coverage: a region in view written by fewer encoded frames than this counts "
        "like a new direction with all its pixels (OVO keeps several views per segment; one noisy view is not "
        "a region's final word)")
    select_lookahead: int = Field(
        1, ge=1, le=16, description="coverage: frames decided together: of each run of this many frames at most the "
        "one of highest gain is encoded (when it reaches the bar), the others are not; 1 = each frame on its own. "
        "Frames wait up to this many frames for their decision")
    select_direction_bins: int = Field(
        24, ge=1, le=64, description="coverage: viewing directions are binned on the sphere into this many bins "
        "(Fibonacci sphere; 24: about 47 degrees across each)")
    select_direction_weight: float = Field(
        0.5, ge=0, description="coverage: weight of a region's pixels seen from a direction bin it was not encoded "
        "from, against new surface (1)")
    select_min_region_share: float = Field(
        0.005, ge=0, le=1, description="coverage: a region counts for new directions and staleness only when it "
        "fills at least this share of the view (OVI-MAP: 1000 of 307200 pixels)")
    select_stale_s: float | None = Field(
        60.0, gt=0, description="coverage: a region in view not encoded for this long (frame stamps) counts with "
        "all its pixels, so it cannot go stale while it is seen (none = never stale)")
    select_embed_share: float | None = Field(
        0.3, ge=0, le=1, description="coverage: of a chosen frame, a region is embedded only when at least this "
        "share of its pixels adds something (surface without a confident region, a region seen from a direction "
        "it was not encoded from, or gone stale); the others still update the map's region keys but carry no "
        "embedding (an encoder of region crops does not compute them; OVI-MAP's per-instance rule); none = "
        "every region of a chosen frame")
    select_embed_min_views: int = Field(
        3, ge=0, le=100, description="coverage, with select_embed_share: a region whose embedding averages fewer "
        "views than this is embedded again whenever a chosen frame shows it, whatever the direction (one noisy "
        "view, or a mask that merged two objects, is not a region's final word); 0 = off")
    select_still_s: float | None = Field(
        2.0, gt=0, le=60, description="coverage: a candidate whose camera stands still (within select_still_m and "
        "select_still_deg of the view last rendered for its robot) reuses that render for up to this long (frame "
        "time), while no update or merge changed the labels and its own depth agrees with the rendered surface "
        "(openfusion.mapping.still_views): a robot waiting at a door costs one ray cast of the map per this long, "
        "not one per frame; none = every candidate is rendered")
    select_still_m: float = Field(
        0.01, ge=0, le=1, description="coverage, with select_still_s: how far a camera may move and still reuse its "
        "last render")
    select_still_deg: float = Field(
        1.0, ge=0, le=45, description="coverage, with select_still_s: how far a camera may turn and still reuse its "
        "last render")
    select_embed_min_agreement: float = Field(
        0.85, ge=0, le=1, description="coverage, with select_embed_share: a region whose embeddings disagree (the "
        "length of their mean, of unit vectors, below this: views of two objects) is embedded again whenever a "
        "chosen frame shows it; views of one object agree to about the encoder's own noise (0.9 at the standard "
        "noise's cosine 0.9); 0 = off")

    @property
    def probe_above_blocks(self) -> int | None:
        """A candidate's view is probed when the map holds more blocks than this, else rendered;
        None: always rendered (``select_view``)."""
        return {"render": None, "probe": 0}.get(self.select_view, self.select_probe_blocks)


class JoinParams(SectionParams):
    """How a robot's odometry frame is joined to the map's (:mod:`openfusion.mapping.robot_join`):
    its first frames build a submap that is registered to the map's surface, accepted only when
    the fit is good, unambiguous and well constrained; later frames are re-checked against the map
    now and then. The geometry service's section extends this model."""

    model_config = ConfigDict(allow_inf_nan=False)

    join_voxel_m: float = Field(
        0.05, gt=0, le=0.5,
        description="registration grid: clouds are thinned to one point per cell and the global search "
        "correlates floor-plan cells of this size")
    join_submap_frames: int = Field(
        40, ge=1, description="a held robot's submap is its last this many frames (a robot that started in "
        "unmapped space joins once its recent frames are in mapped space)")
    join_min_submap_frames: int = Field(
        12, ge=1, description="frames a held robot's submap needs before the first registration attempt")
    join_min_submap_points: int = Field(
        1500, ge=10, description="thinned points a submap needs before a registration attempt")
    join_attempt_every: int = Field(
        10, ge=1, description="while a robot is held, try to join it again every this many of its frames")
    join_idle_attempt_s: float = Field(
        2.0, gt=0, description="...or sooner, when the held robot sent no frame for this long (its playback ended)")
    join_max_held_frames: int = Field(
        100, ge=1,
        description="frames of a held robot kept to be integrated once it joins (memory bound: older ones are "
        "dropped from the hold; a playback replays them after the join, a live robot loses them, counted)")
    join_min_fitness: float = Field(
        0.35, gt=0, le=1,
        description="accept a registration only when at least this share of the submap's points on walls and "
        "furniture (not floors or ceilings) lies within join_fit_distance_m of the map's surface")
    join_fit_distance_m: float = Field(
        0.03, gt=0, le=0.5, description="a submap point fits when the map's surface is this close after registration")
    join_max_rmse_m: float = Field(
        0.02, gt=0, le=0.5, description="...and the fitting points' RMS distance is at most this")
    join_max_ambiguity: float = Field(
        0.8, gt=0, le=1,
        description="...and no other distinct alignment fits nearly as well: the runner-up's fitness is at most "
        "this share of the best's (a symmetric corridor fits several ways)")
    join_min_constraint: float = Field(
        0.01, ge=0, le=1,
        description="...and the fit constrains every direction: the weakest translation and rotation direction "
        "of the point-to-plane information holds at least this share of the strongest (a bare corridor "
        "does not fix the position along it)")
    join_max_conflict: float = Field(
        0.03, ge=0, le=1,
        description="...and the robot's views do not contradict the map: of the pixels where both have a "
        "surface, at most this share has the map's surface in front of what the robot saw (it looked through "
        "a wall of the map: misaligned)")
    join_conflict_tolerance_m: float = Field(
        0.1, gt=0, description="a map surface nearer than the robot's depth by more than this plus the map's "
        "truncation distance (the band its surfaces are sharp to) is a contradiction")
    join_conflict_views: int = Field(
        8, ge=1, description="held frames (spread over the hold) a candidate alignment is checked against")
    join_recheck_every: int = Field(
        30, ge=0, description="re-check a joined robot's transform against the map every this many of its frames "
        "(0 = never)")
    join_recheck_frames: int = Field(
        8, ge=1, description="a re-check registers the robot's last this many frames against the map seen from "
        "their poses")
    join_recheck_min_correction_m: float = Field(
        0.01, ge=0, description="a re-check changes the transform only for a correction of at least this "
        "(or join_recheck_min_correction_deg)")
    join_recheck_min_correction_deg: float = Field(0.2, ge=0, description="see join_recheck_min_correction_m")
    join_recheck_max_correction_m: float = Field(
        0.15, gt=0, description="a re-check proposing more than this (or join_recheck_max_correction_deg) is not "
        "applied: logged and counted, the transform is kept")
    join_recheck_max_correction_deg: float = Field(3.0, gt=0, description="see join_recheck_max_correction_m")
