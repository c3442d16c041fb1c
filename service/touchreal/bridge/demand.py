"""The demand a gateway forwards to the publisher, sans-I/O.

A gateway announces the union of its clients' subscriptions (spikes columns class -> taxels,
channel taxels, and decoder -> taxels) on the ``demand`` subject when it changes and every
``interval`` seconds, with a time to live. The publisher merges the live announcements and publishes
the smallest single frame stream per subject covering them: spikes for the union of the announced
taxels x the union of the announced classes (one frame per update keeps the subject's ``seq`` a
faithful loss counter; a product is exact when clients ask for products, as they do in the
protocol), full-rate channels for the union of the channel taxels, and each announced decoder for
the union of its taxels. Announcements that expire (a gateway gone) stop counting, so computing
stops too.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from touchreal_client import protocol as P

from .subjects import token_ok

DEFAULT_TTL_S = 3.0


@dataclass(frozen=True)
class Announced:
    """One gateway's demand: spikes ``columns`` (class -> taxels), ``channels`` (taxels) and
    ``decoders`` (decoder name -> taxels its decoded outputs are wanted for)."""

    columns: Mapping[str, Sequence[int]]
    channels: Sequence[int] = ()
    decoders: Mapping[str, Sequence[int]] = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return not any(self.columns.values()) and not self.channels and not any(self.decoders.values())


def announcement(gateway_id: str, demand: Announced, ttl_s: float = DEFAULT_TTL_S) -> bytes:
    """A gateway's demand message:
    ``{"gateway": ID, "ttl_ms": N, "columns": {"SA1": [0, 1], ...}, "channels": [0], "decoders": {"force": [0]}}``."""
    cols = {c: sorted(int(t) for t in demand.columns[c]) for c in P.CLASSES if demand.columns.get(c)}
    decs = {n: sorted(int(t) for t in taxels) for n, taxels in sorted(demand.decoders.items()) if taxels}
    return json.dumps({"gateway": gateway_id, "ttl_ms": int(ttl_s * 1000), "columns": cols,
                       "channels": sorted(int(t) for t in demand.channels), "decoders": decs}).encode()


def _taxel_list(v) -> bool:
    return isinstance(v, list) and all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x < 65536 for x in v)


def parse_announcement(data: bytes) -> tuple[str, Announced, float]:
    """(gateway id, its demand, ttl in s); raises ValueError on a malformed message. ``channels`` and
    ``decoders`` are optional."""
    try:
        msg = json.loads(data)
        gid, ttl, cols = msg["gateway"], msg["ttl_ms"], msg["columns"]
        chan, decs = msg.get("channels", []), msg.get("decoders", {})
        ok = (isinstance(gid, str) and isinstance(ttl, int) and 0 < ttl <= 600_000 and isinstance(cols, dict)
              and all(c in P.CLASSES and _taxel_list(t) for c, t in cols.items()) and _taxel_list(chan)
              and isinstance(decs, dict) and all(token_ok(n) and _taxel_list(t) for n, t in decs.items()))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"malformed demand announcement: {exc!r}") from exc
    if not ok:
        raise ValueError("malformed demand announcement: expected gateway (str), ttl_ms (1..600000), "
                         "columns {class: [taxel]}, channels [taxel], decoders {name: [taxel]}")
    return (gid, Announced({c: list(t) for c, t in cols.items()}, list(chan), {n: list(t) for n, t in decs.items()}),
            ttl / 1000.0)


class ForwardedDemand:
    """Live announcements by gateway id; times in seconds of any monotonic clock."""

    def __init__(self) -> None:
        self._live: dict[str, tuple[Announced, float]] = {}

    def announce(self, gateway_id: str, demand: Announced, ttl_s: float, now: float) -> None:
        if demand.empty:
            self._live.pop(gateway_id, None)
        else:
            self._live[gateway_id] = (demand, now + ttl_s)

    def expire(self, now: float) -> None:
        for gid in [g for g, (_, until) in self._live.items() if until <= now]:
            del self._live[gid]

    def spikes(self) -> P.Subscription | None:
        """The one spikes subscription covering every live announcement (None: nobody wants spikes)."""
        taxels: set[int] = set()
        classes: set[str] = set()
        for d, _ in self._live.values():
            for c, t in d.columns.items():
                if t:
                    classes.add(c)
                    taxels.update(t)
        if not classes:
            return None
        return P.Subscription(taxels=sorted(taxels), classes=[c for c in P.CLASSES if c in classes])

    def channels(self) -> P.Subscription | None:
        """Full-rate channels for every announced channel taxel (None: nobody wants channels)."""
        taxels = sorted({t for d, _ in self._live.values() for t in d.channels})
        return P.Subscription(taxels=taxels, classes=[], streams=["channels"], decimation=1) if taxels else None

    def decoded(self) -> dict[str, P.Subscription]:
        """Per announced decoder, the decoded-only subscription covering every gateway's taxels for it."""
        taxels: dict[str, set[int]] = {}
        for d, _ in self._live.values():
            for name, t in d.decoders.items():
                if t:
                    taxels.setdefault(name, set()).update(t)
        return {name: P.Subscription(taxels=sorted(t), classes=[], streams=["decoded"], decoders=[name])
                for name, t in sorted(taxels.items())}

    @property
    def gateways(self) -> list[str]:
        return sorted(self._live)
