"""Word lists that calibrate and test ``match`` (see :mod:`openfusion.mapping.relevancy`).

Each list pairs a query text with the synthetic scene's categories
(:data:`openfusion.sources.synthetic.CATEGORIES`) it refers to; an empty tuple means the text names
nothing in the scene ("zebra"), so any match is a false one.

History (each held-out list is never edited after its results are seen; ``bench/bench_relevancy.py``,
``tests/unit/test_relevancy.py``):

1. ``CALIBRATION`` (grown to 149 queries before anything was measured on the new ones) chose the
   plain-LERF method and, later, v2 (query categories) and its threshold.
2. ``HELD_OUT`` was written separately and never used to choose a threshold, but its misses were
   looked at while the plain-LERF method was tuned.
3. ``HELD_OUT_2`` was written from scratch and committed before any measurement on it; v2 was
   judged on it (MiniLM 0.934 / 0.891).
4. With all three seen, they became the development lists: pooled, they chose v3 ("appliance"
   among the query categories) and its thresholds. ``HELD_OUT_3`` was written from scratch and
   committed before any measurement on it (with more near-domain unrelated texts: household
   things the room lacks); v3 is judged on it, measured once (MiniLM 0.810 / 0.817, docs/CLI.md).
   A method chosen after that needs a new list written before it is measured.
5. ``HELD_OUT_4`` was written from scratch and committed before any measurement on it, for a v4
   (the ScanNet200 class names as query-side contrasts where they do not describe the region),
   which was chosen on the four seen lists and then judged on it: MiniLM 0.869 / 0.737 against v3's
   0.825 / 0.808 on the same list, and "chair" no longer matched "wooden chair" in the hash
   space, so v4 was not shipped (docs/CLI.md). v3 stays; ``HELD_OUT_4`` is its second judged list.
6. With all five seen, all five are development lists: pooled, they chose v5 (v3 and the head
   rule of :mod:`openfusion.mapping.query_head`) and its thresholds, and leaving one list out
   measured it (docs/CLI.md). ``HELD_OUT_5`` was written blind on 2026-11-26 by someone who ran
   no model and saw no result, benchmark or relevancy code (only this file, for the format and to
   keep texts disjoint), and committed before any measurement on it, while v5 was developed; v5
   was judged on it once: MiniLM 0.904 / 0.629 (v3 as shipped 0.729 / 0.743 on the same list).
7. With six seen, the six are the development lists: they chose v6 (the head rule's name cosine
   0.8) and its thresholds. ``HELD_OUT_6`` was written blind the same way and committed before v6
   was measured on it; v6 is judged on it (MiniLM 0.853 / 0.563, v3 as shipped 0.701 / 0.728;
   docs/CLI.md). v6's threshold (precision first) answered "no match" to "something to sit on"
   in the built-in room, so v7 keeps its scoring and takes the threshold at the best F1 of the
   seven seen lists; ``HELD_OUT_7`` was written blind the same way and committed before v7 was
   measured on it, and judges it (MiniLM 0.868 / 0.617, v3 as shipped 0.811 / 0.682).
8. With eight seen, the eight are the development lists: they chose v8 (regions embedded with
   captions, :mod:`openfusion.encoders.captions`; the head rule's name cosine 0.7) and its
   thresholds. ``HELD_OUT_8`` was written blind the same way and committed before anything was
   measured on it; v8 and v7 as shipped were measured on it once (MiniLM 0.875 / 0.733 against
   0.880 / 0.629; docs/CLI.md). A method chosen after that needs a new list written before it is
   measured.

The blind lists (``HELD_OUT_5`` to ``HELD_OUT_8``) are in :mod:`openfusion.testing.word_lists_blind`.

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

#: Written after CALIBRATION and never used to choose a threshold before v3; since v3 a development list.
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
#: scratch and committed before any measurement on it; v2 was judged on it. Since v3 a development list
#: (pooled with the two above, it chose v3's threshold).
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

#: Written after HELD_OUT_2's results had been seen, from scratch and committed before any
#: measurement on it (no method has been scored on it while it was written); never used to choose
#: anything. The ``match`` target of v3 is judged on this list. Its unrelated texts include household
#: things the synthetic room does not have ("a bathtub", "the refrigerator", "stairs", "curtains",
#: "a television"), some naming a category's part or neighbour ("wall clock", "ceiling fan",
#: "a traffic light"): they must not match.
HELD_OUT_3: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names, other forms
    ("the walls", ("wall",)), ("a floor", ("floor",)), ("the doors", ("door",)), ("the windows", ("window",)),
    ("the picture", ("picture",)), ("the beds", ("bed",)), ("the pillows", ("pillow",)), ("some pillows", ("pillow",)),
    ("the couch", ("sofa",)), ("the bookshelves", ("bookshelf",)), ("the cabinets", ("cabinet",)),
    ("my desk", ("desk", "table")), ("the monitors", ("monitor",)), ("the office chair", ("office chair", "chair")),
    ("office chairs", ("office chair", "chair")), ("the table", ("table", "desk")), ("this chair", ("chair", "office chair")),
    ("that lamp", ("lamp",)), ("the plants", ("plant",)), ("a trash can", ("trash can",)),
    # synonyms
    ("sleeper sofa", ("sofa",)), ("chesterfield", ("sofa",)), ("leather couch", ("sofa",)),
    ("two-seater sofa", ("sofa",)), ("king size bed", ("bed",)), ("single bed", ("bed",)), ("bedstead", ("bed",)),
    ("bed pillow", ("pillow", "bed")), ("feather pillow", ("pillow",)), ("book shelf", ("bookshelf",)),
    ("wall shelf", ("bookshelf", "cabinet")), ("cupboards", ("cabinet",)), ("closet", ("cabinet",)),
    ("kitchen cabinet", ("cabinet",)), ("storage unit", ("cabinet", "bookshelf")), ("drawers", ("cabinet",)),
    ("writing table", ("desk", "table")), ("work desk", ("desk", "table")), ("standing desk", ("desk", "table")),
    ("led monitor", ("monitor",)), ("pc monitor", ("monitor",)), ("display screen", ("monitor",)),
    ("widescreen monitor", ("monitor",)), ("ergonomic chair", ("office chair", "chair")),
    ("executive chair", ("office chair", "chair")), ("swivel seat", ("office chair", "chair")),
    ("end table", ("table", "desk")), ("round table", ("table", "desk")), ("wooden table", ("table", "desk")),
    ("kitchen chair", ("chair", "office chair")), ("folding chair", ("chair", "office chair")),
    ("plastic chair", ("chair", "office chair")), ("bedside lamp", ("lamp",)), ("standing lamp", ("lamp",)),
    ("lamp light", ("lamp",)), ("succulent", ("plant",)), ("cactus", ("plant",)), ("ficus", ("plant",)),
    ("potted palm", ("plant",)), ("bonsai", ("plant",)), ("house plant", ("plant",)), ("trashcan", ("trash can",)),
    ("bin", ("trash can",)), ("wastebasket", ("trash can",)), ("garbage", ("trash can",)),
    ("trash bin", ("trash can",)), ("wastepaper basket", ("trash can",)), ("art print", ("picture",)),
    ("canvas painting", ("picture",)), ("portrait", ("picture",)), ("family photo", ("picture",)),
    ("picture frame", ("picture",)), ("window pane", ("window",)), ("window frame", ("window",)),
    ("door frame", ("door",)), ("wooden door", ("door",)), ("exit door", ("door",)), ("ground", ("floor",)),
    ("floor tiles", ("floor",)), ("parquet", ("floor",)), ("hardwood floor", ("floor",)),
    ("painted wall", ("wall",)), ("plaster wall", ("wall",)), ("ceiling panels", ("ceiling",)),
    # paraphrases
    ("something to rest on", (*SEAT, "bed")), ("a place to keep my clothes", ("cabinet",)),
    ("a seat at the desk", ("office chair", "chair")), ("a place to eat dinner", ("table", "desk")),
    ("the screen I look at while working", ("monitor",)), ("something to throw trash in", ("trash can",)),
    ("a light for the desk", ("lamp",)), ("the thing above my head", ("ceiling",)),
    ("what I stand on", ("floor",)), ("the glass in the wall", ("window",)),
    ("a place to lay my head", ("pillow", "bed")), ("where I put my books", ("bookshelf",)),
    ("something green that grows", ("plant",)), ("a place to nap", ("bed", "sofa")),
    ("where I can store files", ("cabinet",)), ("the opening to the next room", ("door",)),
    ("something to lean back on", SEAT), ("a table for the computer", ("desk", "table")),
    ("a photo hanging up", ("picture",)), ("the wall that holds the door", ("wall", "door")),
    # unrelated: household things the room does not have
    ("a bathtub", ()), ("the refrigerator", ()), ("stairs", ()), ("a toilet", ()), ("kitchen sink", ()),
    ("microwave oven", ()), ("a fireplace", ()), ("a mirror", ()), ("wall clock", ()), ("a rug", ()),
    ("curtains", ()), ("a television", ()), ("a laptop", ()), ("a keyboard", ()), ("a printer", ()),
    ("a piano", ()), ("a ceiling fan", ()), ("a vase", ()), ("a coat hanger", ()), ("dishwasher", ()),
    # unrelated: elsewhere
    ("owl", ()), ("hippopotamus", ()), ("squirrel", ()), ("shark", ()), ("butterfly", ()), ("pancake", ()),
    ("cucumber", ()), ("taco", ()), ("cheese", ()), ("cherry", ()), ("tram", ()), ("yacht", ()),
    ("hot air balloon", ()), ("jet ski", ()), ("snowflake", ()), ("beach", ()), ("cliff", ()), ("swamp", ()),
    ("meteor", ()), ("accordion", ()), ("flute", ()), ("banjo", ()), ("football", ()), ("golf club", ()),
    ("skateboard", ()), ("a pair of sneakers", ()), ("an umbrella", ()), ("a wristwatch", ()),
    ("a traffic light", ()), ("a lighthouse", ()), ("a herd of elephants", ()), ("democracy", ()),
    ("pepperoni pizza", ()),
)

#: Written after HELD_OUT_3's results had been seen, from scratch and committed before any
#: measurement on it and before the household vocabulary of v4 was written; never used to choose
#: anything. v4 is judged on this list. Its unrelated texts include about 30 household things the
#: synthetic room does not have, many next to one of its categories ("window blinds", "a light
#: switch", "a desk fan", "a laundry basket", "a blanket"): they must not match.
HELD_OUT_4: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names, other forms
    ("this wall", ("wall",)), ("the floors", ("floor",)), ("the ceilings", ("ceiling",)), ("that door", ("door",)),
    ("this window", ("window",)), ("some pictures", ("picture",)), ("my bed", ("bed",)), ("that pillow", ("pillow",)),
    ("this sofa", ("sofa",)), ("that bookshelf", ("bookshelf",)), ("this cabinet", ("cabinet",)),
    ("that desk", ("desk", "table")), ("this monitor", ("monitor",)), ("my office chair", ("office chair", "chair")),
    ("that table", ("table", "desk")), ("those chairs", ("chair", "office chair")), ("this lamp", ("lamp",)),
    ("my plant", ("plant",)), ("that trash can", ("trash can",)), ("the trash cans", ("trash can",)),
    # synonyms
    ("davenport", ("sofa",)), ("corner sofa", ("sofa",)), ("velvet couch", ("sofa",)), ("queen bed", ("bed",)),
    ("twin bed", ("bed",)), ("cot", ("bed",)), ("platform bed", ("bed",)), ("bolster", ("pillow",)),
    ("sleeping pillow", ("pillow",)), ("decorative pillow", ("pillow", "sofa")), ("bookcases", ("bookshelf",)),
    ("wooden bookshelf", ("bookshelf",)), ("tall bookcase", ("bookshelf",)), ("storage cupboard", ("cabinet",)),
    ("cabinetry", ("cabinet",)), ("file cabinet", ("cabinet",)), ("armoire", ("cabinet",)),
    ("locker", ("cabinet",)), ("corner desk", ("desk", "table")), ("student desk", ("desk", "table")),
    ("display monitor", ("monitor",)), ("lcd monitor", ("monitor",)), ("flat panel display", ("monitor",)),
    ("second screen", ("monitor",)), ("revolving chair", ("office chair", "chair")),
    ("mesh desk chair", ("office chair", "chair")), ("side chair", ("chair", "office chair")), ("bar stool", SEAT),
    ("upholstered chair", SEAT), ("rocking chair", ("chair", "office chair")),
    ("dinner table", ("table", "desk")), ("glass table", ("table", "desk")), ("nightstand", ("table", "cabinet")),
    ("reading lamp", ("lamp",)), ("night lamp", ("lamp",)), ("pendant lamp", ("lamp",)), ("monstera", ("plant",)),
    ("pot plant", ("plant",)), ("spider plant", ("plant",)), ("greenery", ("plant",)), ("foliage", ("plant",)),
    ("garbage pail", ("trash can",)), ("waste can", ("trash can",)), ("trash receptacle", ("trash can",)),
    ("framed painting", ("picture",)), ("wall hanging", ("picture",)), ("photo print", ("picture",)),
    ("glass pane", ("window",)), ("casement window", ("window",)), ("interior door", ("door",)),
    ("sliding door", ("door",)), ("hinged door", ("door",)), ("tiled floor", ("floor",)),
    ("laminate flooring", ("floor",)), ("concrete floor", ("floor",)), ("partition wall", ("wall",)),
    ("brick wall", ("wall",)), ("plaster ceiling", ("ceiling",)), ("overhead ceiling", ("ceiling",)),
    # paraphrases
    ("a place to do my homework", ("desk", "table")), ("art that hangs on a wall", ("picture",)),
    ("where I sleep at night", ("bed",)), ("a spot to sit and read", SEAT), ("what is overhead", ("ceiling",)),
    ("where the light comes through", ("window",)), ("something that brightens a dark corner", ("lamp",)),
    ("a box for waste", ("trash can",)), ("a container for rubbish", ("trash can",)),
    ("a living thing in a pot", ("plant",)), ("the furniture where I keep dishes", ("cabinet",)),
    ("a place to stack books", ("bookshelf",)), ("somewhere to relax with friends", ("sofa",)),
    ("a seat that spins", ("office chair", "chair")), ("the screen showing my code", ("monitor",)),
    ("the surface where I eat", ("table", "desk")), ("what I walk through to enter", ("door",)),
    ("the side of the room", ("wall",)), ("the bottom of the room", ("floor",)),
    ("a soft thing on the bed", ("pillow", "bed")),
    # unrelated: household things the room does not have
    ("a blender", ()), ("a toaster", ()), ("an electric kettle", ()), ("a frying pan", ()), ("a coffee maker", ()),
    ("a vacuum cleaner", ()), ("an ironing board", ()), ("a bath towel", ()), ("a shower curtain", ()),
    ("a doormat", ()), ("window blinds", ()), ("a radiator", ()), ("a smoke detector", ()), ("a light switch", ()),
    ("a doorbell", ()), ("a shoe rack", ()), ("a calendar", ()), ("a loudspeaker", ()), ("a game console", ()),
    ("a wifi router", ()), ("a desk fan", ()), ("a space heater", ()), ("an air conditioner", ()),
    ("a laundry basket", ()), ("a blanket", ()), ("a candle", ()), ("a hair dryer", ()), ("a tablet computer", ()),
    ("a projector", ()),
    # unrelated: elsewhere
    ("raccoon", ()), ("walrus", ()), ("peacock", ()), ("lobster", ()), ("hedgehog", ()), ("croissant", ()),
    ("broccoli", ()), ("dumplings", ()), ("popcorn", ()), ("lemon", ()), ("ferry", ()), ("pickup truck", ()),
    ("glider", ()), ("snowmobile", ()), ("comet", ()), ("oasis", ()), ("geyser", ()), ("prairie", ()),
    ("clarinet", ()), ("bagpipes", ()), ("tuba", ()), ("hockey stick", ()), ("bowling ball", ()),
    ("a pair of skis", ()), ("a bicycle helmet", ()), ("a parking meter", ()), ("a windmill", ()), ("freedom", ()),
    ("a flock of pigeons", ()),
)
