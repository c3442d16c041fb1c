"""The demand a gateway forwards to the publisher, sans-I/O.

A gateway announces the union of its clients' subscriptions (spikes columns class -> taxels,
channel taxels, and decoder -> taxels) on its own subject ``demand.<gateway_id>`` when it changes
and every ``interval`` seconds, with a time to live. The publisher merges the live announcements and publishes
the smallest single frame stream per subject covering them: spikes for the union of the announced
taxels x the union of the announced classes (one frame per update keeps the subject's ``seq`` a
faithful loss counter; a product is exact when clients ask for products, as they do in the
protocol), full-rate channels for the union of the channel taxels, and each announced decoder for
the union of its taxels. Announcements that expire (a gateway gone) stop counting, so computing
stops too.

The sender is the subject's last token, which the broker binds to the gateway's credentials
(:func:`.subjects.gateway_permissions`); an announcement whose body names another gateway is
dropped, so one identity holds at most one of the ``max_gateways`` places and a gateway restarted
under its id renews its own place, full or not.

Announcements are bounded (anyone allowed to publish demand could otherwise make the service
compute everything or grow without limit): at most :data:`MAX_ANNOUNCEMENT_BYTES`, a TTL of at
most :data:`MAX_TTL_MS`, gateway ids and decoder names that are subject tokens, at most
:data:`MAX_DECODERS` decoders, the sender's own id, taxel ids of existing taxels, and at most
``max_gateways`` live gateways. Anything else raises :class:`Rejected` with its reason, for the
publisher to drop and count.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from touchreal_client import protocol as P

from .subjects import token_ok

DEFAULT_TTL_S = 3.0
MAX_ANNOUNCEMENT_BYTES = 256 * 1024
MAX_TTL_MS = 60_000
MAX_DECODERS = 64
MAX_GATEWAYS = 64  #: live gateways per sensor, by default
REJECT_REASONS = ("oversized", "malformed", "out_of_range", "identity_mismatch", "too_many_gateways")


class Rejected(ValueError):
    """An announcement that is dropped; ``reason`` is one of :data:`REJECT_REASONS`."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


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
    """A gateway's demand message, its taxel sets as id ranges (:func:`touchreal_client.protocol.id_ranges`:
    every taxel of a 65,536-taxel skin is ``[[0, 65536]]``):
    ``{"gateway": ID, "ttl_ms": N, "columns": {"SA1": [[0, 2]], ...}, "channels": [[0, 1]], "decoders": {"force": [[0, 1]]}}``."""
    cols = {c: P.id_ranges(demand.columns[c]) for c in P.CLASSES if demand.columns.get(c)}
    decs = {n: P.id_ranges(taxels) for n, taxels in sorted(demand.decoders.items()) if taxels}
    return json.dumps({"gateway": gateway_id, "ttl_ms": int(ttl_s * 1000), "columns": cols,
                       "channels": P.id_ranges(demand.channels), "decoders": decs}).encode()


def _id(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 65536


def _taxel_list(v) -> bool:
    """A list of ranges ``[start, stop]`` (0 <= start <= stop <= 65536) or of single ids (as gateways
    before id ranges announced)."""
    return isinstance(v, list) and all(_id(x) and x < 65536 or isinstance(x, list) and len(x) == 2 and _id(x[0])
                                       and _id(x[1]) and x[0] <= x[1] for x in v)


def _taxels(v: list, n_taxels: int) -> list[int]:
    """The sorted ids of a checked :func:`_taxel_list` (at most ``n_taxels``, however many ranges overlap);
    :class:`Rejected` ``out_of_range`` for an id at or past ``n_taxels``."""
    mask = np.zeros(n_taxels, bool)
    for x in v:
        a, b = (x, x + 1) if isinstance(x, int) else x
        if b > n_taxels:
            raise Rejected("out_of_range", f"taxel {b - 1} does not exist (ids 0..{n_taxels - 1})")
        mask[a:b] = True
    return np.flatnonzero(mask).tolist()


def parse_announcement(sender: str, data: bytes, n_taxels: int = 65536) -> tuple[Announced, float]:
    """(the demand of gateway ``sender``, its ttl in s) from an announcement on ``sender``'s subject;
    raises :class:`Rejected` for an oversized or malformed message, one naming taxels outside
    ``0..n_taxels-1`` or one whose ``gateway`` is not ``sender``. ``channels`` and ``decoders`` are optional."""
    if len(data) > MAX_ANNOUNCEMENT_BYTES:
        raise Rejected("oversized", f"demand announcement of {len(data)} bytes exceeds {MAX_ANNOUNCEMENT_BYTES}")
    try:
        msg = json.loads(data)
        gid, ttl, cols = msg["gateway"], msg["ttl_ms"], msg["columns"]
        chan, decs = msg.get("channels", []), msg.get("decoders", {})
        ok = (isinstance(gid, str) and token_ok(gid) and isinstance(ttl, int) and not isinstance(ttl, bool)
              and 0 < ttl <= MAX_TTL_MS and isinstance(cols, dict)
              and all(c in P.CLASSES and _taxel_list(t) for c, t in cols.items()) and _taxel_list(chan)
              and isinstance(decs, dict) and len(decs) <= MAX_DECODERS
              and all(token_ok(n) and _taxel_list(t) for n, t in decs.items()))
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError) as exc:
        raise Rejected("malformed", f"malformed demand announcement: {exc!r}"[:300]) from exc
    if not ok:
        raise Rejected("malformed", f"malformed demand announcement: expected gateway (a subject token), ttl_ms "
                       f"(1..{MAX_TTL_MS}), columns {{class: [[start, stop]]}}, channels [[start, stop]], decoders "
                       f"{{name: [[start, stop]]}} (at most {MAX_DECODERS})")
    if gid != sender:
        raise Rejected("identity_mismatch", f"an announcement for gateway {gid} on the subject of gateway {sender}")
    try:
        announced = Announced({c: _taxels(t, n_taxels) for c, t in cols.items()}, _taxels(chan, n_taxels),
                              {n: _taxels(t, n_taxels) for n, t in decs.items()})
    except Rejected as exc:
        raise Rejected(exc.reason, f"gateway {gid}: {exc}") from None
    return announced, ttl / 1000.0


class ForwardedDemand:
    """Live announcements by gateway id (at most ``max_gateways``, one each); times in seconds of any
    monotonic clock."""

    def __init__(self, max_gateways: int = MAX_GATEWAYS) -> None:
        self.max_gateways = max_gateways
        self._live: dict[str, tuple[Announced, float]] = {}

    def announce(self, gateway_id: str, demand: Announced, ttl_s: float, now: float) -> None:
        """Record (or withdraw, when empty) a gateway's demand, replacing its previous one: a live
        gateway always renews; a new one beyond ``max_gateways`` live ones raises :class:`Rejected`
        (``too_many_gateways``)."""
        if demand.empty:
            self._live.pop(gateway_id, None)
            return
        if gateway_id not in self._live and len(self._live) >= self.max_gateways:
            self.expire(now)
            if len(self._live) >= self.max_gateways:
                raise Rejected("too_many_gateways", f"{len(self._live)} gateways already announce demand "
                               f"(max_gateways); {gateway_id} is not counted")
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
