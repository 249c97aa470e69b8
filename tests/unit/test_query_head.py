"""The head of a query text (openfusion.mapping.query_head): the hand-written noun-phrase
patterns relevancy's head rule uses (determiners, generic openings, post-modifiers, compounds,
requests and commands)."""

from __future__ import annotations

import pytest

from openfusion.mapping.query_head import QueryHead, drop_request, query_head


@pytest.mark.parametrize(
    ("text", "want"),
    [
        # noun compounds: the last word is the head
        ("wall clock", QueryHead("wall clock", "clock", False)),
        ("a ceiling fan", QueryHead("ceiling fan", "fan", False)),
        ("a desk fan", QueryHead("desk fan", "fan", False)),
        ("window blinds", QueryHead("window blinds", "blinds", False)),
        ("The Trash Can.", QueryHead("trash can", "can", False)),
        ("two-seater sofa", QueryHead("two-seater sofa", "sofa", False)),
        # post-modifiers: prepositional phrases, relative clauses, participles, subject pronouns
        ("a seat at the desk", QueryHead("seat", "seat", True)),
        ("a light for the desk", QueryHead("light", "light", True)),
        ("art that hangs on a wall", QueryHead("art", "art", True)),
        ("a green plant in a pot", QueryHead("green plant", "plant", True)),
        ("a painting hanging on the wall", QueryHead("painting", "painting", True)),
        ("the screen I look at while working", QueryHead("screen", "screen", True)),
        ("the screen showing my code", QueryHead("screen", "screen", True)),
        ("a shelf full of books", QueryHead("shelf", "shelf", True)),
        # quantities take the thing after "of": dropped like a determiner, the rest stands for the text
        ("a couple of pillows", QueryHead("pillows", "pillows", True)),
        ("a stack of books on the desk", QueryHead("books", "books", True)),
        ("a couple", None),
        # no noun head: uses and places, generic or vague heads
        ("something to sit on", None),
        ("a place to sleep", None),
        ("where I put my books", None),
        ("the thing above my head", None),
        ("a soft thing on the bed", None),
        ("the furniture where I keep dishes", None),
        # requests and commands around the thing (a robot operator's "go to the door") and fillers
        ("go to the door", QueryHead("door", "door", True)),
        ("turn on the lamp", QueryHead("lamp", "lamp", True)),
        ("please navigate to the office chair", QueryHead("office chair", "chair", True)),
        ("where is the lamp", QueryHead("lamp", "lamp", True)),
        ("show me something to sit on", QueryHead("something to sit on", "something to sit on", True)),
        ("I need to sit down", QueryHead("to sit down", "to sit down", True)),
        ("bed pls", QueryHead("bed", "bed", True)),
        ("the wall clock please", QueryHead("wall clock", "clock", True)),
        ("how do I get out of here", None),  # "here" is no filler after a generic opening
        ("find", None),
        ("the cabinet next to the bed", QueryHead("cabinet", "cabinet", True)),
        # one word: the text is its own head
        ("chair", None),
        ("the couch", None),
        ("", None),
    ],
)
def test_query_head(text: str, want: QueryHead | None) -> None:
    assert query_head(text) == want


def test_drop_request_keeps_the_rest_as_typed() -> None:
    assert drop_request("Please go to The Door") == "The Door"
    assert drop_request("turn on the lamp") == "the lamp"
    assert drop_request("the lamp") == "the lamp" and drop_request("find") == "find"
    assert drop_request("show me something to sit on") == "something to sit on"
