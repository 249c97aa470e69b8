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
   measured on it, and judges it (MiniLM 0.868 / 0.617, v3 as shipped 0.811 / 0.682). A method
   chosen after that needs a new list written before it is measured.

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


#: Written blind on 2026-11-26 (no model run, no result, benchmark or relevancy code seen; only this
#: file, for the format and to keep the texts disjoint) and committed before any measurement on it.
#: 168 texts: 105 positives (21 class names in other forms, 46 synonyms and specific kinds over all
#: 19 categories, 38 paraphrases) and 63 unrelated (32 household / office things the room lacks, 12
#: of them "<room category> <other thing>" compounds such as "door key"; 31 from elsewhere, 4 of them
#: compounds that start with a room category: "table tennis", "monitor lizard", "cabinet minister",
#: "chair lift").
HELD_OUT_5: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names, other forms
    ("these walls", ("wall",)), ("that floor", ("floor",)), ("this ceiling", ("ceiling",)), ("these doors", ("door",)),
    ("Those Windows", ("window",)), ("this picture", ("picture",)), ("that bed", ("bed",)), ("My Pillow", ("pillow",)),
    ("That Sofa", ("sofa",)), ("these bookshelves", ("bookshelf",)), ("that cabinet", ("cabinet",)),
    ("This Desk", ("desk", "table")), ("that monitor", ("monitor",)), ("this office chair", ("office chair", "chair")),
    ("The Tables", ("table", "desk")), ("that chair", ("chair", "office chair")), ("the lamps", ("lamp",)),
    ("this plant", ("plant",)), ("this trash can", ("trash can",)), ("some plants", ("plant",)),
    ("the desks", ("desk", "table")),
    # synonyms and specific kinds
    ("accent wall", ("wall",)), ("load-bearing wall", ("wall",)), ("carpeted floor", ("floor",)),
    ("vinyl flooring", ("floor",)), ("painted ceiling", ("ceiling",)), ("suspended ceiling", ("ceiling",)),
    ("oak door", ("door",)), ("office door", ("door",)), ("sash window", ("window",)), ("picture window", ("window",)),
    ("oil painting", ("picture",)), ("watercolor painting", ("picture",)), ("framed print", ("picture",)),
    ("guest bed", ("bed",)), ("daybed", ("bed", "sofa")), ("memory foam pillow", ("pillow",)),
    ("down pillow", ("pillow",)), ("scatter cushion", ("pillow", "sofa")), ("three-seater couch", ("sofa",)),
    ("sofa bed", ("sofa", "bed")), ("white bookcase", ("bookshelf",)), ("shelving unit", ("bookshelf", "cabinet")),
    ("credenza", ("cabinet",)), ("drawer unit", ("cabinet",)), ("metal cabinet", ("cabinet",)),
    ("wooden desk", ("desk", "table")), ("computer table", ("desk", "table")), ("L-shaped desk", ("desk", "table")),
    ("curved monitor", ("monitor",)), ("external display", ("monitor",)), ("PC screen", ("monitor",)),
    ("office seat", ("office chair", "chair")), ("adjustable desk chair", ("office chair", "chair")),
    ("square table", ("table", "desk")), ("oak table", ("table", "desk")), ("low table", ("table", "desk")),
    ("armless chair", ("chair", "office chair")), ("straight-backed chair", ("chair", "office chair")),
    ("torchiere lamp", ("lamp",)), ("bedside light", ("lamp",)), ("rubber plant", ("plant",)),
    ("snake plant", ("plant",)), ("peace lily", ("plant",)), ("pedal bin", ("trash can",)),
    ("wastepaper bin", ("trash can",)), ("trash container", ("trash can",)),
    # paraphrases
    ("what the pictures hang on", ("wall",)), ("the upright sides around the room", ("wall",)),
    ("what the furniture stands on", ("floor",)), ("the surface I vacuum", ("floor",)),
    ("what I see when I look up", ("ceiling",)), ("the top of the room", ("ceiling",)),
    ("the thing you knock on before entering", ("door",)), ("how I get into the room", ("door",)),
    ("where I can see the sky from", ("window",)), ("the thing I open for fresh air", ("window",)),
    ("a decoration hanging on the wall", ("picture",)), ("an image in a frame", ("picture",)),
    ("the piece of furniture for sleeping", ("bed",)), ("the thing with sheets and a mattress", ("bed",)),
    ("the soft thing under my head at night", ("pillow",)), ("something soft to lean against", ("pillow", "sofa")),
    ("a long padded seat for several people", ("sofa",)), ("somewhere the whole family can sit together", ("sofa",)),
    ("where the novels are kept", ("bookshelf",)), ("shelves for my book collection", ("bookshelf",)),
    ("storage furniture with doors", ("cabinet",)), ("a cupboard with drawers for papers", ("cabinet",)),
    ("the surface the monitor sits on", ("desk", "table")), ("somewhere to write a letter", ("desk", "table")),
    ("the thing that shows my computer's output", ("monitor",)), ("the screen I read emails on", ("monitor",)),
    ("the chair I sit in at my desk", ("office chair", "chair")), ("a seat that rolls around the room", ("office chair", "chair")),
    ("somewhere to set down my coffee mug", ("table", "desk")), ("somewhere to play a board game", ("table", "desk")),
    ("a seat for one person", ("chair", "office chair")), ("something with a backrest to sit on", SEAT),
    ("what I switch on when it gets dark", ("lamp",)), ("a light with a shade", ("lamp",)),
    ("something I need to water", ("plant",)), ("a bit of nature indoors", ("plant",)),
    ("where I toss empty wrappers", ("trash can",)), ("the container for waste paper", ("trash can",)),
    # unrelated: household / office things the room does not have ("<room category> <other thing>" first)
    ("door key", ()), ("window cleaner", ()), ("lamp oil", ()), ("desk organizer", ()), ("bookshelf speaker", ()),
    ("wall socket", ()), ("floor polish", ()), ("plant fertilizer", ()), ("bed bugs", ()), ("picture hook", ()),
    ("table salt", ()), ("pillow fight", ()),
    ("a curtain rod", ()), ("venetian blinds", ()), ("a stapler", ()), ("a computer mouse", ()), ("a mouse pad", ()),
    ("a bath mat", ()), ("a coat rack", ()), ("a fire sprinkler", ()), ("a thermostat", ()), ("a towel rail", ()),
    ("a bathroom sink", ()), ("a cutting board", ()), ("a dish rack", ()), ("a toothbrush", ()), ("a gas stove", ()),
    ("a paper shredder", ()), ("a whiteboard", ()), ("an alarm clock", ()), ("an aquarium", ()), ("a dehumidifier", ()),
    # unrelated: elsewhere
    ("koala", ()), ("otter", ()), ("badger", ()), ("moose", ()), ("pelican", ()), ("seahorse", ()),
    ("avocado", ()), ("pretzel", ()), ("omelette", ()), ("ramen", ()), ("cupcake", ()), ("tugboat", ()),
    ("monorail", ()), ("forklift", ()), ("go-kart", ()), ("sand dune", ()), ("a lagoon", ()), ("coral reef", ()),
    ("xylophone", ()), ("ukulele", ()), ("harmonica", ()), ("a rugby ball", ()), ("a surfboard", ()),
    ("boxing gloves", ()), ("gravity", ()), ("nostalgia", ()), ("justice", ()), ("table tennis", ()),
    ("monitor lizard", ()), ("cabinet minister", ()), ("chair lift", ()),
)


#: Written blind on 2026-11-26 (no model run; no result, benchmark, test, doc or relevancy code
#: seen; only this file, for the format and to keep the texts disjoint) and committed before any
#: measurement on it. 163 texts: 103 positives (20 class names in other forms, 46 synonyms and
#: specific kinds over all 19 categories, 37 paraphrases) and 60 unrelated (30 household / office
#: things the room lacks, 14 of them "<room category> <other thing>" compounds such as "wall safe";
#: 30 from elsewhere, 6 of them idioms or compounds built on a room category: "bedrock", "pillow
#: lava", "table mountain", "power plant", "debt ceiling", "window of opportunity"). Parts count as
#: the object ("doorknob" -> door).
HELD_OUT_6: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names, other forms (articles, determiners, possessives, position / size adjectives)
    ("the left wall", ("wall",)), ("the back wall", ("wall",)), ("the entire floor", ("floor",)),
    ("the room's ceiling", ("ceiling",)), ("the door on the right", ("door",)), ("the big window", ("window",)),
    ("the small picture", ("picture",)), ("your bed", ("bed",)), ("a couple of pillows", ("pillow",)),
    ("our sofa", ("sofa",)), ("the tall bookshelf", ("bookshelf",)), ("the corner cabinet", ("cabinet",)),
    ("her desk", ("desk", "table")), ("the left monitor", ("monitor",)),
    ("his office chair", ("office chair", "chair")), ("the nearest table", ("table", "desk")),
    ("any chair", ("chair", "office chair")), ("the lamp over there", ("lamp",)), ("the little plant", ("plant",)),
    ("our trash can", ("trash can",)),
    # synonyms and specific kinds (all 19 categories)
    ("interior wall", ("wall",)), ("dividing wall", ("wall",)),
    ("floor surface", ("floor",)),
    ("drop ceiling", ("ceiling",)), ("vaulted ceiling", ("ceiling",)),
    ("doorknob", ("door",)), ("door handle", ("door",)), ("swing door", ("door",)),
    ("windowsill", ("window",)), ("bay window", ("window",)),
    ("photo", ("picture",)), ("landscape painting", ("picture",)), ("framed picture", ("picture",)),
    ("headboard", ("bed",)), ("four-poster bed", ("bed",)),
    ("body pillow", ("pillow",)), ("throw cushion", ("pillow", "sofa")), ("sofa cushion", ("pillow", "sofa")),
    ("living room couch", ("sofa",)), ("chaise longue", SEAT),
    ("shelf", ("bookshelf", "cabinet")), ("book shelving", ("bookshelf",)),
    ("utility cabinet", ("cabinet",)), ("cabinet drawer", ("cabinet",)),
    ("work table", ("desk", "table")), ("drafting table", ("desk", "table")), ("executive desk", ("desk", "table")),
    ("gaming monitor", ("monitor",)), ("desktop display", ("monitor",)), ("monitor screen", ("monitor",)),
    ("office swivel chair", ("office chair", "chair")), ("drafting chair", ("office chair", "chair")),
    ("console table", ("table", "desk")), ("breakfast table", ("table", "desk")), ("tabletop", ("table", "desk")),
    ("stacking chair", ("chair", "office chair")), ("chair back", ("chair", "office chair")),
    ("desk light", ("lamp",)), ("uplighter", ("lamp",)), ("light bulb", ("lamp",)),
    ("pothos", ("plant",)), ("aloe vera", ("plant",)), ("fiddle-leaf fig", ("plant",)),
    ("rubbish can", ("trash can",)), ("refuse bin", ("trash can",)), ("trash basket", ("trash can",)),
    # paraphrases: function, place or appearance
    ("what separates this room from the next one", ("wall",)), ("the boundary of the room on every side", ("wall",)),
    ("where a dropped pen would land", ("floor",)), ("the part of the room I'd mop", ("floor",)),
    ("what is right above us", ("ceiling",)), ("the highest surface in the room", ("ceiling",)),
    ("the entrance to this room", ("door",)), ("what I close for some privacy", ("door",)),
    ("where daylight enters the room", ("window",)), ("the thing I look through to see the street", ("window",)),
    ("something framed to look at", ("picture",)), ("the art on display", ("picture",)),
    ("the furniture with a mattress and duvet", ("bed",)), ("the thing I make every morning", ("bed",)),
    ("the thing I fluff up before sleeping", ("pillow",)), ("something soft to hug", ("pillow",)),
    ("a long upholstered seat with cushions", ("sofa",)),
    ("furniture that holds books", ("bookshelf",)), ("where I'd look for something to read", ("bookshelf",)),
    ("furniture with doors to hide clutter", ("cabinet",)),
    ("where the spare office supplies are stored", ("cabinet", "bookshelf")),
    ("where I do my office work", ("desk", "table")), ("where the keyboard and mouse go", ("desk", "table")),
    ("what I stare at all day at work", ("monitor",)), ("the screen connected to my computer", ("monitor",)),
    ("the chair with wheels and armrests", ("office chair", "chair")),
    ("a seat whose height I can adjust", ("office chair", "chair")),
    ("something to put a plate on", ("table", "desk")), ("a flat surface on four legs", ("table", "desk")),
    ("somewhere for a guest to sit", SEAT), ("a single seat with four legs", ("chair", "office chair")),
    ("what I turn on to read at night", ("lamp",)), ("the thing that lights up my desk", ("lamp",)),
    ("something with green leaves", ("plant",)), ("something that needs sunlight and water", ("plant",)),
    ("where used tissues go", ("trash can",)), ("the thing I empty every week", ("trash can",)),
    # unrelated: household / office things the room does not have ("<room category> <other thing>" first)
    ("wall safe", ()), ("wall charger", ()), ("wall mirror", ()), ("floor rug", ()), ("floor mop", ()),
    ("floor plan", ()), ("doorstop", ()), ("window envelope", ()), ("bed tray", ()), ("desk phone", ()),
    ("table runner", ()), ("table saw", ()), ("lamp post", ()), ("chair mat", ()),
    ("a flat-screen TV", ()), ("a bulletin board", ()), ("a dartboard", ()), ("a mop bucket", ()), ("a bookend", ()),
    ("a power strip", ()), ("a webcam", ()), ("a hole punch", ()), ("a pair of headphones", ()),
    ("a paperweight", ()), ("an extension cord", ()), ("a cardboard box", ()), ("a globe", ()),
    ("a sewing machine", ()), ("a water cooler", ()), ("an umbrella stand", ()),
    # unrelated: elsewhere (animals, food, vehicles, nature, instruments, sport, abstract)
    ("armadillo", ()), ("chameleon", ()), ("woodpecker", ()), ("bison", ()), ("a swarm of bees", ()),
    ("guacamole", ()), ("cinnamon roll", ()), ("paella", ()), ("grapefruit", ()),
    ("hovercraft", ()), ("steamroller", ()), ("rickshaw", ()),
    ("mangrove", ()), ("tundra", ()), ("ocean floor", ()),
    ("mandolin", ()), ("didgeridoo", ()), ("cymbals", ()),
    ("a javelin", ()), ("pole vault", ()), ("a shuttlecock", ()),
    ("curiosity", ()), ("inflation", ()), ("friendship", ()),
    ("bedrock", ()), ("pillow lava", ()), ("table mountain", ()), ("power plant", ()), ("debt ceiling", ()),
    ("window of opportunity", ()),
)


#: Written blind on 2026-11-26 (no model run; no result, benchmark, test, doc or relevancy code
#: seen; only this file, for the format and to keep the texts disjoint), as ten kinds of users
#: would type to a robot in the room, and committed before any measurement on it. 168 texts: 107
#: positives (20 class names in other forms, among them "find the door" and the misspelling
#: "bookshelfs"; 50 synonyms and specific kinds over all 19 categories; 37 paraphrases) and 61
#: unrelated (31 household / office things the room lacks, 7 of them compounds on a room word such
#: as "a floor fan", "a baby monitor"; 30 from elsewhere).
HELD_OUT_7: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names, other forms (plurals, determiners, possessives, colour / position words, requests)
    ("show me the wall", ("wall",)), ("the floor under the bed", ("floor",)), ("the white ceiling", ("ceiling",)),
    ("find the door", ("door",)), ("where is the window", ("window",)), ("all the pictures", ("picture",)),
    ("the bed in the corner", ("bed",)), ("the pillow on the bed", ("pillow",)), ("the grey sofa", ("sofa",)),
    ("bookshelfs", ("bookshelf",)), ("the cabinet next to the bed", ("cabinet",)),
    ("the desk's surface", ("desk", "table")), ("both monitors", ("monitor",)),
    ("the black office chair", ("office chair", "chair")), ("the small table", ("table", "desk")),
    ("the chair by the desk", ("chair", "office chair")), ("every chair in the room", ("chair", "office chair")),
    ("the lamp by the sofa", ("lamp",)), ("the plant's leaves", ("plant",)),
    ("the trash can under the desk", ("trash can",)),
    # synonyms and specific kinds (all 19 categories; everyday words first, then less common ones)
    ("wallpaper", ("wall",)), ("concrete wall", ("wall",)),
    ("linoleum", ("floor",)), ("marble floor", ("floor",)), ("wood flooring", ("floor",)),
    ("ceiling tiles", ("ceiling",)), ("false ceiling", ("ceiling",)),
    ("entrance", ("door",)), ("room door", ("door",)), ("door hinge", ("door",)),
    ("window ledge", ("window",)), ("double-glazed window", ("window",)),
    ("drawing", ("picture",)), ("canvas print", ("picture",)), ("abstract painting", ("picture",)),
    ("kid's bed", ("bed",)), ("box spring", ("bed",)),
    ("cushions", ("pillow", "sofa")), ("pillow sham", ("pillow",)),
    ("love seat", ("sofa",)), ("fabric sofa", ("sofa",)),
    ("display shelves", ("bookshelf", "cabinet")), ("etagere", ("bookshelf",)),
    ("cabinet door", ("cabinet",)), ("hutch", ("cabinet",)), ("tallboy", ("cabinet",)),
    ("study table", ("desk", "table")), ("gaming desk", ("desk", "table")), ("secretary desk", ("desk", "table")),
    ("dual monitors", ("monitor",)), ("ultrawide monitor", ("monitor",)), ("VDU", ("monitor",)),
    ("wheelie chair", ("office chair", "chair")), ("spinny chair", ("office chair", "chair")),
    ("mesh office chair", ("office chair", "chair")),
    ("bedside table", ("table", "desk")), ("folding table", ("table", "desk")), ("occasional table", ("table", "desk")),
    ("easy chair", SEAT), ("metal chair", ("chair", "office chair")), ("chair leg", ("chair", "office chair")),
    ("wingback chair", SEAT),
    ("night light", ("lamp",)), ("lamp stand", ("lamp",)), ("anglepoise lamp", ("lamp",)),
    ("planter", ("plant",)), ("indoor tree", ("plant",)), ("yucca", ("plant",)),
    ("paper bin", ("trash can",)), ("swing bin", ("trash can",)),
    # paraphrases: function, place or appearance
    ("a place to hang a clock", ("wall",)),
    ("where the robot drives around", ("floor",)), ("what my feet touch", ("floor",)),
    ("what the light hangs from", ("ceiling",)), ("the inside of the roof", ("ceiling",)),
    ("how do I get out of here", ("door",)), ("something to walk through into the hallway", ("door",)),
    ("where I can check the weather outside", ("window",)), ("the glass I see the trees through", ("window",)),
    ("a photo of someone in a frame", ("picture",)), ("something nice to look at on the wall", ("picture",)),
    ("where I go when I'm tired", ("bed",)), ("where grandma takes her afternoon nap", ("bed", "sofa")),
    ("what I put my head on when I sleep", ("pillow", "bed")), ("the fluffy thing on the couch", ("pillow", "sofa")),
    ("the big seat where the family watches movies", ("sofa",)), ("a big cushy seat for three people", ("sofa",)),
    ("where I can find a novel to read", ("bookshelf",)), ("thing for put the books", ("bookshelf",)),
    ("where I keep folders locked away", ("cabinet",)), ("the box with doors for storing stuff", ("cabinet",)),
    ("the furniture the computer sits on", ("desk", "table")), ("where I sit to do paperwork", ("desk", "table")),
    ("the thing I watch videos on at my desk", ("monitor",)), ("the big screen on the desk", ("monitor",)),
    ("the chair that spins around", ("office chair", "chair")),
    ("the seat in front of the computer", ("office chair", "chair")),
    ("somewhere to put my cup of tea", ("table", "desk")), ("where we eat together", ("table", "desk")),
    ("where can I sit down", SEAT), ("something to sit on at the table", ("chair", "office chair")),
    ("something to light up the room at night", ("lamp",)), ("the thing with a bulb in it", ("lamp",)),
    ("the green thing in the pot", ("plant",)), ("something alive in the room", ("plant",)),
    ("where the empty bottle should go", ("trash can",)), ("what smells if I forget to empty it", ("trash can",)),
    # unrelated: household / office things the room does not have (compounds on a room category word first)
    ("a desk calendar", ()), ("a floor fan", ()), ("a bread bin", ()), ("a plant mister", ()),
    ("a trash compactor", ()), ("a wall-mounted TV", ()), ("a baby monitor", ()),
    ("a coffee mug", ()), ("a pen holder", ()), ("sticky notes", ()), ("a computer tower", ()),
    ("a phone charger", ()), ("a pair of scissors", ()), ("a tape dispenser", ()), ("an electrical outlet", ()),
    ("a coat hook", ()), ("a fuse box", ()), ("a bathroom scale", ()), ("a yoga mat", ()),
    ("a pair of slippers", ()), ("a teapot", ()), ("a rice cooker", ()), ("a spice rack", ()), ("a sink", ()),
    ("a shower head", ()), ("a soap dispenser", ()), ("a toilet brush", ()), ("a first aid kit", ()),
    ("a fire extinguisher", ()), ("a clothes drying rack", ()), ("a stack of papers", ()),
    # unrelated: elsewhere (animals, food, vehicles, nature, instruments, sport, abstract)
    ("llama", ()), ("ostrich", ()), ("platypus", ()), ("a sea turtle", ()), ("a golden retriever", ()),
    ("hummingbird", ()),
    ("falafel", ()), ("chocolate cake", ()), ("a bowl of cereal", ()), ("spring rolls", ()), ("a boiled egg", ()),
    ("a cable car", ()), ("a speedboat", ()), ("a double-decker bus", ()), ("a tandem bicycle", ()),
    ("stalactite", ()), ("a tide pool", ()), ("a salt marsh", ()), ("a snowy mountain peak", ()),
    ("oboe", ()), ("tambourine", ()), ("bongo drums", ()),
    ("a basketball hoop", ()), ("a frisbee", ()), ("a pair of ice skates", ()), ("a badminton net", ()),
    ("happiness", ()), ("mathematics", ()), ("the weather forecast", ()), ("Monday morning", ()),
)


#: Written blind on 2026-11-26 by someone who ran no model and saw no result, benchmark or relevancy
#: code (only this file), committed before any measurement on it: it judges the method chosen next.
HELD_OUT_8: tuple[tuple[str, tuple[str, ...]], ...] = (
    # class names, other forms (articles, possessives, adjectives, short commands, caps)
    ("the white wall", ("wall",)), ("floor here", ("floor",)), ("the ceiling above the bed", ("ceiling",)),
    ("the white door", ("door",)), ("go to door", ("door",)), ("window near the desk", ("window",)),
    ("the pretty picture", ("picture",)), ("the unmade bed", ("bed",)), ("bed pls", ("bed",)),
    ("the white pillows", ("pillow",)), ("the blue couch", ("sofa",)), ("the book shelf", ("bookshelf",)),
    ("the wooden cabinet", ("cabinet",)), ("go to the desk", ("desk", "table")), ("my monitor", ("monitor",)),
    ("the swivel chair", ("office chair", "chair")), ("the little table", ("table", "desk")),
    ("the red chair", ("chair", "office chair")), ("turn on the lamp", ("lamp",)), ("WHERE IS THE LAMP", ("lamp",)),
    ("the green plant", ("plant",)), ("the bin", ("trash can",)),
    # synonyms and other common names
    ("the side wall", ("wall",)), ("plasterboard wall", ("wall",)),
    ("the ground in here", ("floor",)), ("tile floor", ("floor",)),
    ("roof of room", ("ceiling",)), ("high ceiling", ("ceiling",)),
    ("the exit", ("door",)), ("the door knob", ("door",)),
    ("the window sill", ("window",)),
    ("the painting over the sofa", ("picture",)), ("that photo on the wall", ("picture",)),
    ("a framed poster", ("picture",)), ("image on wall", ("picture",)),
    ("queen size bed", ("bed",)),
    ("the pillow on the couch", ("pillow",)), ("a fluffy pillow", ("pillow",)),
    ("the settee", ("sofa",)),
    ("the bookcase in the corner", ("bookshelf",)),
    ("shelf for book", ("bookshelf",)),
    ("the cupboard", ("cabinet",)), ("the cabinet doors", ("cabinet",)),
    ("my computer desk", ("desk", "table")),
    ("the computer monitor", ("monitor",)), ("the screen on the desk", ("monitor",)),
    ("screen of computer", ("monitor",)),
    ("my desk chair", ("office chair", "chair")),
    ("the spinning chair", ("office chair", "chair")),
    ("the coffee table", ("table", "desk")),
    ("the table in the middle of the room", ("table", "desk")),
    ("a chair for my guest", ("chair", "office chair")),
    ("sit", ("chair", "office chair", "sofa")),
    ("the light", ("lamp",)), ("the bedside lamp", ("lamp",)),
    ("lamp for read", ("lamp",)),
    ("the potted plant", ("plant",)), ("the flowers", ("plant",)), ("tree in pot", ("plant",)),
    ("the trash", ("trash can",)), ("garbage can pls", ("trash can",)),
    ("the rubbish bin under the desk", ("trash can",)),
    # paraphrases of use, place or look
    ("the thing the picture is hanging on", ("wall",)),
    ("excuse me, which wall could I hang my grandson's drawing on?", ("wall",)),
    ("where I dropped my earring", ("floor",)), ("the part of the room I sweep", ("floor",)),
    ("the white thing way up over my head", ("ceiling",)), ("look up, the top of the room", ("ceiling",)),
    ("the way into the hallway", ("door",)), ("door for go outside", ("door",)), ("how do I leave the room", ("door",)),
    ("where the sunshine comes in", ("window",)), ("glass to see outside", ("window",)),
    ("what I open when it's too hot in here", ("window",)),
    ("the frame with my family in it", ("picture",)),
    ("where I go night night", ("bed",)), ("somewhere to sleep tonight", ("bed",)),
    ("where I lie down after a long day", ("bed", "sofa")),
    ("the soft thing for my head in bed", ("pillow", "bed")), ("something to prop my back up in bed", ("pillow",)),
    ("where we all sit to watch telly", ("sofa",)), ("a big soft seat for the whole family", ("sofa",)),
    ("where are my story books", ("bookshelf",)), ("the shelves with all the books", ("bookshelf",)),
    ("the furniture with drawers", ("cabinet",)), ("where I keep my socks", ("cabinet",)),
    ("where I do my homework", ("desk", "table")), ("the thing my computer is on", ("desk", "table")),
    ("what shows the picture from my computer", ("monitor",)), ("the screen I game on", ("monitor",)),
    ("the chair I spin on", ("office chair", "chair")), ("the seat with little wheels", ("office chair", "chair")),
    ("somewhere to put my coffee down", ("table", "desk")), ("where we put the snacks", ("table", "desk")),
    ("something to sit on at dinner", ("chair", "office chair")),
    ("a seat with four legs and a back", ("chair", "office chair")),
    ("I need to sit down", ("chair", "office chair", "sofa")),
    ("where can granny sit", ("chair", "office chair", "sofa")),
    ("something so I can see in the dark", ("lamp",)), ("the thing that makes light by the bed", ("lamp",)),
    ("the thing that needs watering", ("plant",)), ("something growing in a pot", ("plant",)),
    ("where do I throw this wrapper", ("trash can",)), ("throw away place", ("trash can",)),
    ("where the banana peel goes", ("trash can",)),
    # unrelated: household / office things the room does not have ("<room category> <other thing>" first)
    ("a wall calendar", ()), ("a window fan", ()), ("bed sheets", ()), ("a heart rate monitor", ()),
    ("a trash bag", ()), ("a picture book", ()), ("a wall outlet", ()), ("a desk stapler", ()),
    ("a microwave", ()), ("a toaster oven", ()), ("a slow cooker", ()), ("a saucepan", ()), ("a wine glass", ()),
    ("a toilet roll", ()), ("a plunger", ()), ("a laundry hamper", ()), ("a clothes iron", ()), ("a broom", ()),
    ("a dustpan", ()), ("a smart speaker", ()), ("a TV remote", ()), ("a video game controller", ()),
    ("a smartphone", ()), ("a treadmill", ()), ("a teddy bear", ()), ("a backpack", ()), ("a pair of glasses", ()),
    ("a bunch of keys", ()), ("a pencil sharpener", ()), ("find the fridge", ()), ("navigate to charging dock", ()),
    # unrelated: elsewhere (idioms and compounds on a room word first)
    ("Wall Street", ()), ("picture perfect", ()), ("trash talk", ()), ("table of contents", ()), ("riverbed", ()),
    ("Windows 11 update", ()), ("plant-based diet", ()), ("chairman of the board", ()),
    ("a hamster", ()), ("a tortoise", ()), ("a bald eagle", ()), ("a goldfish", ()), ("a bowl of soup", ()),
    ("a slice of toast", ()), ("french fries", ()), ("a cheeseburger", ()), ("a minivan", ()), ("a police car", ()),
    ("a sailing ship", ()), ("a pine forest", ()), ("a snowstorm", ()), ("an electric guitar", ()),
    ("a soccer ball", ()), ("loneliness", ()), ("the meaning of life", ()), ("go to the kitchen", ()),
    ("the supermarket", ()), ("my birthday party", ()), ("a dragon", ()),
)
