"""The demand a gateway forwards to the publisher, sans-I/O.

A gateway announces the union of its clients' subscriptions (its hub's
:class:`~touchreal.server.demand.Demand` columns: class -> taxels) on the ``demand`` subject when it
changes and every ``interval`` seconds, with a time to live. The publisher merges the live
announcements and publishes the smallest single frame stream covering them: the union of the
announced taxels x the union of the announced classes (one frame per update keeps the subject's
``seq`` a faithful loss counter; a product is exact when clients ask for products, as they do in
the protocol). Announcements that expire (a gateway gone) stop counting, so computing stops too.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence

from touchreal_client import protocol as P

DEFAULT_TTL_S = 3.0


def announcement(gateway_id: str, columns: Mapping[str, Sequence[int]], ttl_s: float = DEFAULT_TTL_S) -> bytes:
    """A gateway's demand message: ``{"gateway": ID, "ttl_ms": N, "columns": {"SA1": [0, 1], ...}}``."""
    cols = {c: sorted(int(t) for t in columns[c]) for c in P.CLASSES if c in columns and columns[c]}
    return json.dumps({"gateway": gateway_id, "ttl_ms": int(ttl_s * 1000), "columns": cols}).encode()


def parse_announcement(data: bytes) -> tuple[str, dict[str, list[int]], float]:
    """(gateway id, columns, ttl in s); raises ValueError on a malformed message."""
    try:
        msg = json.loads(data)
        gid, ttl, cols = msg["gateway"], msg["ttl_ms"], msg["columns"]
        ok = (isinstance(gid, str) and isinstance(ttl, int) and 0 < ttl <= 600_000 and isinstance(cols, dict)
              and all(c in P.CLASSES and isinstance(t, list) and all(isinstance(x, int) and 0 <= x < 65536 for x in t)
                      for c, t in cols.items()))
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"malformed demand announcement: {exc!r}") from exc
    if not ok:
        raise ValueError("malformed demand announcement: expected gateway (str), ttl_ms (1..600000), columns {class: [taxel]}")
    return gid, {c: list(t) for c, t in cols.items()}, ttl / 1000.0


class ForwardedDemand:
    """Live announcements by gateway id; times in seconds of any monotonic clock."""

    def __init__(self) -> None:
        self._live: dict[str, tuple[dict[str, list[int]], float]] = {}

    def announce(self, gateway_id: str, columns: dict[str, list[int]], ttl_s: float, now: float) -> None:
        if columns:
            self._live[gateway_id] = (columns, now + ttl_s)
        else:
            self._live.pop(gateway_id, None)

    def expire(self, now: float) -> None:
        for gid in [g for g, (_, until) in self._live.items() if until <= now]:
            del self._live[gid]

    def subscription(self) -> P.Subscription:
        """The one spikes subscription covering every live announcement (empty lists: nothing)."""
        taxels: set[int] = set()
        classes: set[str] = set()
        for cols, _ in self._live.values():
            for c, t in cols.items():
                classes.add(c)
                taxels.update(t)
        return P.Subscription(taxels=sorted(taxels), classes=[c for c in P.CLASSES if c in classes])

    @property
    def gateways(self) -> list[str]:
        return sorted(self._live)
