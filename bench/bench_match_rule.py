#!/usr/bin/env python3
"""What v9's share of the best does to the built-in room's answers, with and without noise.

The word lists hold one region per category, so they cannot see what a real map has: several
regions of one object or of one category (four walls, two pillows; with the gt encoder's
``standard`` noise, fragments seen once whose embedding is the category's blurred by noise of
cosine 0.9). ``match`` must keep those while it drops other categories. This bench maps the
built-in room (MiniLM, 120 frames at 160x120, 4 cm voxels) with noise ``off`` and ``standard``
(three seeds each) in this process, asks each of the room's 19 category names (as a user would,
every region of the map with at least ``min_region_points`` surface points, the query service's
rule) and counts, for each rule in one run:

- **instances kept**: regions of the category named (its label, and its embedding closest to
  that category's among the 19: a region whose embedding a noisy merge took from another
  category is left out) that are a ``match``, over all such regions;
- **wrong matches**: matches whose region is of another category (not counting "chair" <->
  "office chair", a chair of another kind), per name asked;
- **lowest share**: the smallest margin share (margin / best margin) of a region of the category
  named; a share of the best above it drops that region.

Rows: v8 (threshold only), the share of the best at 0.5 to 0.9 (v9: 0.7) and, measured and not
kept, an additive gap to the best margin. The baseline is v8, measured in the same run on the
same maps.

    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_match_rule.py          # about 2 min on 2 cores
    HF_HUB_OFFLINE=1 .venv/bin/python bench/bench_match_rule.py --quick  # one seed per noise
"""

from __future__ import annotations

import argparse
import collections

import numpy as np

from openfusion.encoders import make_region_encoder, make_text_encoder
from openfusion.encoders.captions import region_text_embeddings
from openfusion.mapping import VolumeParams
from openfusion.mapping.params import default_min_region_points
from openfusion.mapping.pipeline import map_scene
from openfusion.mapping.relevancy import RelevancyScorer, match_mask, relevancy_texts
from openfusion.sources import open_source
from openfusion.sources.synthetic import CATEGORIES

SHARES: tuple[float | None, ...] = (None, 0.5, 0.6, 0.65, 0.7, 0.75, 0.8, 0.9)
#: Additive gaps to the best margin (measured, not kept).
GAPS: tuple[float, ...] = (0.05, 0.1, 0.15)
#: Categories a name may also match: a chair of another kind.
SAME = {"chair": {"office chair"}, "office chair": {"chair"}}


def room_regions(text, noise: str, seed: int) -> tuple[np.ndarray, list[str]]:  # noqa: ANN001
    """(embeddings, category) of the regions of a map of the room with enough surface points;
    category: the label when the embedding is closest to that label's category, else ``"?"``."""
    encoder = make_region_encoder("gt", text_encoder=text, noise=noise, seed=seed)
    source = open_source(f"synthetic:seed={seed},frames=120,width=160,height=120,lap=120")
    result = map_scene(source, region_encoder=encoder, volume_params=VolumeParams(voxel_size_m=0.04))
    surface = result.volume.extract_points()
    points = collections.Counter(surface.keys.tolist())
    least = default_min_region_points()
    keys = [int(k) for k in result.dictionary.keys if points.get(int(k), 0) >= least]
    emb = np.stack([result.dictionary.embedding(k) for k in keys])
    cats = list(CATEGORIES)
    cat_emb = region_text_embeddings(text.encode, cats)
    unit = lambda a: a / np.linalg.norm(a, axis=1, keepdims=True)  # noqa: E731
    closest = (unit(emb) @ unit(cat_emb).T).argmax(1)
    labels = [result.dictionary.label(k) or "" for k in keys]
    return emb, [lab if cats[c] == lab else "?" for lab, c in zip(labels, closest, strict=True)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="one seed per noise profile")
    parser.add_argument("--full", action="store_true", help="(bench/run_all.py) the default run")
    args = parser.parse_args()
    seeds = (1,) if args.quick else (1, 2, 3)
    text = make_text_encoder("minilm", device="cpu")
    scorer = RelevancyScorer(text)
    cal = scorer.calibration
    names = list(CATEGORIES)
    vectors = {}
    for name in names:
        parts = [name, *relevancy_texts(name)]
        vectors[name] = dict(zip(parts, text.encode(parts), strict=True))
    print(f"built-in room, MiniLM, 120 frames 160x120, 4 cm, seeds {', '.join(map(str, seeds))}; the room's "
          f"{len(names)} category names asked; regions with >= {default_min_region_points()} surface points")
    print("| noise | rule | instances kept | wrong matches per name | lowest share of an instance |")
    print("|---|---|---|---|---|")
    for noise in ("off", "standard"):
        kept = collections.Counter()
        wrong = collections.Counter()
        instances = 0
        lowest = 1.0
        for seed in seeds:
            emb, cats = room_regions(text, noise, seed)
            for name in names:
                margin = scorer.text_margins(name, vectors[name], emb)
                mine = np.array([c == name for c in cats])
                others = np.array([c not in ("?", name, *SAME.get(name, ())) for c in cats])
                instances += int(mine.sum())
                if mine.any() and margin.max() > 0:
                    lowest = min(lowest, float((margin[mine] / margin.max()).min()))
                rules = {share: match_mask(margin, threshold=cal.threshold, temperature=cal.temperature,
                                           best_share=share) for share in SHARES}
                rules.update({f"gap {g}": rules[None] & (margin >= margin.max() - g) for g in GAPS})
                for rule, ok in rules.items():
                    kept[rule] += int((ok & mine).sum())
                    wrong[rule] += int((ok & others).sum())
        asked = len(names) * len(seeds)
        for key in [*SHARES, *(f"gap {g}" for g in GAPS)]:
            if key is None:
                rule = "v8: threshold only (baseline)"
            elif isinstance(key, str):
                rule = f"within {key[4:]} of the best margin (not kept)"
            else:
                rule = f"share of the best {key}" + (" (v9)" if key == cal.best_share else "")
            print(f"| {noise} | {rule} | {kept[key]} / {instances} ({kept[key] / max(instances, 1):.3f}) | "
                  f"{wrong[key] / asked:.2f} ({wrong[key] / max(wrong[None], 1):.2f}x v8) | {lowest:.3f} |")


if __name__ == "__main__":
    main()
