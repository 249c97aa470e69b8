"""What one request may ask for: the limits of the query contract, declared once.

Every surface that takes a query checks these values with these functions, so a value past a
limit is refused with the same one line wherever it is caught:

| limit | value | where it is checked |
|---|---|---|
| :data:`MAX_TEXT_CHARS` | 512 characters per query text | the wire schemas (:mod:`openfusion.wire.schemas.query`), the query service, ``openfusion query`` (both modes), the Python client, the query page (its input box too) |
| :data:`MAX_TOP_K` | 100 regions per text | the same |
| :data:`MAX_BATCH_TEXTS` | 64 texts per batch request | the wire schema; the Python client sends more in batches of 64 |
| :data:`MAX_QUERY_POINTS` | 200,000 points in one query reply (the query service fetches at most this many from geometry for all its regions; a request's ``max_points`` per region is at most this too) | the wire schemas, the query service, the Python client |
| :data:`MAX_SURFACE_POINTS` | 500,000 surface points or mesh vertices per geometry reply | the geometry service (``max_points_reply`` may lower it), ``openfusion web --max-points`` |
| :data:`MAX_MESSAGE_BYTES` | 64 MiB per encoded message | the codec (:mod:`openfusion.wire.codec`), both ways |
| :data:`MAX_CHECKPOINT_CHUNK_BYTES` | 4 MiB of checkpoint file per reply (a replica copying its peer's checkpoint, docs/SHARDS.md) | the wire schemas (:mod:`openfusion.wire.schemas.checkpoint`), the serving geometry |
| :data:`MAX_CHECKPOINT_FILES` | 16 files in one checkpoint listing | the wire schemas |

A refusal is a :class:`LimitError` (a :class:`~openfusion.errors.UserError`: one line, exit code 2
in the ``openfusion`` commands; 400 with ``{"error": ...}`` on the page; ``reply_err`` with code
``too_large`` from the query service, which the commands and the page turn into the same line).
The message names the value, the limit and the parameter as the surface calls it (``--top-k`` on
the command line, ``top_k`` elsewhere).

Why these values: 512 characters is more than any query of the word lists (the longest is 64) and
the MiniLM text tower reads 256 tokens at most; 100 regions is more than a furnished room holds
answers for, and keeps a reply with points well under the message size; the point limits bound
one reply's points to what the message size carries (200,000 points of 12 bytes: 2.4 MB).
"""

from __future__ import annotations

from openfusion.errors import UserError

#: Longest query text, in characters.
MAX_TEXT_CHARS = 512
#: Most regions one query text may ask for (``top_k``).
MAX_TOP_K = 100
#: Most texts one batch request may carry.
MAX_BATCH_TEXTS = 64
#: Most points one query reply carries (its regions together; ``max_points`` per region at most this).
MAX_QUERY_POINTS = 200_000
#: Most surface points or mesh vertices one geometry reply may carry.
MAX_SURFACE_POINTS = 500_000
#: Largest encoded message, either way.
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
#: Most bytes of a checkpoint file one reply carries (a 1 GB map is 256 replies, never one).
MAX_CHECKPOINT_CHUNK_BYTES = 4 * 1024 * 1024
#: Most files one checkpoint listing names (a tile store is one file; room for what a format adds).
MAX_CHECKPOINT_FILES = 16


class LimitError(UserError, ValueError):
    """A request value past a limit of this module (one line naming the value and the limit)."""


def check_text(text: str, *, which: str = "") -> str:
    """``text`` when it is 1 to :data:`MAX_TEXT_CHARS` characters and not blank; ``which`` names
    it in the message (``"text 2 of 3 "``)."""
    if not isinstance(text, str):
        raise LimitError(f"the query {which}must be text, got {type(text).__name__}")
    if not text.strip():
        raise LimitError(f"the query {which}is empty" if which else "the query text is empty")
    if len(text) > MAX_TEXT_CHARS:
        raise LimitError(f"the query {which or 'text '}has {len(text)} characters; the limit is {MAX_TEXT_CHARS}")
    return text


def check_top_k(top_k: object, *, name: str = "top_k") -> int:
    """``top_k`` as an int when it is a whole number from 1 to :data:`MAX_TOP_K`; ``name``: what
    the surface calls it."""
    return _whole(top_k, name, MAX_TOP_K)


def check_max_points(max_points: object, *, name: str = "max_points") -> int:
    """``max_points`` as an int when it is a whole number from 1 to :data:`MAX_QUERY_POINTS`."""
    return _whole(max_points, name, MAX_QUERY_POINTS)


def check_batch(texts: list[str]) -> list[str]:
    """``texts`` when there are 1 to :data:`MAX_BATCH_TEXTS` of them, each as :func:`check_text` wants."""
    if not 1 <= len(texts) <= MAX_BATCH_TEXTS:
        raise LimitError(f"a batch holds 1 to {MAX_BATCH_TEXTS} texts, got {len(texts)}")
    for i, text in enumerate(texts):
        check_text(text, which=f"text {i + 1} of {len(texts)} " if len(texts) > 1 else "")
    return texts


def _whole(value: object, name: str, most: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise LimitError(f"{name} must be a whole number from 1 to {most:,}, got {value!r}")
    if not 1 <= value <= most:
        raise LimitError(f"{name} must be from 1 to {most:,}, got {value}")
    return value
