"""Several query services on one map: their names, and how a request is answered once.

Each query service holds the whole dictionary and the region summaries (nothing is split), so
any of them can answer any request. ``query.instance`` (``--query.instance N``, or ``openfusion
run --query-services N``) numbers them: instance 1 (or none) is ``query``, the others
``query-2`` … ``query-N``: the names their health and liveliness use (``openfusion health``
lists each), while all of them declare the same queryables (``…/query/text`` and the others).

Answered once, by Zenoh: every query queryable is declared ``complete`` and clients ``get`` with
Zenoh's default target ``BEST_MATCHING``, which delivers a query to ONE complete queryable
(eclipse-zenoh 1.x: the nearest; on one router, the same one for every client), so a request is
computed once and answered once, never by both. When that query service's session goes (closed
or killed: the router drops its face), the next request goes to another one; nothing is
replicated or elected by us. Measured with 32 concurrent clients in ``bench/bench_query_load.py``;
tested in ``tests/bus/test_query_services.py``.
"""

from __future__ import annotations

from openfusion.wire.endpoints import is_query_service, query_service_name

#: Most query services numbered on one map (a sanity bound on ``query.instance``).
MAX_QUERY_INSTANCES = 64

__all__ = ["MAX_QUERY_INSTANCES", "is_query_service", "query_service_name"]
