"""Captions of known categories: what the gt encoder embeds for a region besides its name.

The gt encoder stands in for a real region encoder. A real one (CLIP on a crop, or a captioning
vision-language model whose caption a text model embeds, as ConceptGraphs and HOV-SG do) puts
more into a region's embedding than the bare class name: what the thing is for, where it stands,
what it looks like. A query such as "where I go when I'm tired" has nothing in common with the
word "bed" but much with "used for sleeping and lying down to rest". So for a category this table
knows, the gt encoder embeds (:func:`region_text_embeddings`)::

    region = unit( mean_i unit(e(caption_i)) + CAPTION_NAME_WEIGHT * unit(e(name)) )

and a category it does not know (a dataset's raw category outside the built-in room) by its name
alone, as before. Still one embedding per region: a query costs one dot product per region.

Provenance, so the relevancy figures stay honest: the captions were written on 2026-11-26 by
someone who saw no word list, result or code of this project, from the category names alone, as a
captioner would describe a typical instance (six per category: the name, other names, use, place,
look, and one everyday caption). They were not edited after any measurement. The weight 0.5 was
chosen on the development word lists (docs/CLI.md, "Relevancy and no match"), then judged once on
``HELD_OUT_8``. ``region_text="name"`` (an option of the gt encoder) embeds names only.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

#: The name's weight against the captions' mean (both unit vectors) in a region's embedding.
CAPTION_NAME_WEIGHT = 0.5

#: Six captions per category of the built-in room (module docstring for where they come from).
CAPTIONS: dict[str, tuple[str, ...]] = {
    'wall': (
        'a flat painted interior wall',
        'a room wall, partition or drywall surface',
        'divides rooms and holds hanging decorations and shelves',
        'a vertical surface enclosing the room on all sides',
        'a smooth white plaster surface, flat and vertical',
        'a plain white painted wall surface in a room',
    ),
    'floor': (
        'a hardwood floor of a room',
        'flooring, ground surface, carpet, tiles or laminate',
        'the surface people walk and stand on indoors',
        'the horizontal ground surface at the bottom of the room',
        'flat planks of wood, tiles or carpet covering the ground',
        'a polished wooden floor surface you walk on',
    ),
    'ceiling': (
        'a white ceiling overhead in a room',
        'the ceiling, overhead surface or roof of the room',
        'covers the top of the room and holds light fixtures',
        'the flat surface high above at the top of the room',
        'a smooth white painted plaster surface overhead',
        'a plain white ceiling with a light fixture above',
    ),
    'door': (
        'a closed wooden door',
        'an interior door, doorway or entrance to a room',
        'opens and closes to let people enter and leave',
        'set into the wall in a frame at the room entrance',
        'a tall rectangular wooden panel with a handle and hinges',
        'a closed white wooden door with a metal door handle',
    ),
    'window': (
        'a glass window in a room',
        'a windowpane, casement or sliding glass window',
        'lets daylight and fresh air into the room',
        'set in an outside-facing frame, often with curtains or blinds',
        'clear glass panes in a rectangular white frame',
        'a bright window with glass panes showing the outside view',
    ),
    'picture': (
        'a framed picture hanging on the wall',
        'a painting, photograph, poster, print or wall art',
        'decorates the room and displays art or photos',
        'hung on the wall at eye level',
        'a flat rectangular image inside a thin wooden or metal frame',
        'a framed colorful painting decorating the wall',
    ),
    'bed': (
        'a double bed with a mattress',
        'a single, double or king size bed frame',
        'used for sleeping and lying down to rest',
        'in the bedroom with nightstands on either side',
        'a mattress on a frame with a headboard, sheets and blanket',
        'a made bed covered with a blanket and bedsheets',
    ),
    'pillow': (
        'a soft white pillow',
        'a cushion, throw pillow or bed pillow',
        'supports your head while sleeping or your back while sitting',
        'lying on a bed or sofa, against the headboard or backrest',
        'a soft rectangular fabric cushion stuffed with filling',
        'a fluffy white pillow with a cotton pillowcase',
    ),
    'sofa': (
        'a fabric sofa with cushions',
        'a couch, settee, loveseat or sectional',
        'used for sitting, relaxing and lounging with several people',
        'placed in the living room facing the television',
        'a long padded upholstered seat with armrests, backrest and cushions',
        'a comfortable gray couch with soft cushions for lounging',
    ),
    'bookshelf': (
        'a wooden bookshelf filled with books',
        'a bookcase, shelving unit or book rack',
        'used to store and display books and ornaments',
        'standing upright in a study or living room corner',
        'a tall open frame with several horizontal wooden shelves',
        'tall shelves packed with rows of colorful books',
    ),
    'cabinet': (
        'a wooden storage cabinet',
        'a cupboard, dresser, chest of drawers or sideboard',
        'stores clothes, dishes and household items out of sight',
        'standing along the side of a room or under a countertop',
        'a boxy wooden unit with drawers, hinged fronts and knobs',
        'a closed wooden cupboard with drawers and small handles',
    ),
    'desk': (
        'a wooden work desk',
        'a writing desk, computer desk or study desk',
        'used for working, studying, writing and using a computer',
        'in a home office or study, pushed against a wall',
        'a flat rectangular desktop on legs with drawers underneath',
        'a work desk with a keyboard, papers and a computer on top',
    ),
    'monitor': (
        'a flat computer monitor',
        'a computer screen, display or flat screen',
        'shows images and text from a computer for work',
        'placed on a workspace behind a keyboard and mouse',
        'a thin black flat screen rectangle on a stand',
        'a black computer screen on a stand, turned on or off',
    ),
    'office chair': (
        'a black office chair',
        'a swivel chair, desk chair or computer chair',
        'used for sitting while working at a computer',
        'pulled up at a desk in a home office',
        'a padded seat and backrest on a swivel base with wheels',
        'an adjustable rolling desk chair with armrests and casters',
    ),
    'table': (
        'a wooden dining table',
        'a coffee table, side table, kitchen or dining table',
        'used for eating meals, placing items and gathering around',
        'in the middle of the dining or living room, with seats around',
        'a flat wooden tabletop supported by four legs',
        'a round wooden table with a few items on top',
    ),
    'chair': (
        'a wooden dining chair',
        'a side chair, kitchen chair, stool or armchair',
        'used for sitting down, one person at a time',
        'placed around a dining table or in a corner',
        'a seat with a backrest and four legs, no wheels',
        'a simple wooden chair with four legs and a backrest',
    ),
    'lamp': (
        'a lamp with a fabric lampshade',
        'a reading light, bedside light or standing lamp',
        'provides light for reading and lighting up the room',
        'on a nightstand or standing in a corner of the room',
        'a lampshade on a slim stand with a light bulb',
        'a glowing lamp with a white shade giving warm light',
    ),
    'plant': (
        'a green potted indoor plant',
        'a houseplant, indoor plant, fern or small tree in a pot',
        'decorates the room and adds greenery and fresh air',
        'standing in a pot in a sunny corner of the room',
        'green leaves and stems growing from soil in a ceramic pot',
        'a leafy green houseplant in a white flower pot',
    ),
    'trash can': (
        'a small trash can',
        'a waste bin, garbage can, wastebasket or rubbish bin',
        'used for throwing away garbage, paper and waste',
        'on the ground in a corner or beside a workspace',
        'a round plastic or metal bin with an open top or lid',
        'a small plastic waste basket lined with a garbage bag',
    ),
}


def _unit(a: np.ndarray) -> np.ndarray:
    a = np.atleast_2d(np.asarray(a, np.float64))
    return a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)


def region_text_embeddings(
    encode: Callable[[list[str]], np.ndarray],
    categories: Sequence[str],
    *,
    captions: Mapping[str, Sequence[str]] | None = None,
    name_weight: float = CAPTION_NAME_WEIGHT,
) -> np.ndarray:
    """(k, d) float32 unit region embeddings of ``categories`` (module docstring): name and
    captions for a category in ``captions`` (default :data:`CAPTIONS`; ``{}``: names only), the
    name alone otherwise. ``encode`` is a text encoder's ``encode``; every distinct text is
    embedded once, in one call."""
    table = CAPTIONS if captions is None else captions
    names = list(categories)
    texts = list(dict.fromkeys([*names, *(c for n in names for c in table.get(n, ()))]))
    if not texts:
        return np.zeros((0, 0), np.float32)
    vec = dict(zip(texts, _unit(encode(texts)), strict=True))
    out = []
    for name in names:
        caps = table.get(name, ())
        v = vec[name] if not caps else np.mean([vec[c] for c in caps], axis=0) + name_weight * vec[name]
        out.append(_unit(v)[0])
    return np.stack(out).astype(np.float32)
