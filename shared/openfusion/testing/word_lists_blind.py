"""The word lists written blind (``HELD_OUT_5`` to ``HELD_OUT_8``; see
:mod:`openfusion.testing.word_lists` for the format, the history and how each was used).

Each was written by someone who ran no model and saw no result, benchmark or relevancy code (only
the lists already written, for the format and to keep the texts disjoint), and committed before
any measurement on it. They live apart from the earlier lists only to keep each file short.
"""

from __future__ import annotations

from openfusion.testing.word_lists import SEAT

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
