"""Fan-out: each update is rendered once per distinct subscription and offered to every subscriber.

Sans-I/O apart from an ``asyncio.Event`` per subscriber for wake-up: :meth:`Hub.publish` never
waits. Each :class:`Subscriber` has a bounded queue; a frame that does not fit is dropped for that
subscriber only (its ``seq`` still advances, so the client sees the gap, and ``dropped`` counts
it); a subscriber whose queue stays full, or whose sender takes no frame while frames wait, for
``slow_timeout_s`` is marked for closing with :data:`~touchreal_client.protocol.CLOSE_SLOW_CONSUMER`. Other subscribers are unaffected. Its control
replies are never dropped but bounded (:data:`~touchreal_client.protocol.CONTROL_QUEUE_MESSAGES` and
``CONTROL_QUEUE_BYTES``): a client that asks faster than it reads is marked for closing with
:data:`~touchreal_client.protocol.CLOSE_FLOODING`.

A queue is bounded in time as well: a frame that waited longer than ``max_age_s`` is dropped when
the sender reaches it (:meth:`Subscriber.next_frame`; counted, a ``seq`` gap like any drop), so an
overloaded server sends fresh frames late by at most that much instead of a backlog seconds late.

An update whose spikes frame would tell a subscription nothing new (no spike of its classes and
taxels, no flag, and the same ``final_us`` for its classes as the last one rendered for it) sends no
spikes frame: updates come every hop (5 ms) and only the fast classes' ``final_us`` moves on most of
them, so a PC-only subscriber gets one frame per PC update while an SA1 subscriber gets every hop's.

Queued items are rendered frames without the per-connection fields; the sender stamps ``seq``,
``dropped`` and ``sent_us`` when it hands the frame to the socket (:meth:`Subscriber.render`).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from touchreal_client import protocol as P

from .demand import Demand, build_demand
from .runtime import Update, wall_us

DROP_QUEUE_FULL = "queue_full"  #: a frame that did not fit a client's queue
DROP_UPSTREAM = "upstream_loss"  #: a frame lost before it reached the hub (a gateway's broker hop, an overloaded loop)
DROP_STALE = "stale"  #: a frame that waited in a client's queue longer than its max age
DROP_REASONS = (DROP_QUEUE_FULL, DROP_UPSTREAM, DROP_STALE)
MAX_AGE_S = 0.25  #: default: a queued frame older than this (s) is dropped rather than sent


def _uncounted(reason: str, n: int) -> None:
    pass


@dataclass(frozen=True)
class Picked:
    """The taxels a subscription names, resolved on one skin."""

    ids: np.ndarray  #: sorted ids (int64)
    mask: np.ndarray  #: (MAX_TAXELS,) bool: ``mask[id]`` is set for the ids in ``ids``


def _count(picked: Picked | None, n_taxels: int) -> int:
    return n_taxels if picked is None else picked.ids.size


def _taxel_key(s: P.Subscription) -> tuple:
    """What decides a subscription's taxels (hashable)."""
    return None if s.taxels is None else tuple(s.taxels), s.region


def _render_key(s: P.Subscription, taxel_key: tuple) -> tuple:
    """What decides the frames a subscription is sent (hashable): subscribers with equal keys share them."""
    return (taxel_key, None if s.classes is None else tuple(s.classes), tuple(s.streams), s.encoding,
            s.decimation, None if s.decoders is None else tuple(s.decoders))


@dataclass
class Queued:
    kind: int  #: P.KIND_*
    payload: bytes | str  #: binary frame, or the JSON body text
    seq: int
    queued_at: float = 0.0  #: the subscriber's clock (s) when it was queued


class Subscriber:
    """One connection's subscription, queue and counters (the WebSocket layer drives it)."""

    def __init__(self, sub_id: int, capacity: int, slow_timeout_s: float, clock: Callable[[], float] = time.monotonic,
                 on_drop: Callable[[str, int], None] = _uncounted, max_age_s: float | None = MAX_AGE_S):
        self.id = sub_id
        self.max_age_s = max_age_s  #: queued frames older than this (s) are dropped, not sent (None: no limit)
        self.on_drop = on_drop  #: told (reason, frames) of every drop: DROP_QUEUE_FULL or DROP_UPSTREAM
        self.capacity = capacity
        self.slow_timeout_s = slow_timeout_s
        self.clock = clock
        self.subscription: P.Subscription | None = None
        #: the subscription's taxel and render keys, made once when it is set (a taxel list may be long)
        self.taxel_key: tuple = ()
        self.render_key: tuple = ()
        self.queue: deque[Queued] = deque()
        self.seq = 0
        self.dropped = 0
        self.sent = 0
        self.full_since: float | None = None
        self.taken_at = clock()  #: when the sender last took a frame (or the queue last became non-empty)
        self.kick: tuple[int, str] | None = None  #: (close code, reason) once it must go
        self.kicked = asyncio.Event()
        self.control: deque[str] = deque()  #: JSON messages (hello, clock, subscribed, time, error): never dropped
        self.control_chars = 0  #: characters queued in ``control``
        self.after_frames: deque[str] = deque()  #: JSON messages that follow every frame queued before them (ended)
        #: False for a subscriber no client reads control messages from (a NATS publisher's lane)
        self.takes_control = True
        self.wakeup = asyncio.Event()

    def say(self, text: str) -> None:
        """Queue a control message; it goes out before any queued frame. One that would overflow the
        bounded reply queue marks the subscriber for closing (CLOSE_FLOODING) instead."""
        if self.kick is not None:
            return
        if len(self.control) >= P.CONTROL_QUEUE_MESSAGES or self.control_chars + len(text) > P.CONTROL_QUEUE_BYTES:
            self.kick = (P.CLOSE_FLOODING, f"flooding: {len(self.control)} control messages ({self.control_chars} "
                         "bytes) unsent; read the replies before sending more requests")
            self.kicked.set()
            return
        self.control.append(text)
        self.control_chars += len(text)
        self.wakeup.set()

    def say_after_frames(self, text: str) -> None:
        """Queue a message that goes out once the frames queued now have been sent (never dropped)."""
        self.after_frames.append(text)
        self.wakeup.set()

    def pop_control(self) -> str:
        """The oldest queued control message (for the sender)."""
        text = self.control.popleft()
        self.control_chars -= len(text)
        return text

    def offer(self, kind: int, payload: bytes | str) -> None:
        seq, self.seq = self.seq, self.seq + 1
        now = self.clock()
        self._drop_stale()  # a sender stuck on a slow socket must not let stale frames fill the queue
        if self.queue and now - self.taken_at >= self.slow_timeout_s and self.kick is None:
            self._kick(f"slow consumer: no frame taken for {self.slow_timeout_s:g} s")
        if len(self.queue) >= self.capacity:
            self.dropped += 1
            self.on_drop(DROP_QUEUE_FULL, 1)
            if self.full_since is None:
                self.full_since = now
            elif now - self.full_since >= self.slow_timeout_s and self.kick is None:
                self._kick(f"slow consumer: queue of {self.capacity} frames full for {self.slow_timeout_s:g} s")
            return
        self.full_since = None
        if not self.queue:
            self.taken_at = now  # waiting starts with the first queued frame
        self.queue.append(Queued(kind, payload, seq, now))
        self.wakeup.set()

    def _kick(self, why: str) -> None:
        self.kick = (P.CLOSE_SLOW_CONSUMER, f"{why}, {self.dropped} frames dropped")
        self.kicked.set()

    def next_frame(self) -> Queued | None:
        """The oldest queued frame still fresh enough to send (None: none left); those that waited longer
        than ``max_age_s`` are dropped on the way (DROP_STALE)."""
        self._drop_stale()
        if not self.queue:
            return None
        self.taken_at = self.clock()
        return self.queue.popleft()

    def _drop_stale(self) -> None:
        if self.max_age_s is None:
            return
        limit = self.clock() - self.max_age_s
        while self.queue and self.queue[0].queued_at < limit:
            self.queue.popleft()
            self.dropped += 1
            self.on_drop(DROP_STALE, 1)

    def skip(self, n: int) -> None:
        """``n`` frames meant for this subscriber were lost before they reached the hub (a broker hop):
        its ``seq`` jumps and ``dropped`` counts them, exactly as for a frame its own queue dropped."""
        self.seq += n
        self.dropped += n
        self.on_drop(DROP_UPSTREAM, n)

    def render(self, item: Queued) -> tuple[bytes | str, int]:
        """The frame as this connection sends it now, and its sent_us."""
        sent = wall_us()
        self.sent += 1
        if isinstance(item.payload, str):
            return P.render_json(item.payload, item.seq, self.dropped, sent), sent
        return bytes(P.stamp(item.payload, item.seq, self.dropped, sent)), sent


def limits(settings) -> dict[str, int | float]:
    """The hello's ``limits``: what one connection may send and have queued, and the keepalive (``settings``:
    serve's or a gateway's: ``queue_frames``, ``slow_timeout_s``, ``max_clients``, ``ping_interval_s``,
    ``ping_timeout_s``; times in s)."""
    return {"max_message_bytes": P.MAX_CLIENT_MESSAGE_BYTES, "queue_frames": settings.queue_frames,
            "slow_timeout_s": settings.slow_timeout_s, "control_messages": P.CONTROL_QUEUE_MESSAGES,
            "control_bytes": P.CONTROL_QUEUE_BYTES, "max_errors_in_a_row": P.MAX_ERRORS_IN_A_ROW,
            "control_rate_per_s": P.CONTROL_RATE_PER_S, "control_burst": P.CONTROL_BURST,
            "control_bytes_per_s": P.CONTROL_BYTES_PER_S, "control_burst_bytes": P.CONTROL_BURST_BYTES,
            "max_clients": settings.max_clients, "ping_interval_s": settings.ping_interval_s,
            "ping_timeout_s": settings.ping_timeout_s, "max_frame_age_ms": settings.max_frame_age_ms}


class Hub:
    """All subscribers of one service; lives on the event loop.

    Subscription changes take effect in the rendering at once, and in the :attr:`demand` (what the
    pipeline computes) at most once per ``refresh_s``: changes that arrive closer together are
    coalesced into one rebuild (:meth:`demand_changed`), so no client can make the demand churn
    faster than the updates it feeds."""

    def __init__(self, capacity: int, slow_timeout_s: float, max_age_s: float | None = MAX_AGE_S,
                 refresh_s: float = 0.005, clock: Callable[[], float] = time.monotonic):
        self.refresh_s, self.clock = refresh_s, clock
        self._refreshed_at = -float("inf")
        self._refresh: asyncio.TimerHandle | None = None
        self.capacity = capacity
        self.slow_timeout_s = slow_timeout_s
        self.max_age_s = max_age_s
        self.subscribers: dict[int, Subscriber] = {}
        self._ids = itertools.count(1)
        self.demand = Demand()
        self.on_drop: Callable[[str, int], None] = _uncounted  #: given to every subscriber (metrics)
        self.n_taxels = 1  #: ids spikes and subscriptions address: taxels, or a population's afferents
        self.addresses = "taxels"  #: what the ids are: "taxels" or "afferents" (the hello's ``addresses``)
        self.positions_mm: np.ndarray | None = None  #: (n_taxels, 2) taxel centres (mm), for rectangle regions
        self.allowed_classes: Sequence[str] = P.CLASSES
        self.decoder_classes: Mapping[str, Sequence[str]] = {}
        self.decoder_names: list[str] = []
        self.known = False  #: configured: what is served is known (a gateway learns it from the publisher's hello)
        self.frames_rendered = 0
        self._finals: dict[tuple, tuple] = {}  #: per distinct subscription: the final_us last rendered
        self._picked: dict[tuple, Picked | None] = {}  #: per distinct (taxels, region): its taxels, resolved

    # -- membership -----------------------------------------------------------------------------
    def add(self) -> Subscriber:
        sub = Subscriber(next(self._ids), self.capacity, self.slow_timeout_s, on_drop=self.on_drop, max_age_s=self.max_age_s)
        self.subscribers[sub.id] = sub
        return sub

    def remove(self, sub: Subscriber) -> None:
        if self.subscribers.pop(sub.id, None) is not None and sub.subscription is not None:
            self.demand_changed()

    def broadcast(self, text: str) -> None:
        """A control message (``hello``, ``clock``) for every client."""
        for sub in self.subscribers.values():
            if sub.takes_control:
                sub.say(text)

    def subscribe(self, sub: Subscriber, subscription: P.Subscription | None) -> None:
        sub.subscription = subscription
        if subscription is not None:
            sub.taxel_key = _taxel_key(subscription)
            sub.render_key = _render_key(subscription, sub.taxel_key)
        self.demand_changed()

    def demand_changed(self) -> None:
        """Rebuild the demand now, or, if it was rebuilt less than ``refresh_s`` ago, once that much
        time has passed (a rebuild already scheduled covers this change too). Without a running event
        loop (sans-I/O use) it is rebuilt at once."""
        if self._refresh is not None:
            return
        wait = self._refreshed_at + self.refresh_s - self.clock()
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:
            wait = 0.0
        if wait <= 0:
            self.refresh_demand()
        else:
            self._refresh = loop.call_later(wait, self.refresh_demand)

    def admit(self, msg: Mapping) -> P.Subscription:
        """A subscribe message as a subscription of what is served. Without ``classes`` it asks for
        the classes served; naming a class not served, a taxel (or a ``region`` id range reaching one)
        that does not exist, a ``region`` rectangle while the taxel positions are unknown or a decoder
        not offered raises :class:`~touchreal_client.protocol.ProtocolError` with code ``not_served``
        (the connection keeps its previous subscription). Until the hub is configured (a gateway
        before its publisher's hello) anything well-formed is admitted."""
        s = P.parse_subscribe(dict(msg))
        if s.classes is None:
            s.classes = [c for c in P.CLASSES if c in self.allowed_classes]
        if not self.known:
            return s
        problems = []
        if self.addresses == "afferents":
            if s.version < 2:
                raise P.ProtocolError("this server's spikes address afferents, not taxels: subscribe with protocol "
                                      "version 2 (the hello lists the afferents)", "unsupported_version")
            if bad := [x for x in s.streams if x != "spikes"]:
                problems.append(f"streams {bad} are per taxel and not served with a population (its afferents "
                                "have spikes only)")
        if bad := [c for c in s.classes if c not in self.allowed_classes]:
            problems.append(f"classes {bad} are not served (served: {list(self.allowed_classes)})")
        if bad := [t for t in s.taxels or () if t >= self.n_taxels]:
            problems.append(f"{self.addresses} {bad[:8]}{'...' if len(bad) > 8 else ''} do not exist (ids 0..{self.n_taxels - 1})")
        region = s.region or P.Region()
        if bad := [list(r) for r in region.ranges if r[1] > self.n_taxels]:
            problems.append(f"region.ranges {bad[:4]} reach past the last of the {self.addresses} (ids 0..{self.n_taxels - 1})")
        if region.rects and self.positions_mm is None:
            problems.append("region.rects need the taxel positions, which this server does not know: use region.ranges")
        n = _count(self.picked(s), self.n_taxels)
        if {"channels", "decoded"} & set(s.streams) and n > P.MAX_FRAME_TAXELS:
            problems.append(f"channels and decoded frames carry at most {P.MAX_FRAME_TAXELS} taxels, not {n}: "
                            "subscribe to fewer taxels")
        if "decoded" in s.streams and (bad := [d for d in s.decoders or () if d not in self.decoder_classes]):
            problems.append(f"decoders {bad[:8]} are not offered (offered: {self.decoder_names})")
        if problems:
            raise P.ProtocolError("; ".join(problems) + "; the previous subscription stays", "not_served")
        return s

    def configure(self, n_taxels: int, allowed_classes: Sequence[str], decoder_classes: Mapping[str, Sequence[str]],
                  positions_mm: np.ndarray | None = None, addresses: str | None = None) -> None:
        """What is served: ``n_taxels`` taxels, the classes and the decoders (name -> the classes they
        read). ``positions_mm``: the (n_taxels, 2) taxel centres (mm) rectangle regions select by; None
        keeps the ones configured before if they are of ``n_taxels`` taxels (a change of classes or
        decoders), else rectangles are refused. ``addresses`` "afferents": the ids are a population's
        afferents (``n_taxels`` of them, ``positions_mm`` theirs), which have spikes only and need
        protocol version 2; None keeps what was configured."""
        self.known = True
        if addresses is not None:
            self.addresses = addresses
        if positions_mm is not None:
            self.positions_mm = np.asarray(positions_mm, float).reshape(n_taxels, 2)
        elif self.positions_mm is not None and len(self.positions_mm) != n_taxels:
            self.positions_mm = None
        self.n_taxels, self.allowed_classes = n_taxels, list(allowed_classes)
        self.decoder_classes = dict(decoder_classes)
        self.decoder_names = list(decoder_classes)
        self._picked.clear()
        self.refresh_demand()

    def picked(self, s: P.Subscription, key: tuple | None = None) -> Picked | None:
        """The taxels subscription ``s`` names (its ``taxels`` and ``region``; ``key``: its :func:`_taxel_key`
        if known), resolved once per distinct pair while the skin stays the same; None: every taxel."""
        key = _taxel_key(s) if key is None else key
        if key not in self._picked:
            ids = s.taxel_ids(self.n_taxels, self.positions_mm)
            if ids is None:
                self._picked[key] = None
            else:
                mask = np.zeros(P.MAX_TAXELS, bool)  # indexed by any uint16 id a frame may carry
                mask[ids] = True
                self._picked[key] = Picked(ids, mask)
        return self._picked[key]

    def refresh_demand(self) -> None:
        if self._refresh is not None:
            self._refresh.cancel()
            self._refresh = None
        self._refreshed_at = self.clock()
        subs = [s for s in self.subscribers.values() if s.subscription is not None]
        keys = {id(s.subscription): s.taxel_key for s in subs}
        self._picked = {k: v for k, v in self._picked.items() if k in keys.values()}  # forget subscriptions gone

        def picked_ids(s: P.Subscription) -> np.ndarray | None:
            p = self.picked(s, keys[id(s)])
            return None if p is None else p.ids

        self.demand = build_demand([s.subscription for s in subs], self.n_taxels, self.allowed_classes,
                                   self.decoder_classes, picked_ids)

    # -- fan-out --------------------------------------------------------------------------------
    def publish(self, upd: Update) -> None:
        """Render the update once per distinct subscription and offer it to every subscriber."""
        cache: dict[tuple, list[tuple[int, bytes | str]]] = {}
        for sub in list(self.subscribers.values()):
            s = sub.subscription
            if s is None or sub.kick is not None:
                continue
            key = sub.render_key
            frames = cache.get(key)
            if frames is None:
                frames = cache[key] = self._render(upd, s, key)
                self.frames_rendered += len(frames)
            for kind, payload in frames:
                sub.offer(kind, payload)
        self._finals = {k: v for k, v in self._finals.items() if k in cache}  # forget subscriptions gone

    def skip(self, n_frames: int, stream: str, decoder: str | None = None) -> None:
        """``n_frames`` frames of ``stream`` (of ``decoder``'s outputs, for ``decoded``) were lost upstream (a
        gateway's broker hop, or updates the service's overloaded event loop dropped): every subscriber
        that would have received them is told, one ``seq`` and one ``dropped`` per frame."""
        for sub in self.subscribers.values():
            s = sub.subscription
            if s is None or sub.kick is not None or stream not in s.streams:
                continue
            if decoder is None or s.decoders is None or decoder in s.decoders:
                sub.skip(n_frames)

    def _render(self, upd: Update, s: P.Subscription, key: tuple) -> list[tuple[int, bytes | str]]:
        """The frames of ``upd`` for subscription ``s`` (``key``), without a spikes frame that has
        nothing new for it."""
        out: list[P.Frame] = []
        picked = self.picked(s, key[0])
        taxels = np.arange(self.n_taxels) if picked is None else picked.ids
        if "spikes" in s.streams and upd.spikes:
            h = P.Header(P.KIND_SPIKES, upd.update, upd.emit_us, upd.params_rev, upd.flags)
            classes = self.allowed_classes if s.classes is None else s.classes
            sel = np.ones(upd.cls.size, bool)
            if len(set(classes)) < len(P.CLASSES):
                sel &= np.isin(upd.cls, [P.CLASSES.index(c) for c in classes])
            if picked is not None:
                sel &= picked.mask[upd.taxel]
            final = {c: (upd.final_us.get(c) if c in classes else None) for c in P.CLASSES}
            mark = tuple(final.values())
            if sel.any() or upd.flags or self._finals.get(key) != mark:
                out.append(P.SpikesFrame(h, upd.t_us[sel], upd.taxel[sel], upd.cls[sel], final))
            self._finals[key] = mark
        if "channels" in s.streams and upd.channels is not None and upd.channels.n_samples:
            ch = upd.channels
            k = ch.k0 + np.arange(ch.n_samples)
            pick = k % s.decimation == 0
            if pick.any():
                h = P.Header(P.KIND_CHANNELS, upd.update, upd.emit_us, upd.params_rev, upd.flags)
                t0_us = int(k[pick][0]) * 200 + upd.offset_us  # the 5 kHz grid: 200 us per sample
                out.append(P.ChannelsFrame(h, t0_us, 200 * s.decimation, taxels.astype(np.uint16),
                                           ch.data[pick][:, taxels, :].astype(np.float32)))
        if "decoded" in s.streams:
            wanted = self.decoder_names if s.decoders is None else s.decoders
            for name, dec_taxels, t_us, values in upd.decoded:
                if name not in wanted:
                    continue
                dec = np.asarray(dec_taxels, np.int64)
                cols = np.flatnonzero(dec < self.n_taxels if picked is None else picked.mask[dec])
                h = P.Header(P.KIND_DECODED, upd.update, upd.emit_us, upd.params_rev, upd.flags)
                out.append(P.DecodedFrame(h, self.decoder_names.index(name), np.array(dec_taxels, np.uint16)[cols],
                                          t_us, values[:, cols, :]))
        return [(f.header.kind, _encode(f, s.encoding)) for f in out]


def _encode(frame: P.Frame, encoding: str) -> bytes | str:
    if encoding == "json":
        return json.dumps(P.frame_json_body(frame), separators=(",", ":"))
    if isinstance(frame, P.SpikesFrame):
        return P.encode_spikes(frame.header, frame.t_us, frame.taxel, frame.cls, frame.final_us)
    if isinstance(frame, P.ChannelsFrame):
        return P.encode_channels(frame.header, frame.t0_us, frame.period_us, frame.taxels, frame.data)
    return P.encode_decoded(frame.header, frame.decoder, frame.taxels, frame.t_us, frame.values)
