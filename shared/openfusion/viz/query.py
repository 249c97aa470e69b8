"""Text queries for the viewers: pick the text encoder of the map's embedding space, rank regions.

A map records the embedding space of its regions (``minilm-l6-v2``, ``hash-trigram-256``,
``clip-vit-b-32``, ...). A query must be embedded in the same space; :func:`text_encoder_for_map`
picks the matching text encoder, or checks the one the user named, and refuses a mismatch with a
:class:`~openfusion.viz.errors.VizError` naming both spaces.
"""

from __future__ import annotations

import logging
import re

from openfusion.mapping.dictionary import RegionDictionary
from openfusion.mapping.errors import EmbeddingSpaceError
from openfusion.mapping.queries import query_regions
from openfusion.viz.colouring import QueryHit
from openfusion.viz.errors import VizError

logger = logging.getLogger(__name__)

_HASH_SPACE = re.compile(r"^hash-trigram-(\d+)$")


def default_text_encoder_spec(embedding_space: str) -> tuple[str, dict]:
    """(text encoder name, options) that embeds text in ``embedding_space``; VizError when none is known."""
    if embedding_space == "minilm-l6-v2":
        return "minilm", {}
    match = _HASH_SPACE.match(embedding_space)
    if match:
        return "hash", {"dim": int(match.group(1))}
    if embedding_space.startswith("clip"):
        return "clip-regions", {}
    raise VizError(
        f"no built-in text encoder embeds queries in the map's embedding space {embedding_space!r}; "
        "name one with --text-encoder (and --text-model)"
    )


def text_encoder_for_map(
    dictionary: RegionDictionary, *, name: str | None = None, model: str | None = None
):  # noqa: ANN201 - returns an openfusion.encoders.TextEncoder
    """The text encoder for queries against ``dictionary`` (built lazily: MiniLM loads a model).

    ``name``/``model`` override the choice (``model`` is the ONNX file for ``onnx`` or the CLIP
    weights for ``clip-regions``). Raises VizError when the encoder cannot be built or its space
    differs from the map's.
    """
    from openfusion.encoders import EncoderError, make_text_encoder

    space = dictionary.embedding_space
    if name is None:
        name, options = default_text_encoder_spec(space)
    else:
        options = {}
    if model is not None:
        options["model_path" if name == "onnx" else "model"] = model
    try:
        encoder = make_text_encoder(name, **options)
    except (EncoderError, ValueError, OSError) as exc:
        raise VizError(f"cannot build text encoder {name!r}: {exc}") from exc
    if encoder.embedding_space != space:
        raise VizError(
            f"text encoder {name!r} embeds in space {encoder.embedding_space!r} but the map's regions are in "
            f"{space!r}; use a text encoder of the map's space"
        )
    return encoder


def query_text(dictionary: RegionDictionary, text: str, *, top_k: int, text_encoder) -> list[QueryHit]:  # noqa: ANN001
    """The ``top_k`` regions best matching ``text`` (best first); empty when the map has no region."""
    text = str(text).strip()
    if not text:
        raise VizError("the query text is empty")
    if top_k < 1:
        raise VizError(f"top-k must be >= 1, got {top_k}")
    vector = text_encoder.encode([text])[0]
    try:
        results = query_regions(dictionary, None, vector, top_k, embedding_space=text_encoder.embedding_space)
    except EmbeddingSpaceError as exc:
        raise VizError(str(exc)) from exc
    hits = [QueryHit(int(r.key), float(r.score), r.label) for r in results]
    logger.info("query %r: %s", text, ", ".join(f"{h.key}:{h.label}:{h.score:.3f}" for h in hits) or "no regions")
    return hits
