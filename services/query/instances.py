"""Several query services on one map: their names, and how a request is answered once.

Each query service holds the whole dictionary and the region summaries (nothing is split), so
any of them can answer any request. ``query.instance`` (``--query.instance N``, or ``openfusion
run --query-services N``) numbers them: instance 1 (or none) is ``query``, the others
``query-2`` … ``query-N``: the names their health and liveliness use (``openfusion health``
lists each), while all of them declare the same queryables (``…/query/text`` and the others).

Answered once, and spread:

- every query queryable is declared ``complete`` on the shared key (``…/query/text``), and a
  ``get`` there uses Zenoh's default target ``BEST_MATCHING``, which delivers it to ONE complete
  queryable: computed once, answered once. On one router that is always the same service
  (eclipse-zenoh 1.10; across routers, each router's nearest), so the shared key alone gives a hot
  standby, not more throughput;
- each query service also declares every endpoint on its own instance key
  (``…/query/text/query-2``, :meth:`~openfusion.wire.endpoints.Endpoint.instance_key`), and
  :class:`~openfusion.client.OpenFusionClient` takes the live query services (liveliness,
  refreshed every 2 s) in turn (:mod:`openfusion.bus.instances`): one key per request, one
  queryable behind it. With one query service alive the client uses the shared key as before;
- a query service that goes away: killed, its router drops the session and routes the shared key
  to another one at once; stopped, its query queryables are left to the session's close (not
  undeclared first: a router keeps routing BEST_MATCHING queries to an undeclared complete
  queryable while its session lives, measured with zenoh 1.10), and a request that got no reply
  at all is asked again for up to 0.5 s (:func:`openfusion.bus.get`), on the shared key when the
  instance asked by name is gone.

Nothing is replicated or elected by us. Measured with 32 concurrent clients in
``bench/bench_query_load.py``; tested in ``tests/bus/test_query_services.py``.
"""

from __future__ import annotations

from openfusion.wire.endpoints import is_query_service, query_service_name

#: Most query services numbered on one map (a sanity bound on ``query.instance``).
MAX_QUERY_INSTANCES = 64

__all__ = ["MAX_QUERY_INSTANCES", "is_query_service", "query_service_name"]
