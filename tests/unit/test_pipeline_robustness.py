"""One bad frame never ends an in-process run.

Bad inputs tried: an encoder that returns no region at all for a frame (an empty observation is
a normal frame), an encoder that raises on one frame (logged, counted in ``semantic_failed``,
the frame keeps its geometry), and the gt encoder's noise dropping every region of every frame
(``--noise standard`` on a ScanNet-layout scene used to end ``openfusion run --in-process`` with
``ValueError: cannot reshape array of size 0``)."""

from __future__ import annotations

import numpy as np

from openfusion.encoders import make_region_encoder
from openfusion.encoders.noise import NoiseProfile, apply_region_noise
from openfusion.mapping import VolumeParams
from openfusion.mapping.params import SelectParams
from openfusion.mapping.pipeline import map_scene
from openfusion.sources import open_source
from openfusion.testing.encoders import FlakyEncoder

SMALL = VolumeParams(initial_block_count=2048)
SPEC = "synthetic:frames=6,width=160,height=120"
EVERY = SelectParams(select="every")  # every frame to the encoder: the bad ones among them


def test_an_empty_observation_and_an_encoder_error_are_counted_and_the_run_completes() -> None:
    """Frame 2 (no regions) is a normal semantic frame; frame 3 (encoder error) is counted in
    semantic_failed and still integrated; every frame is integrated and the map has regions."""
    result = map_scene(open_source(SPEC), region_encoder=FlakyEncoder(empty_on=[2], fail_on=[3]), volume_params=SMALL,
                       select_params=EVERY)
    stats = result.stats
    assert stats.frames_integrated == 6
    assert stats.semantic_failed == 1
    assert stats.semantic_frames == 5
    assert len(result.dictionary) > 3
    assert result.volume.num_blocks > 0


def test_noise_that_drops_every_region_leaves_empty_observations_not_a_crash() -> None:
    """The noise model with every region dropped returns (0, h, w) maps and (0, d) embeddings, and a
    whole run of such frames completes with semantic frames counted and no region."""
    maps = np.random.default_rng(0).random((3, 12, 16)).astype(np.float32)
    emb = np.eye(3, 8, dtype=np.float32)
    profile = NoiseProfile(name="drop-all", drop_prob=1.0)
    out_maps, out_emb, labels, report = apply_region_noise(maps, emb, ["a", "b", "c"], profile,
                                                           np.random.default_rng(0))
    assert out_maps.shape == (0, 12, 16) and out_emb.shape == (0, 8) and labels == []
    assert report.dropped == 3 and report.output_regions == 0
    encoder = make_region_encoder("gt", text_encoder="hash", noise=profile)
    result = map_scene(open_source(SPEC), region_encoder=encoder, volume_params=SMALL, select_params=EVERY)
    assert result.stats.frames_integrated == 6 and result.stats.semantic_frames == 6
    assert result.stats.semantic_failed == 0 and len(result.dictionary) == 0
