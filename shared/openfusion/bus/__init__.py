"""Zenoh helpers every service and client uses: session, typed publisher/subscriber/queryable,
``get`` for clients, liveliness, periodic health stats and clean shutdown.

Rules these helpers enforce:

- Zenoh never calls user code directly: each entity registers a tiny callback that only puts
  the sample/query into a Python queue; a worker thread of ours decodes it and runs the user's
  callback/handler, which may then call Zenoh freely.
- A message that does not decode (:class:`openfusion.wire.codec.DecodeError`) is logged with the key
  and reason, counted as an error and dropped: subscriber callbacks never see bad messages;
  queryables answer it with ``reply_err(ErrorReply(code="bad_request:<reason>"))``.
- Every query is answered (reply or reply_err) or, when the service is overloaded, dropped
  (which finalizes it, so the caller does not wait for its timeout).
- Drops are counted, not silent. Each :class:`Publisher` stamps every sample with an attachment
  ``<8-byte source id><uint64 little-endian sequence number>``; a :class:`Subscriber` counts
  (a) samples its own bounded queue discarded (``latest_only`` keeps one) and (b) gaps in the
  sequence of each source (samples lost before they reached us, e.g. dropped by congestion
  control). Samples sent before a subscriber saw a source's first sample are not counted (a late
  joiner has not "dropped" history). Hence, for one publisher and a subscriber declared before it
  started: ``published == received + drops`` once the queue is drained.

Keys, message types and owners come from :mod:`openfusion.wire.endpoints` (declared once).
A service is a :class:`ServiceRunner` (see ``openfusion.testing.demo_service`` for the pattern)::

    def setup(runner: ServiceRunner) -> None:
        runner.queryable(PING, handle_ping)          # PING = Endpoint(("demo", "ping"), ...)
        runner.publisher(SENSOR_RGBD)
        reply = runner.call(GEOMETRY_RENDER, RenderRequest(...))

    sys.exit(run_service(config, "demo", setup))

After ``setup`` has declared the service's entities it declares the liveliness token
``{prefix}/{map}/health/{service}`` (so "alive" means "ready to answer"), publishes
:class:`HealthStats` there every ``config.health_period_s`` (and answers queries on that key with
the latest stats), stops on SIGINT/SIGTERM, undeclares everything, closes the session and
returns exit code 0.
"""

from openfusion.bus.health import HealthReporter, collect_health, live_services
from openfusion.bus.pubsub import Publisher, Subscriber
from openfusion.bus.query import Queryable, QueryError, RequestError, call, get, get_all
from openfusion.bus.runner import ServiceRunner, run_service
from openfusion.bus.session import BusError, free_loopback_port, open_session
from openfusion.bus.stats import ServiceStats

__all__ = [
    "BusError",
    "HealthReporter",
    "Publisher",
    "QueryError",
    "Queryable",
    "RequestError",
    "ServiceRunner",
    "ServiceStats",
    "Subscriber",
    "call",
    "collect_health",
    "free_loopback_port",
    "get",
    "get_all",
    "live_services",
    "open_session",
    "run_service",
]
