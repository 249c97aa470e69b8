"""Word lists that calibrate and test ``match`` (see :mod:`openfusion.mapping.relevancy`).

Each list pairs a query text with the synthetic scene's categories
(:data:`openfusion.sources.synthetic.CATEGORIES`) it refers to; an empty tuple means the text names
nothing in the scene ("zebra"), so any match is a false one. ``CALIBRATION`` (grown to 149
queries before anything was measured on the new ones) chose the relevancy formulation and the
per-space thresholds in :data:`openfusion.mapping.relevancy.CALIBRATIONS`. ``HELD_OUT`` was written
separately and never used to choose a threshold, but its misses were looked at while the earlier
method was tuned; ``HELD_OUT_2`` was then written from scratch and committed before any
measurement on it, and the target is judged on it (``HELD_OUT`` is the second figure). Neither
held-out list is edited after its results are seen (``bench/bench_relevancy.py``,
``tests/unit/test_relevancy.py``).

Three kinds of positives: the class names themselves, synonyms ("couch" -> sofa) and paraphrases
("something to sit on" -> chair, office chair or sofa). A query is right when the first region of
its answer that is a match is one of its categories (:func:`openfusion.mapping.relevancy.evaluate_match`).
"""

from __future__ import annotations

SEAT = ("chair", "office chair", "sofa")

#: (query text, categories it names) used to choose negatives, temperature and thresholds.
CALIBRATION: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names
    ("wall", ("wall",)), ("floor", ("floor",)), ("ceiling", ("ceiling",)), ("door", ("door",)),
    ("window", ("window",)), ("picture", ("picture",)), ("bed", ("bed",)), ("pillow", ("pillow",)),
    ("sofa", ("sofa",)), ("bookshelf", ("bookshelf",)), ("cabinet", ("cabinet",)), ("desk", ("desk",)),
    ("monitor", ("monitor",)), ("office chair", ("office chair", "chair")), ("table", ("table", "desk")),
    ("chair", ("chair", "office chair")), ("lamp", ("lamp",)), ("plant", ("plant",)),
    ("trash can", ("trash can",)),
    # synonyms
    ("couch", ("sofa",)), ("seat", SEAT), ("armchair", SEAT), ("computer screen", ("monitor",)),
    ("display", ("monitor",)), ("rubbish bin", ("trash can",)), ("garbage can", ("trash can",)),
    ("light", ("lamp",)), ("houseplant", ("plant",)), ("bookcase", ("bookshelf",)),
    ("cupboard", ("cabinet",)), ("painting", ("picture",)), ("cushion", ("pillow", "sofa")),
    ("mattress", ("bed",)), ("swivel chair", ("office chair", "chair")), ("writing desk", ("desk", "table")),
    ("dining table", ("table", "desk")), ("doorway", ("door",)),
    # paraphrases
    ("something to sit on", SEAT), ("a place to sleep", ("bed",)), ("where the books are", ("bookshelf",)),
    ("a bin for garbage", ("trash can",)), ("a screen for the computer", ("monitor",)),
    ("a green plant in a pot", ("plant",)), ("a framed picture on the wall", ("picture",)),
    # unrelated
    ("zebra", ()), ("volcano", ()), ("banana", ()), ("car", ()), ("elephant", ()), ("pizza", ()),
    ("guitar", ()), ("ocean", ()), ("mountain", ()), ("airplane", ()), ("bicycle", ()), ("giraffe", ()),
    ("spaceship", ()), ("tornado", ()), ("pineapple", ()), ("violin", ()), ("submarine", ()),
    ("dinosaur", ()), ("sandwich", ()), ("river", ()), ("helicopter", ()), ("lion", ()), ("glacier", ()),
    ("tractor", ()), ("a red sports car", ()), ("a herd of cows", ()), ("the moon", ()),
    # added later (written before any measurement with them), to choose on a larger list
    # class names, other forms
    ("the door", ("door",)), ("the window", ("window",)), ("a picture", ("picture",)), ("the bed", ("bed",)),
    ("the pillow", ("pillow",)), ("the sofa", ("sofa",)), ("a bookshelf", ("bookshelf",)),
    ("the cabinet", ("cabinet",)), ("a desk", ("desk", "table")), ("the monitor", ("monitor",)),
    ("the chair", ("chair", "office chair")), ("the lamp", ("lamp",)), ("the plant", ("plant",)),
    ("the trash can", ("trash can",)), ("the wall", ("wall",)), ("a ceiling", ("ceiling",)),
    # synonyms
    ("sectional sofa", ("sofa",)), ("futon", ("sofa", "bed")), ("bunk bed", ("bed",)), ("pillowcase", ("pillow",)),
    ("library shelf", ("bookshelf",)), ("storage cabinet", ("cabinet",)), ("sideboard", ("cabinet",)),
    ("study desk", ("desk", "table")), ("desktop monitor", ("monitor",)), ("flat screen", ("monitor",)),
    ("computer chair", ("office chair", "chair")), ("gaming chair", ("office chair", "chair")),
    ("side table", ("table", "desk")), ("wooden chair", ("chair", "office chair")), ("table lamp", ("lamp",)),
    ("light fixture", ("lamp",)), ("fern", ("plant",)), ("potted fern", ("plant",)),
    ("waste container", ("trash can",)), ("litter bin", ("trash can",)), ("photograph", ("picture",)),
    ("framed art", ("picture",)), ("window glass", ("window",)), ("bedroom door", ("door",)),
    ("floorboards", ("floor",)), ("wooden floor", ("floor",)), ("drywall", ("wall",)),
    ("ceiling of the room", ("ceiling",)),
    # paraphrases
    ("something soft for sleeping", ("pillow", "bed")), ("a place to lie down", ("bed", "sofa")),
    ("a table to write on", ("desk", "table")), ("where the trash goes", ("trash can",)),
    ("a light to read by", ("lamp",)), ("a flower in a pot", ("plant",)),
    ("the thing I open to leave the room", ("door",)), ("the glass that lets light in", ("window",)),
    ("a cupboard to store clothes", ("cabinet",)), ("a comfy seat for two people", ("sofa",)),
    ("a display for a computer", ("monitor",)), ("the surface I walk on", ("floor",)),
    # unrelated
    ("horse", ()), ("kiwi fruit", ()), ("snowman", ()), ("bridge", ()), ("castle", ()), ("trombone", ()),
    ("parrot", ()), ("sushi", ()), ("skyscraper", ()), ("motorboat", ()), ("cheetah", ()), ("cloud", ()),
    ("pyramid", ()), ("donut", ()), ("harp", ()), ("kite", ()), ("fire truck", ()),
    ("a field of sunflowers", ()), ("a stormy sea", ()), ("washing machine", ()), ("shower", ()), ("oven", ()),
)

#: Written after CALIBRATION and never used to choose anything: the list the figures are measured on.
HELD_OUT: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names, other forms
    ("walls", ("wall",)), ("the floor", ("floor",)), ("a door", ("door",)), ("windows", ("window",)),
    ("a bed", ("bed",)), ("pillows", ("pillow",)), ("a sofa", ("sofa",)), ("the bookshelf", ("bookshelf",)),
    ("cabinets", ("cabinet",)), ("the desk", ("desk", "table")), ("a monitor", ("monitor",)),
    ("chairs", ("chair", "office chair")), ("a lamp", ("lamp",)), ("plants", ("plant",)),
    ("trash", ("trash can",)), ("the ceiling", ("ceiling",)), ("a table", ("table", "desk")),
    # synonyms
    ("settee", ("sofa",)), ("stool", SEAT), ("desk chair", ("office chair", "chair")),
    ("computer monitor", ("monitor",)), ("screen", ("monitor",)), ("waste basket", ("trash can",)),
    ("dustbin", ("trash can",)), ("floor lamp", ("lamp",)), ("potted plant", ("plant",)),
    ("bookcase with books", ("bookshelf",)), ("shelves", ("bookshelf", "cabinet")), ("wardrobe", ("cabinet",)),
    ("poster", ("picture",)), ("photo frame", ("picture",)), ("artwork", ("picture",)),
    ("loveseat", ("sofa",)), ("workstation", ("desk",)), ("coffee table", ("table", "desk")),
    ("bedroom bed", ("bed",)), ("reading light", ("lamp",)), ("entrance door", ("door",)),
    # paraphrases
    ("somewhere to sit", SEAT), ("something to sleep on", ("bed",)), ("a place to put books", ("bookshelf",)),
    ("where to throw rubbish", ("trash can",)), ("a place to work at", ("desk", "table")),
    ("something that gives light", ("lamp",)), ("a comfortable couch", ("sofa",)),
    ("a soft pillow for the head", ("pillow",)), ("the glass window", ("window",)),
    # unrelated
    ("kangaroo", ()), ("earthquake", ()), ("strawberry", ()), ("truck", ()), ("whale", ()),
    ("hamburger", ()), ("trumpet", ()), ("desert", ()), ("waterfall", ()), ("motorcycle", ()),
    ("penguin", ()), ("rainbow", ()), ("satellite", ()), ("hurricane", ()), ("watermelon", ()),
    ("saxophone", ()), ("sailboat", ()), ("crocodile", ()), ("spaghetti", ()), ("forest", ()),
    ("train", ()), ("tiger", ()), ("iceberg", ()), ("bulldozer", ()), ("a blue racing bike", ()),
    ("a flock of sheep", ()), ("the sun", ()), ("octopus", ()), ("lightning", ()), ("tennis racket", ()),
)

#: Written after HELD_OUT's results had been seen (so HELD_OUT had informed earlier choices), from
#: scratch and committed before any measurement on it; never used to choose anything. The ``match``
#: target is judged on this list, with HELD_OUT as a second figure.
HELD_OUT_2: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names, other forms
    ("a wall", ("wall",)), ("floors", ("floor",)), ("ceilings", ("ceiling",)), ("doors", ("door",)),
    ("a window", ("window",)), ("pictures", ("picture",)), ("beds", ("bed",)), ("a pillow", ("pillow",)),
    ("sofas", ("sofa",)), ("bookshelves", ("bookshelf",)), ("a cabinet", ("cabinet",)),
    ("desks", ("desk", "table")), ("monitors", ("monitor",)), ("an office chair", ("office chair", "chair")),
    ("tables", ("table", "desk")), ("a chair", ("chair", "office chair")), ("lamps", ("lamp",)),
    ("a plant", ("plant",)), ("trash cans", ("trash can",)),
    # synonyms
    ("couches", ("sofa",)), ("divan", ("sofa",)), ("bed frame", ("bed",)), ("double bed", ("bed",)),
    ("throw pillow", ("pillow", "sofa")), ("book rack", ("bookshelf",)), ("shelving", ("bookshelf", "cabinet")),
    ("chest of drawers", ("cabinet",)), ("dresser", ("cabinet",)), ("filing cabinet", ("cabinet",)),
    ("office desk", ("desk", "table")), ("computer desk", ("desk", "table")), ("lcd screen", ("monitor",)),
    ("computer display", ("monitor",)), ("task chair", ("office chair", "chair")),
    ("rolling chair", ("office chair", "chair")), ("kitchen table", ("table", "desk")),
    ("dining chair", ("chair", "office chair")), ("desk lamp", ("lamp",)), ("lampshade", ("lamp",)),
    ("indoor plant", ("plant",)), ("flower pot", ("plant",)), ("waste bin", ("trash can",)),
    ("garbage bin", ("trash can",)), ("recycling bin", ("trash can",)), ("framed photo", ("picture",)),
    ("wall art", ("picture",)), ("windowpane", ("window",)), ("front door", ("door",)),
    ("flooring", ("floor",)), ("recliner", SEAT),
    # paraphrases
    ("a place to sit down", SEAT), ("something to lie on", ("bed", "sofa")),
    ("where I can put my laptop", ("desk", "table")), ("where to put the garbage", ("trash can",)),
    ("something that lights the room", ("lamp",)), ("a shelf full of books", ("bookshelf",)),
    ("a painting hanging on the wall", ("picture",)), ("a place to store things", ("cabinet", "bookshelf")),
    ("the computer screen on the desk", ("monitor",)), ("where I can look outside", ("window",)),
    ("the way out of the room", ("door",)), ("a cushion to rest my head on", ("pillow",)),
    ("a chair with wheels", ("office chair", "chair")), ("a leafy plant", ("plant",)),
    # unrelated
    ("camel", ()), ("tsunami", ()), ("blueberry", ()), ("bus", ()), ("dolphin", ()), ("burrito", ()),
    ("drum kit", ()), ("canyon", ()), ("volleyball", ()), ("scooter", ()), ("flamingo", ()),
    ("thunderstorm", ()), ("rocket", ()), ("avalanche", ()), ("mango", ()), ("cello", ()), ("canoe", ()),
    ("alligator", ()), ("lasagna", ()), ("jungle", ()), ("ambulance", ()), ("gorilla", ()), ("asteroid", ()),
    ("excavator", ()), ("a yellow school bus", ()), ("a pack of wolves", ()), ("the stars", ()),
    ("jellyfish", ()), ("baseball bat", ()), ("bathtub", ()), ("refrigerator", ()),
)
