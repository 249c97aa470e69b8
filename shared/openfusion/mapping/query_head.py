"""The head of a query text: the noun a region must be, for "wall clock", "a seat at the desk".

A text encoder embeds a phrase as a blend of its words, so "wall clock" lands next to the wall
and "a seat at the desk" next to the desk. Relevancy (:mod:`openfusion.mapping.relevancy`) asks
the head word to describe the region too. This module finds it with a few hand-written,
deterministic patterns: no parser with an English model can be installed offline (spaCy's and
NLTK's models download from GitHub), and English noun phrases in object queries are regular
enough for these rules:

1. lower-case, drop a trailing ``.?!``; drop a leading request or command ("go to", "take me
   to", "turn on", "show me", "find", "where is", "please": what a robot operator types around
   the thing, "go to the door") and, unless the text opens with a generic word (step 2: "how do I
   get out of here"), trailing fillers ("please", "pls", "here", "now"); drop leading
   determiners ("the", "a", "my", "this", ...) and quantities with their "of" ("a couple of", "a
   pair of", "a stack of");
2. a text that starts with a generic or question word ("something to sit on", "a place to
   sleep", "where I put my books", "the thing above my head") has no noun head: None;
3. cut a post-modifier: from the first preposition, relative pronoun or subject pronoun after
   the first word ("a seat | at the desk", "art | that hangs on a wall", "the screen | I look
   at"), or from an ``-ing`` / ``-ed`` word followed by one of them ("a painting | hanging on the
   wall");
4. the rest is the core noun phrase; its last word is the head ("wall clock" -> "clock",
   "a green plant" -> "plant");
5. a vague head ("thing", "item", "furniture": a word for any object of a room, "a soft thing
   on the bed") leaves the text whole: None.

:func:`query_head` returns (core, head, whether a post-modifier was cut), or None when there is
nothing to check: a generic text, a vague head, or a core of one word with nothing cut (the head
is the text itself). After a dropped command, a generic or vague rest is returned whole as the
core ("show me | something to sit on"), so the command's words do not count. The rules are
English-only and approximate ("chest of drawers" -> "chest"); ``tests/unit/test_query_head.py``
lists what they do.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_DETERMINERS = frozenset(
    "the a an this that these those my your our his her their its some any".split())
#: Words that start a text with no noun head (it describes a use or a place, not a thing).
_GENERIC = frozenset(
    "something somewhere someplace anything anywhere thing things place spot stuff object objects one "
    "where what which who how way".split())
#: Head words that name no kind of thing ("a soft thing on the bed"): nothing to check.
_VAGUE_HEADS = frozenset("thing things one ones stuff object objects item items piece kind sort type furniture".split())
#: Words that start a post-modifier (prepositions, relative and subject pronouns).
_POST = frozenset(
    "at for on in with from that which where who whose to by near under above over below beneath "
    "beside behind inside into onto of up full i you we he she they while when next".split())
#: Nouns of quantity or arrangement that take the thing after "of" ("a couple of pillows", "a pair
#: of chairs", "a stack of books"): they are dropped with their "of", as determiners are.
_QUANTITIES = frozenset("couple pair set bunch stack pile row group few lot lots number handful".split())
#: Leading requests and commands (word sequences), dropped before the noun phrase: "go to the
#: door" asks for the door. Longest first, so "go over to" wins over "go".
_COMMANDS: tuple[tuple[str, ...], ...] = tuple(sorted((tuple(c.split()) for c in (
    "please", "pls", "hey", "ok", "okay", "robot", "now", "can you", "could you", "would you",
    "go to", "go over to", "go back to", "take me to", "bring me to", "lead me to", "guide me to", "navigate to",
    "drive to", "move to", "head to", "walk to", "get to", "approach", "stop at", "face", "turn to",
    "find", "find me", "locate", "show me", "show", "point to", "point at", "look at", "look for", "search for",
    "highlight", "i need", "i want", "i'm looking for", "i am looking for", "looking for",
    "where is", "where are", "where's", "is there", "are there",
    "turn on", "turn off", "switch on", "switch off", "open", "close", "clean", "check")), key=len, reverse=True))
#: Trailing fillers, dropped after the noun phrase ("bed pls", "floor here").
_FILLERS = frozenset("please pls plz here there now thanks".split())
_TOKEN = re.compile(r"[a-z0-9][a-z0-9'\-]*")


@dataclass(frozen=True)
class QueryHead:
    """The core noun phrase of a query (determiners and post-modifier dropped) and its head word."""

    core: str
    head: str
    cut: bool  # a post-modifier (or a leading "a couple of") was dropped: the core stands for the text


def drop_request(text: str) -> str:
    """``text`` without its leading requests and commands ("go to the door" -> "the door",
    "please turn on the lamp" -> "the lamp"), as typed otherwise; the text itself when it has none
    or is nothing else. Relation queries (:func:`openfusion.mapping.relations.parse_relation_query`)
    read the rest: "turn on the lamp" is no lamp with something "on" it."""
    tokens = list(_TOKEN.finditer(text.lower()))
    words = [t.group() for t in tokens]
    start = 0
    while (c := next((c for c in _COMMANDS if words[start: start + len(c)] == list(c)
                      and len(words) > start + len(c)), None)):
        start += len(c)
    return text if start == 0 else text[tokens[start].start():]


def query_head(text: str) -> QueryHead | None:
    """The core noun phrase and head word of ``text`` (module docstring); None when the text has
    no noun head or is one word (nothing to check)."""
    rest = drop_request(text)
    command = rest != text  # a leading request or command was dropped
    words = _TOKEN.findall(rest.lower())
    while words and words[0] in _DETERMINERS:
        words = words[1:]
    dropped = command  # words besides determiners were dropped: the core stands for the text
    while len(words) > 2 and words[0] in _QUANTITIES and words[1] == "of":  # "a couple of pillows"
        words, dropped = words[2:], True
        while words and words[0] in _DETERMINERS:
            words = words[1:]
    if not words:
        return None
    if words[0] in _GENERIC or (command and words[0] == "to"):  # no noun head ("i need | to sit down");
        # after a command the rest stands for the text
        return QueryHead(" ".join(words), " ".join(words), True) if command else None
    while len(words) > 1 and words[-1] in _FILLERS:  # "bed pls", "floor here"
        words, dropped = words[:-1], True
    cut = len(words)
    for i in range(1, len(words)):
        w = words[i]
        participle = len(w) > 5 and w.endswith(("ing", "ed")) and w not in _VAGUE_HEADS
        if w in _POST or (participle and i + 1 < len(words) and words[i + 1] in _POST | _DETERMINERS):
            cut = i
            break
    core = words[:cut]
    if core[-1] in _VAGUE_HEADS:
        return QueryHead(" ".join(words), " ".join(words), True) if command else None
    if len(core) == 1 and cut == len(words) and not dropped:
        return None
    return QueryHead(" ".join(core), core[-1], cut < len(words) or dropped)
