"""Evaluation class lists and the raw-category -> class tables (the one place they live).

The gt encoder embeds each region's *raw* category name ("office chair"); the protocol queries
the map with *class* names ("chair"). This module says which raw categories count as which
class, so that label mapping is decided here and nowhere else.
"""

from __future__ import annotations

import logging

logger = logging.getLogger(__name__)

#: NYU40 class names by id 1..40 (index = id - 1), spelled as in ScanNet's
#: ``scannetv2-labels.combined.tsv`` column ``nyu40class``. Id 0 = unannotated.
NYU40_CLASSES: tuple[str, ...] = (
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "blinds", "desk", "shelves", "curtain", "dresser", "pillow", "mirror",
    "floor mat", "clothes", "ceiling", "books", "refridgerator", "television", "paper", "towel",
    "shower curtain", "box", "whiteboard", "person", "night stand", "toilet", "sink", "lamp",
    "bathtub", "bag", "otherstructure", "otherfurniture", "otherprop",
)  # fmt: skip

#: Classes ``--exclude-background`` drops by default: ConceptGraphs' ``n_exclude=4`` set
#: ("other", floor, wall, ceiling), with NYU40's three "other*" classes standing for "other".
DEFAULT_BACKGROUND_CLASSES: tuple[str, ...] = (
    "wall", "floor", "ceiling", "otherstructure", "otherfurniture", "otherprop",
)  # fmt: skip

#: The synthetic world's evaluation classes (the text queries of a synthetic scene are the ones
#: present in it). Every raw category of :data:`openfusion.sources.synthetic.CATEGORIES` maps to
#: one of these (tests/test_eval_ground_truth.py checks it).
SYNTHETIC_CLASSES: tuple[str, ...] = (
    "wall", "floor", "ceiling", "door", "window", "picture", "bed", "pillow", "sofa", "bookshelf",
    "cabinet", "desk", "monitor", "chair", "table", "lamp", "plant", "trash can",
)  # fmt: skip

#: Raw category (as the synthetic world and the gt encoder name it) -> evaluation class, where
#: they differ. Categories not listed are their own class (see :func:`class_for_category`).
SYNTHETIC_CATEGORY_TO_CLASS: dict[str, str] = {
    "office chair": "chair",
}

_warned: set[str] = set()


def class_for_category(category: str) -> str:
    """The evaluation class of a raw category; unknown categories are their own class."""
    cat = category.strip().lower()
    cls = SYNTHETIC_CATEGORY_TO_CLASS.get(cat)
    if cls is not None:
        return cls
    if cat not in _warned and cat not in NYU40_CLASSES:
        _warned.add(cat)
        logger.info("raw category %r has no class mapping; it is evaluated as its own class", category)
    return cat
