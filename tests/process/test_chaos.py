"""Chaos: a 200-frame playback of the synthetic room through ``openfusion run`` during which
geometry, then semantic, then query are killed with SIGKILL at seeded random points (frames
integrated so far). The run completes, run.json counts one restart of each, every frame is
integrated exactly once (frames integrated = frames read - frames skipped), and the saved map
matches an uninterrupted run of the same playback: surface points within 1 % and f-mIoU (the
evaluation protocol's, the room's class names as MiniLM queries) within 0.02.

Slow (two runs of 200 frames at 320x240 and a text encoder): ``pytest -m slow tests/process/test_chaos.py``."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
from supervision_support import BackgroundRun

from openfusion.encoders import make_text_encoder
from openfusion.eval.ground_truth import synthetic_ground_truth
from openfusion.eval.metrics import compute_metrics
from openfusion.eval.protocol import (
    class_scores_mask,
    classify_embeddings,
    confusion_for_points,
    ground_truth_labels_for,
    labels_from_region_keys,
)
from openfusion.eval.runner import QUICK
from openfusion.mapping import load_map
from openfusion.sources.synthetic import SyntheticWorld
from openfusion.wire.counters import GeometryCounter

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]

FRAMES = 200
SEED = 19
ARGS = ("--source", "synthetic:seed=1,width=320,height=240", "--frames", str(FRAMES), "--rate-hz", "10",
        "--query", "chair", "--set", "supervision.checkpoint_period_s=3", "--restart-backoff-s", "0.5",
        "--timeout-s", "1200")


def map_quality(map_dir: Path) -> tuple[int, float]:
    """(surface points, f-mIoU) of a saved map of the synthetic room (seed 1), as ``openfusion
    eval`` scores a map: each region labelled by its best class query, each point by its region,
    matched to the nearest ground-truth point."""
    loaded = load_map(map_dir)
    surface = loaded.volume.extract_points()
    points = np.asarray(surface.points, dtype=np.float64)
    keys = np.asarray(surface.keys, dtype=np.int64)
    gt = synthetic_ground_truth(SyntheticWorld(1), spacing_m=QUICK.gt_spacing_m, source="synthetic")
    class_emb = np.asarray(make_text_encoder("minilm").encode(list(gt.class_names)), dtype=np.float32)
    allowed = class_scores_mask(gt.class_names, QUICK.excluded_classes)
    dictionary = loaded.dictionary
    region_cls = classify_embeddings(np.asarray(dictionary.unit_embeddings(), dtype=np.float32), class_emb,
                                     allowed=allowed)
    pred = labels_from_region_keys(keys, np.asarray(dictionary.keys, dtype=np.int64), region_cls)
    gt_of_points, _ = ground_truth_labels_for(points, gt)
    cm = confusion_for_points(pred, gt_of_points, gt.class_names)
    return len(points), compute_metrics(cm, exclude_classes=QUICK.excluded_classes, unlabelled=QUICK.unlabelled).f_mIoU


def integrated(h: dict) -> float:
    g = h.get("geometry")
    return g.counter(GeometryCounter.FRAMES_INTEGRATED) if g is not None else 0.0


def test_kill_geometry_semantic_and_query_mid_run_and_lose_nothing(tmp_path: Path) -> None:
    rng = random.Random(SEED)
    plan = [("geometry", rng.randint(40, 70)), ("semantic", rng.randint(85, 110)), ("query", rng.randint(120, 145))]
    chaos = BackgroundRun(tmp_path, *ARGS, name="chaos")
    try:
        for service, at in plan:
            chaos.wait_for(lambda h, at=at: integrated(h) >= at)
            chaos.kill(service, restarts_before=0)
        chaos_summary = chaos.finish(timeout_s=1500)
    finally:
        chaos.close()
    calm = BackgroundRun(tmp_path, *ARGS, name="calm")
    try:
        calm_summary = calm.finish(timeout_s=1500)
    finally:
        calm.close()

    chaos_points, chaos_fmiou = map_quality(chaos.out / "map")
    calm_points, calm_fmiou = map_quality(calm.out / "map")
    print(f"chaos {plan}: {chaos_points} points, f-mIoU {chaos_fmiou:.3f}, {chaos_summary}; "
          f"uninterrupted: {calm_points} points, f-mIoU {calm_fmiou:.3f}")
    assert chaos_summary["restarts"] == {"geometry": 1, "semantic": 1, "query": 1, "bridge": 0}, plan
    assert calm_summary["restarts"] == {"geometry": 0, "semantic": 0, "query": 0, "bridge": 0}
    for summary in (chaos_summary, calm_summary):
        skipped = sum(summary["frames_skipped"].values())
        assert summary["frames_integrated"] == summary["frames_read"] - skipped == FRAMES
        assert summary["error"] is None
    assert chaos_summary["frames_replayed"] > 0
    assert abs(chaos_points - calm_points) <= 0.01 * calm_points
    assert abs(chaos_fmiou - calm_fmiou) <= 0.02
    assert calm_fmiou > 0.3  # the comparison means something: the map is labelled
