"""Embeddings only for the regions a chosen view adds (openfusion.mapping.region_gate): the rule,
the scorer's wanted pixels, a crop encoder that skips the crops, the update that fuses a region
without an embedding, the pool's messages that carry the mask and the flags, and the in-process
pipeline (fewer regions embedded, the same frames encoded, the same surface labelled).

Bad inputs tried: a wanted mask that is not 2-D, a share outside [0, 1], an observation whose
``embedded`` flags are of the wrong length or type or whose skipped row is not zero (refused by
``validate`` and by ``plan_update`` with the field named), a pool request with a mask and no share
and a reply with flags for another number of regions (refused by the schema)."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from openfusion.encoders import EncoderError, RegionObservation
from openfusion.encoders.crops import CropSpec
from openfusion.encoders.proposal_encoder import ProposalRegionEncoder
from openfusion.frame import CameraIntrinsics, Frame
from openfusion.mapping import RegionDictionary, RenderedView, plan_update
from openfusion.mapping.params import SelectParams
from openfusion.mapping.region_gate import encode_where, gate_observation, regions_wanted
from openfusion.mapping.selection import CoverageScorer
from openfusion.poses import look_at
from openfusion.wire.codec import decode, encode
from openfusion.wire.schemas import EncodeReply, EncodeRequest, RgbdFrame

H, W = 12, 16


def masks_of(*column_ranges: tuple[int, int]) -> np.ndarray:
    """One confidence map per (start, stop) column range (confidence 0.9 inside)."""
    out = np.zeros((len(column_ranges), H, W), np.float32)
    for i, (a, b) in enumerate(column_ranges):
        out[i][:, a:b] = 0.9
    return out


def unit_rows(n: int, dim: int = 4) -> np.ndarray:
    rows = np.eye(dim, dtype=np.float32)[np.arange(n) % dim]
    return np.ascontiguousarray(rows)


# ------------------------------------------------------------------ the rule
def test_a_region_is_embedded_when_enough_of_it_is_wanted() -> None:
    wanted = np.zeros((H, W), bool)
    wanted[:, :8] = True  # the left half adds something
    conf = masks_of((0, 8), (4, 12), (7, 16), (0, 0))  # all in, half in, 1 of 9 columns in, empty
    assert regions_wanted(conf, wanted, 0.4).tolist() == [True, True, False, True]
    assert regions_wanted(conf, wanted, 0.6).tolist() == [True, False, False, True]
    assert regions_wanted(conf, None, 0.4).all() and regions_wanted(conf, wanted, None).all()
    # the wanted mask may be of another size (the scored view): resampled to the maps'
    small = np.zeros((3, 4), bool)
    small[:, :2] = True
    assert regions_wanted(conf, small, 0.4).tolist() == [True, True, False, True]
    with pytest.raises(ValueError, match="2-D"):
        regions_wanted(conf, np.ones(5, bool), 0.4)
    with pytest.raises(ValueError, match="within"):
        regions_wanted(conf, wanted, 1.5)


def test_gated_observation_keeps_every_mask_and_zeroes_the_skipped_embeddings() -> None:
    wanted = np.zeros((H, W), bool)
    wanted[:, :8] = True
    obs = RegionObservation(masks_of((0, 8), (8, 16)), unit_rows(2), "space")
    gated = gate_observation(obs, wanted, 0.4)
    assert gated.num_regions == 2 and gated.num_embedded == 1
    assert gated.embedded.tolist() == [True, False]
    np.testing.assert_array_equal(gated.embeddings[1], 0.0)
    np.testing.assert_array_equal(gated.embeddings[0], obs.embeddings[0])
    gated.validate(dim=4)
    assert gate_observation(obs, None, None) is obs  # no gate: untouched
    # bad flags are refused with the field named
    bad = RegionObservation(gated.conf_maps, gated.embeddings, "space", embedded=np.array([True]))
    with pytest.raises(EncoderError, match="embedded"):
        bad.validate()
    bad = RegionObservation(gated.conf_maps, gated.embeddings, "space", embedded=np.array([1, 0]))
    with pytest.raises(EncoderError, match="embedded"):
        bad.validate()
    bad = RegionObservation(gated.conf_maps, unit_rows(2), "space", embedded=np.array([True, False]))
    with pytest.raises(EncoderError, match="not embedded"):
        bad.validate()


# ------------------------------------------------------------------ a crop encoder skips the crops
class _Proposer:
    name = "columns"

    def propose(self, frame: Frame, out_hw: tuple[int, int]) -> np.ndarray:
        h, w = out_hw
        out = np.zeros((3, h, w), np.float32)
        for i in range(3):
            out[i][:, i * w // 3:(i + 1) * w // 3] = 1.0
        return out


class _CountingEmbedder:
    embedding_space, dim, crop_spec = "space", 4, CropSpec(size=8)

    def __init__(self) -> None:
        self.crops = 0

    def embed_crops(self, crops: np.ndarray) -> np.ndarray:
        self.crops += len(crops)
        return np.tile(np.array([[1.0, 0.5, 0.0, 0.0]], np.float32), (len(crops), 1))


def test_a_crop_encoder_embeds_only_the_wanted_regions_crops() -> None:
    embedder = _CountingEmbedder()
    enc = ProposalRegionEncoder(_Proposer(), embedder, name="test", output_scale=1.0)
    K = CameraIntrinsics(48, 12, 40.0, 40.0, 24.0, 6.0)
    frame = Frame(frame_id=0, stamp_ns=0, color=np.full((12, 48, 3), 90, np.uint8),
                  depth=np.ones((12, 48), np.float32), depth_scale=1.0, intrinsics=K, T_world_cam=np.eye(4))
    wanted = np.zeros((12, 48), bool)
    wanted[:, 16:32] = True  # only the middle column of regions adds something
    obs = encode_where(enc, frame, wanted, 0.4)
    assert embedder.crops == 1  # the other two crops were never cut nor embedded
    assert obs.num_regions == 3 and obs.embedded.tolist() == [False, True, False]
    obs.validate(dim=4)
    assert enc.stats["regions"] == 1 and enc.stats["regions_not_embedded"] == 2
    full = enc.encode(frame)  # no gate: every region
    assert embedder.crops == 4 and full.embedded is None and full.num_embedded == 3


# ------------------------------------------------------------------ the update
def test_a_region_without_embedding_fuses_its_key_but_changes_no_embedding_and_starts_no_region() -> None:
    d = RegionDictionary("space", 4)
    e_chair = unit_rows(1)[0]
    chair = d.add(e_chair, label="chair")
    key_map = np.full((H, W), -1, np.int32)
    key_map[:, :8] = chair
    rendered = RenderedView(key_map, (key_map >= 0).astype(np.float32) * 0.8, np.ones((H, W), np.float32))
    conf = masks_of((0, 8), (9, 12), (12, 16))  # the chair again; two new ones
    emb = np.zeros((3, 4), np.float32)
    emb[2] = unit_rows(3)[2]
    obs = RegionObservation(conf, emb, "space", embedded=np.array([False, False, True]))
    plan = plan_update(obs, rendered, d)
    assert plan.matched == [(0, chair)]  # matched on geometry alone
    assert d.count(chair) == 1  # ... but its embedding is not touched
    np.testing.assert_array_equal(d.embedding(chair), e_chair)
    assert (plan.key_map[:, 1:7] == chair).all()  # its pixels still fuse the chair's key
    assert [i for i, _ in plan.new_keys] == [2] and 1 in plan.skipped  # no embedding, no new region
    assert len(d) == 2
    with pytest.raises(ValueError, match="embedded"):
        plan_update(RegionObservation(conf, emb, "space", embedded=np.array([True, False])), rendered, d)


def test_dictionary_support_says_how_many_views_and_how_well_they_agree() -> None:
    d = RegionDictionary("space", 4)
    a = d.add(unit_rows(1)[0])
    b = d.add(unit_rows(1)[0])
    d.observe(b, unit_rows(2)[1])  # a second view of another object
    counts, agreement = d.support_of(np.array([a, b, 999]))
    assert counts.tolist() == [1, 2, 0]
    assert agreement[0] == pytest.approx(1.0) and agreement[1] == pytest.approx(np.sqrt(0.5), abs=1e-6)
    assert agreement[2] == 0.0


# ------------------------------------------------------------------ the scorer's wanted pixels
SW, SH = 16, 12
SK = CameraIntrinsics(SW, SH, 14.0, 14.0, (SW - 1) / 2, (SH - 1) / 2)
T_FRONT = look_at(np.array([0.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), up=np.array([0.0, 0.0, 1.0]))
T_BACK = look_at(np.array([4.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), up=np.array([0.0, 0.0, 1.0]))


def _view(scorer: CoverageScorer, keys: np.ndarray, T: np.ndarray = T_FRONT, stamp_s: float = 0.0):  # noqa: ANN202
    return scorer.prepare(frame_id=0, stamp_ns=int(stamp_s * 1e9), T_world_cam=T, intrinsics=SK,
                          depth_m=np.full((SH, SW), 2.0, np.float32), key_map=keys,
                          conf_map=(keys >= 0).astype(np.float32))


def test_wanted_pixels_are_new_surface_new_directions_and_unsettled_regions() -> None:
    scorer = CoverageScorer(SelectParams(select_width_px=SW, select_patience_s=None))
    keys = np.full((SH, SW), 7, np.int32)
    keys[:, SW // 2:] = -1  # left: region 7, right: no region
    ev = _view(scorer, keys)
    assert scorer.wanted_px(ev).all()  # region 7 never encoded from here, and new surface
    scorer.mark_selected(ev)
    scorer.observe_plan(keys, T_FRONT, SK, 0)
    again = scorer.wanted_px(_view(scorer, keys, stamp_s=1.0))
    assert not again[:, : SW // 2].any() and again[:, SW // 2:].all()  # the region is covered from here
    assert scorer.wanted_px(_view(scorer, keys, T=T_BACK, stamp_s=1.0))[:, SW // 2:].any()  # from behind: new
    # a region whose embeddings are too few or disagree is wanted again from any direction
    scorer.embedding_support = lambda k: (np.ones(len(k), np.int64), np.ones(len(k), np.float32))
    assert scorer.wanted_px(_view(scorer, keys, stamp_s=1.0))[:, : SW // 2].all()  # 1 view < 2
    scorer.embedding_support = lambda k: (np.full(len(k), 5, np.int64), np.full(len(k), 0.6, np.float32))
    assert scorer.wanted_px(_view(scorer, keys, stamp_s=1.0))[:, : SW // 2].all()  # views disagree
    scorer.embedding_support = lambda k: (np.full(len(k), 5, np.int64), np.full(len(k), 0.95, np.float32))
    assert not scorer.wanted_px(_view(scorer, keys, stamp_s=1.0))[:, : SW // 2].any()  # settled
    # the decision leaves the mask on the view, measured before the view is recorded
    ev = _view(scorer, keys, T=T_BACK, stamp_s=2.0)
    _, chosen = scorer.decide(ev)
    assert chosen and ev.wanted_px is not None and ev.wanted_px[:, : SW // 2].all()


def test_a_chosen_view_waiting_for_the_encoder_wants_what_is_still_new_when_it_is_encoded() -> None:
    """The services' window encodes a chosen frame later than it decided it, after the frames
    taken before it labelled and settled much of what its render showed (with the decision's mask
    the services embedded 3.5-4x the regions one process does). Asked again with the map rendered
    again: regions settled meanwhile are not wanted, surface labelled meanwhile is wanted only from
    a direction its region was not encoded from, surface still unlabelled stays wanted, a region
    whose views came to disagree is wanted again, and without a new render only the settling is
    asked again."""
    scorer = CoverageScorer(SelectParams(select_width_px=SW, select_patience_s=None))
    support = {"count": 1, "agreement": 1.0}
    scorer.embedding_support = lambda k: (np.full(len(k), support["count"], np.int64),
                                          np.full(len(k), support["agreement"], np.float32))
    left, right = np.s_[:, : SW // 2], np.s_[:, SW // 2:]
    keys = np.full((SH, SW), 7, np.int32)
    keys[right] = -1
    scorer.mark_selected(_view(scorer, keys))
    scorer.observe_plan(keys, T_FRONT, SK, 0)  # region 7 encoded once from the front
    waiting = _view(scorer, keys, stamp_s=1.0)  # chosen while region 7 has one view of the 2 asked
    _, chosen = scorer.decide(waiting, hold=True)
    assert chosen and waiting.wanted_px.all()
    np.testing.assert_array_equal(scorer.wanted_now(waiting), waiting.wanted_px)  # nothing applied since
    # frames taken before it applied: region 7 settled, the right half labelled region 8
    later = keys.copy()
    later[right] = 8
    scorer.observe_plan(later, T_FRONT, SK, int(0.5e9))
    support.update(count=3)
    conf = (later >= 0).astype(np.float32)
    assert not scorer.wanted_now(waiting, later, conf).any()  # both covered from here and settled
    without_render = scorer.wanted_now(waiting)
    assert not without_render[left].any() and without_render[right].all()  # as decided, settling asked again
    still_bare = later.copy()
    still_bare[:, -2:] = -1
    assert scorer.wanted_now(waiting, still_bare, (still_bare >= 0).astype(np.float32))[:, -2:].all()
    from_behind = later.copy()
    from_behind[right] = 9  # labelled since by a region never encoded from this side
    scorer.observe_plan(from_behind, T_BACK, SK, int(0.6e9))
    assert scorer.wanted_now(waiting, from_behind, conf)[right].all()
    support.update(agreement=0.5)  # its views came to disagree: wanted again
    assert scorer.wanted_now(waiting, later, conf).all()


def test_regions_an_encoder_is_embedding_count_as_viewed_until_its_frame_is_done() -> None:
    """A pool of two: a second worker takes a frame while the first encodes one that will embed
    region 7 (its one view so far, two asked). Until the first frame is released, region 7 counts
    as settled for the second; once released (applied, or let go) it is asked for again. A region
    the first frame wanted too little of (under ``select_embed_share``) is not counted. Surface
    the first frame shows unlabelled stays wanted (it may not label it)."""
    scorer = CoverageScorer(SelectParams(select_width_px=SW, select_patience_s=None, select_embed_min_views=2))
    scorer.embedding_support = lambda k: (np.ones(len(k), np.int64), np.ones(len(k), np.float32))
    keys = np.full((SH, SW), 7, np.int32)
    keys[:, SW // 2:] = 8
    scorer.mark_selected(_view(scorer, keys))
    scorer.observe_plan(keys, T_FRONT, SK, 0)
    scorer.observe_plan(keys, T_FRONT, SK, 1)  # both written by 2 encoded frames, embeddings of 1 view
    first, second = _view(scorer, keys, stamp_s=1.0), _view(scorer, keys, stamp_s=2.0)
    second.frame_id = 1
    for ev in (first, second):
        scorer.wanted_px(ev)
    wanted = np.zeros((SH, SW), bool)
    wanted[:, : SW // 2] = True  # region 7 wanted, region 8 not
    wanted[0, -1] = True  # one pixel of region 8: under the share
    assert scorer.wanted_now(second).all()
    scorer.embedding_in_flight(first, None, wanted)
    now = scorer.wanted_now(second)
    assert not now[:, : SW // 2].any() and now[:, SW // 2:].all()
    scorer.release(first.frame_id, first.stamp_s)
    assert scorer.wanted_now(second).all()
    # surface no region holds yet stays wanted while a frame in flight shows it: it may not label it
    bare = keys.copy()
    bare[:, SW // 2:] = -1
    first, second = _view(scorer, bare, stamp_s=3.0), _view(scorer, bare, stamp_s=4.0)
    for ev in (first, second):
        scorer.wanted_px(ev)
    scorer.embedding_in_flight(first, None, np.ones((SH, SW), bool))
    assert scorer.wanted_now(second)[:, SW // 2:].all()
    scorer.release(first.frame_id, first.stamp_s)


# ------------------------------------------------------------------ the pool's messages
def _rgbd() -> RgbdFrame:
    K = CameraIntrinsics(8, 6, 7.0, 7.0, 4.0, 3.0)
    frame = Frame(frame_id=3, stamp_ns=5, color=np.zeros((6, 8, 3), np.uint8), depth=np.ones((6, 8), np.float32),
                  depth_scale=1.0, intrinsics=K, T_world_cam=np.eye(4))
    return RgbdFrame.from_frame(frame)


def test_the_pool_request_carries_the_mask_and_the_reply_the_flags() -> None:
    wanted = np.zeros((3, 4), bool)
    wanted[0, 0] = True
    req = EncodeRequest.of(_rgbd(), None, map_id="m", embedding_space="s", embed_where=wanted, embed_share=0.4)
    back = decode(encode(req), expected=EncodeRequest)
    np.testing.assert_array_equal(back.embed_where, wanted)
    assert back.embed_share == pytest.approx(0.4)
    plain = decode(encode(EncodeRequest.of(_rgbd(), None, map_id="m", embedding_space="s")), expected=EncodeRequest)
    assert plain.embed_where is None and plain.embed_share is None
    with pytest.raises(ValidationError, match="together"):
        EncodeRequest(**{**plain.model_dump(), "embed_where": wanted})
    reply = EncodeReply(frame_id=3, worker_id="w", embedding_space="s", conf_maps=masks_of((0, 4), (4, 8)),
                        embeddings=np.zeros((2, 4), np.float32), encode_ms=1.0, embedded=np.array([True, False]))
    assert decode(encode(reply), expected=EncodeReply).embedded.tolist() == [True, False]
    with pytest.raises(ValidationError, match="embedded flags"):
        EncodeReply(**{**reply.model_dump(), "embedded": np.array([True])})


# ------------------------------------------------------------------ the in-process pipeline
def test_the_pipeline_embeds_fewer_regions_and_labels_the_same_surface() -> None:
    """Two laps of a small room: the second lap's chosen frames show regions already described from
    there, so they are fused without embeddings; the same frames are encoded and the same surface
    labelled as when every region of a chosen frame is embedded, and run.json says how many."""
    from openfusion.app.summary import RunSummary
    from openfusion.mapping import VolumeParams
    from openfusion.mapping.pipeline import map_scene
    from openfusion.sources import open_source
    from openfusion.testing.encoders import FlakyEncoder

    frames = list(open_source("synthetic:frames=24,lap=12,width=160,height=120"))
    volume = VolumeParams(initial_block_count=4096)

    def run(share: float | None):  # noqa: ANN202
        return map_scene(frames, region_encoder=FlakyEncoder(empty_on=(), fail_on=()), volume_params=volume,
                         select_params=SelectParams(select_embed_share=share))

    gated, every_region = run(SelectParams().select_embed_share), run(None)
    assert gated.stats.encoder_calls == every_region.stats.encoder_calls > 2
    assert gated.stats.encoder_regions < every_region.stats.encoder_regions
    assert gated.stats.regions_not_embedded > 0 and every_region.stats.regions_not_embedded == 0
    returned = gated.stats.encoder_regions + gated.stats.regions_not_embedded
    assert abs(returned - every_region.stats.encoder_regions) <= 0.05 * returned  # the same frames' regions

    def labelled(result) -> float:  # noqa: ANN001
        keys = np.asarray(result.volume.extract_points().keys)
        return float((keys >= 0).mean())

    assert labelled(gated) >= labelled(every_region) - 0.01
    summary = RunSummary.from_pipeline(gated.stats, regions=len(gated.dictionary), source="synthetic", encoder="gt",
                                       noise="off", semantic_every=1, wall_s=1.0)
    assert summary.regions_not_embedded == gated.stats.regions_not_embedded
    assert summary.encoder_regions == gated.stats.encoder_regions


def test_select_params_from_a_bench_command_line() -> None:
    """``FIELD=VALUE`` pairs as the benches take them; an empty value is none (bad: no ``=``, a
    share out of range, an unknown field)."""
    p = SelectParams.from_pairs(["select_embed_share=", "select_lookahead=3"])
    assert p.select_embed_share is None and p.select_lookahead == 3
    assert SelectParams.from_pairs(["select_embed_share=0.5"]).select_embed_share == 0.5
    with pytest.raises(ValueError, match="FIELD=VALUE"):
        SelectParams.from_pairs(["select_embed_share"])
    with pytest.raises(ValidationError, match="select_embed_share"):
        SelectParams.from_pairs(["select_embed_share=2"])
    with pytest.raises(ValidationError, match="no_such_field"):
        SelectParams.from_pairs(["no_such_field=1"])


def test_the_selector_hands_each_chosen_frame_its_mask_once_and_keeps_few() -> None:
    """A frame chosen gets its wanted pixels once; a frame never chosen, or asked twice, gets none
    (every region embedded); a caller that never asks leaves at most WANTED_KEPT masks behind."""
    from openfusion.mapping.selection import WANTED_KEPT, FrameSelector
    from openfusion.sources import open_source

    def empty_map(T_world_cam, K):  # noqa: ANN001, ANN202  (nothing mapped: every view is new surface)
        return RenderedView(np.full((K.height_px, K.width_px), -1, np.int32),
                            np.zeros((K.height_px, K.width_px), np.float32),
                            np.zeros((K.height_px, K.width_px), np.float32))

    frames = list(open_source("synthetic:frames=120,lap=120,width=64,height=48"))
    selector = FrameSelector(SelectParams(select_patience_s=None), empty_map)
    assert selector.wants(frames[0])
    wanted, share = selector.embed_where(frames[0])
    assert wanted is not None and wanted.any() and share == SelectParams().select_embed_share
    assert selector.embed_where(frames[0]) == (None, None)  # asked once
    assert selector.embed_where(frames[1]) == (None, None)  # never chosen
    chosen = sum(selector.wants(frame) for frame in frames[3:])  # new surface all round the room
    assert chosen > WANTED_KEPT and len(selector._wanted) == WANTED_KEPT
