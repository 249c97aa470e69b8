"""The page's API requests read and refused: the parameters of ``/api/query`` and the one set of
limits (:mod:`openfusion.wire.limits`), and :class:`WebError`, an HTTP error answer naming what
was wrong (a service's refusal turned into one by :func:`bus_error`)."""

from __future__ import annotations

import re
from collections.abc import Mapping
from http import HTTPStatus
from urllib.parse import parse_qs

from openfusion.bus import QueryError
from openfusion.errors import OpenFusionError
from openfusion.wire.limits import LimitError, check_text, check_top_k

#: Answers a query asks for when the page does not say.
DEFAULT_TOP_K = 5


class WebError(OpenFusionError):
    """An HTTP error answer: ``status`` and a message for the page."""

    def __init__(self, status: HTTPStatus, message: str) -> None:
        self.status = status
        self.message = message
        super().__init__(f"{status.value}: {message}")


def one_param(params: Mapping[str, list[str]], name: str) -> str | None:
    """The one value of parameter ``name`` (None when it is not given; 400 when given more than once)."""
    values = params.get(name)
    if values is None:
        return None
    if len(values) != 1:
        raise WebError(HTTPStatus.BAD_REQUEST, f"give {name} once, got it {len(values)} times")
    return values[0]


def only_params(params: Mapping[str, list[str]], allowed: tuple[str, ...]) -> None:
    """400 naming the first parameter not in ``allowed``."""
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        allowed_text = ", ".join(allowed) if allowed else "none"
        raise WebError(HTTPStatus.BAD_REQUEST, f"unknown parameter {unknown[0]!r} (this endpoint takes: {allowed_text})")


def parse_query_params(query_string: str) -> tuple[str, int]:
    """(text, top_k) of ``/api/query``; :class:`WebError` 400 naming what is wrong."""
    try:
        params = parse_qs(query_string, keep_blank_values=True, strict_parsing=False, max_num_fields=8,
                          errors="strict")
    except (ValueError, UnicodeDecodeError) as exc:
        raise WebError(HTTPStatus.BAD_REQUEST, f"cannot read the query string: {exc}") from None
    only_params(params, ("text", "top_k"))
    text = one_param(params, "text")
    if text is None or not text.strip():
        raise WebError(HTTPStatus.BAD_REQUEST, "the query text is empty (give text=...)")
    raw_k = one_param(params, "top_k")
    try:  # the one set of limits (openfusion.wire.limits), with the lines every surface gives
        check_text(text)
        top_k = DEFAULT_TOP_K if raw_k is None else check_top_k(
            int(raw_k) if re.fullmatch(r"[0-9]{1,12}", raw_k) else raw_k)
    except LimitError as exc:
        raise WebError(HTTPStatus.BAD_REQUEST, str(exc)) from None
    return text, top_k


def bus_error(exc: QueryError) -> WebError:
    """A service's refusal or silence as the page's answer: 504 not answered, 400 a value past a limit, else 502."""
    if exc.code == "timeout":
        return WebError(HTTPStatus.GATEWAY_TIMEOUT, f"the service did not answer: {exc.reason}")
    if exc.code == "too_large" or exc.code.startswith("bad_request"):
        return WebError(HTTPStatus.BAD_REQUEST, f"the service refused the request: {exc.reason}")
    return WebError(HTTPStatus.BAD_GATEWAY, f"the service refused the request ({exc.code}): {exc.reason}")
