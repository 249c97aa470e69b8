"""``SyntheticSource``: frames of a ``SyntheticWorld`` as a frame source, and ``open_synthetic``.

Frame i is rendered at pose i of the world's camera path, with Kinect-like depth noise drawn
from a stream seeded by (world seed, 1000 + i), so frames are a pure function of the seed, the
index and the options. The path is a closed lap (``lap=N`` frames, default
:data:`~openfusion.sources.synthetic.camera.LAP_FRAMES`); a source with more frames than a lap walks
the lap again with the same poses, while frame ids and stamps keep increasing. ``open_synthetic``
parses the ``synthetic:key=value,...`` spec options
(:mod:`openfusion.sources.synthetic_spec`).
"""

from __future__ import annotations

import numpy as np

from openfusion.frame import CameraIntrinsics, Frame
from openfusion.sources.base import IndexedFrameSource
from openfusion.sources.synthetic.camera import LAP_FRAMES, default_intrinsics
from openfusion.sources.synthetic.depth import DEPTH_MAX_M, DEPTH_MIN_M, DEPTH_SCALE, apply_depth_noise
from openfusion.sources.synthetic.world import SyntheticWorld
from openfusion.sources.synthetic_spec import SPEC_KEYS, synthetic_options


class SyntheticSource(IndexedFrameSource):
    """Frames rendered from a ``SyntheticWorld`` along its ``camera_path`` (streams directly).

    Frame i: ``frame_id = i``, ``stamp_ns = round(i * 1e9 / fps)``, depth uint16 mm, exact
    instance image and the categories of the instances it shows. Frames are a pure function
    of (world seed, i, options): iterating twice gives identical frames. ``frames_per_lap``
    (default :data:`~openfusion.sources.synthetic.camera.LAP_FRAMES`): frames of one lap of the
    room; frame ``i`` is taken at the pose of frame ``i mod frames_per_lap`` (``self.lap``).
    """

    def __init__(
        self,
        world: SyntheticWorld,
        num_frames: int = 300,
        width_px: int = 640,
        height_px: int = 480,
        *,
        fps: float = 30.0,
        depth_noise: bool = True,
        frames_per_lap: int | None = None,
        intrinsics: CameraIntrinsics | None = None,
        stride: int = 1,
        max_frames: int | None = None,
    ) -> None:
        if num_frames < 0:
            raise ValueError(f"num_frames must be >= 0, got {num_frames}")
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        super().__init__(f"synthetic:seed={world.seed}", stride=stride, max_frames=max_frames)
        self.world = world
        self.num_frames = int(num_frames)
        if intrinsics is not None and (intrinsics.width_px, intrinsics.height_px) != (width_px, height_px):
            raise ValueError(
                f"intrinsics are for {intrinsics.width_px}x{intrinsics.height_px}, frames asked for {width_px}x{height_px}"
            )
        self.intrinsics = intrinsics if intrinsics is not None else default_intrinsics(width_px, height_px)
        self.fps = float(fps)
        self.depth_noise = depth_noise
        self.lap = int(frames_per_lap) if frames_per_lap is not None else LAP_FRAMES
        # One lap's poses (or fewer): later laps take the same poses.
        self.poses = world.camera_path(min(self.num_frames, self.lap), frames_per_lap=self.lap)

    def _num_items(self) -> int:
        return self.num_frames

    def _load(self, index: int) -> Frame:
        T = self.poses[index % self.lap]
        view = self.world.render(T, self.intrinsics)
        if self.depth_noise:
            rng = np.random.default_rng([self.world.seed, 1000 + index])
            depth_m = apply_depth_noise(view.depth_m, view.view_cos, rng)
        else:
            depth_m = np.where((view.depth_m >= DEPTH_MIN_M) & (view.depth_m <= DEPTH_MAX_M), view.depth_m, 0.0)
        depth = np.round(depth_m * DEPTH_SCALE).astype(np.uint16)
        present = np.flatnonzero(np.bincount(view.instance.ravel()))
        cats = {int(i): self.world.categories[int(i)] for i in present if i != 0}
        return Frame(
            frame_id=index,
            stamp_ns=int(round(index * 1e9 / self.fps)),
            color=view.color,
            depth=depth,
            depth_scale=DEPTH_SCALE,
            intrinsics=self.intrinsics,
            T_world_cam=T.copy(),
            instance=view.instance,
            instance_categories=cats,
            source=self.name,
        )


def open_synthetic(spec_options: dict[str, str] | None = None, **kwargs) -> SyntheticSource:
    """A ``SyntheticSource`` from ``synthetic:seed=N,frames=N,width=W,height=H,fps=F,noise=0|1,lap=N``
    options (strings, :data:`~openfusion.sources.synthetic_spec.SPEC_KEYS`) plus keyword arguments
    of ``SyntheticSource`` (and ``seed``)."""
    merged = dict(kwargs)
    for name, value in synthetic_options(spec_options or {}).items():
        if name in merged:
            key = next(k for k, (n, _conv) in SPEC_KEYS.items() if n == name)
            raise ValueError(f"synthetic option {key!r} is given both in the spec and as the keyword {name!r}")
        merged[name] = value
    seed = int(merged.pop("seed", 0))
    return SyntheticSource(SyntheticWorld(seed), **merged)
