"""What the query page may ask of the map (:class:`WebBackend`: a query, the surface points, the
services' health) and the JSON it gets back; :class:`ClientBackend` asks an
:class:`~openfusion.client.OpenFusionClient`, the only way from the page to the services."""

from __future__ import annotations

import math
from typing import Any, Protocol

#: Points of each answered region sent to the browser (the highlight)...
HIGHLIGHT_MAX_POINTS = 4_000
#: ... and of all answered regions together (fewer per region when a query asks for many).
HIGHLIGHT_BUDGET_POINTS = 80_000
#: Seconds the health panel waits for the services' stats.
HEALTH_TIMEOUT_S = 1.5


class WebBackend(Protocol):
    """What the page may ask of the map, and nothing else."""

    map_id: str

    def query(self, text: str, top_k: int) -> dict[str, Any]: ...

    def points(self, max_points: int) -> dict[str, Any]: ...

    def health(self) -> dict[str, Any]: ...


class ClientBackend:
    """:class:`WebBackend` through an :class:`~openfusion.client.OpenFusionClient` (its Zenoh
    session is safe to use from the server's request threads)."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.map_id = str(client.keys.map_id)

    def query(self, text: str, top_k: int) -> dict[str, Any]:
        reply = self.client.query_text(text, top_k=top_k, with_points=True, max_points=highlight_points(top_k))
        return {"query": reply.query, "embedding_space": reply.embedding_space,
                "regions": [answer_record(region) for region in reply.regions]}

    def points(self, max_points: int) -> dict[str, Any]:
        reply = self.client.points(max_points=max_points)
        return {"count": len(reply.points), "truncated": bool(reply.truncated),
                "positions": _rounded(reply.points), "colors": [int(c) for c in reply.colors.reshape(-1)],
                "keys": [int(k) for k in reply.keys]}

    def health(self) -> dict[str, Any]:
        live = self.client.live_services(timeout_s=HEALTH_TIMEOUT_S)
        stats = self.client.health(timeout_s=HEALTH_TIMEOUT_S)
        services = []
        for name in sorted(set(live) | set(stats)):
            s = stats.get(name)
            services.append({"service": name, "alive": name in live,
                             **({"fps": s.fps, "errors": s.errors, "drops": s.drops, "uptime_s": s.uptime_s,
                                 "latency_ms_p50": s.latency_ms_p50} if s is not None else {})})
        return {"map_id": self.map_id, "services": services}


def highlight_points(top_k: int) -> int:
    """Points of each answered region sent to the browser when a query asks for ``top_k``."""
    return max(1, min(HIGHLIGHT_MAX_POINTS, HIGHLIGHT_BUDGET_POINTS // max(1, top_k)))


def answer_record(region: Any) -> dict[str, Any]:
    """One ranked region as the page shows it; ``relevancy`` and ``match`` only when the reply has them."""
    record: dict[str, Any] = {
        "key": int(region.key), "score": round(float(region.score), 4), "label": region.label,
        "num_points": int(region.num_points), "bbox_min": _rounded(region.bbox_min),
        "bbox_max": _rounded(region.bbox_max),
        "points": _rounded(region.points) if getattr(region, "points", None) is not None else [],
    }
    for name in ("relevancy", "match"):
        value = getattr(region, name, None)
        if value is not None:
            record[name] = _plain(value)
    return record


def _rounded(array: Any) -> list[float]:
    """A float array as a flat list, millimetres (3 decimals)."""
    return [round(float(v), 3) for v in array.reshape(-1)]


def _plain(value: Any) -> Any:
    """A reply field as plain JSON (models and arrays included)."""
    if hasattr(value, "model_dump"):
        value = value.model_dump(mode="json")
    if hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, float):
        return round(value, 4) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if value is None or isinstance(value, bool | int | str):
        return value
    return str(value)


# ------------------------------------------------------------------------------ the page
