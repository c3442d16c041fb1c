"""A recorded session (:class:`~touchreal_client.session.Session`) as a rosbag2 folder that
``ros2 bag info`` and ``ros2 bag play`` read: MCAP storage (zstd chunks), CDR messages, metadata
version 8 (read by Humble and every later distribution). Extra ``ros2`` (``rosbags``).

The messages are the live bridge's (:mod:`.messages`). A session holds concatenated arrays rather
than the frames that carried them, so the export cuts them on a grid of ``hop_us`` (the hello's;
5 ms without one), the cadence of the live stream's frames, from the session's origin:

* ``/touchreal/spikes/<CLASS>`` (``touchreal_msgs/msg/Spikes``): one message per class and hop of
  the class's coverage (the span in which every spike of it was received), empty ones included as
  live, but for the empty hops the source never ran (the wire clock jumps over them between a
  replay's trials: where a clock epoch ends before the next one starts); ``final_us``: the end of
  the hop (of the coverage for the last one), exclusive.
* ``/touchreal/channels`` and ``/touchreal/force`` (``Channels``, ``Force``): one block per hop of
  the recorded (decimated) samples, cut also where a sample is missing; ``period_us`` is the
  recording's most common sample interval (0 if it holds a single sample).
* ``/touchreal/decoded/<DECODER>`` (``Decoded``): one message per step.
* ``/touchreal/description`` (``std_msgs/msg/String``): the hello (JSON), once, at the bag's first
  time, offered transient-local so that ``ros2 bag play`` republishes it latched. None without a
  hello (an encode folder).

Every other topic is offered reliable and volatile. ``update`` is the hop's index since the origin
(a session keeps no update counters) and ``params_rev`` the session's newest parameter revision (0
without one: a session does not keep which revision made what).

Time: ``header.stamp`` (and a spike's ``stamps``) is the server wall time of the wire stamp by the
recorded clock points, whole us as :meth:`Session.wall_us_of`; without clock points (an encode
folder, a server without a clock model) ``created_wall_us + (t_us - origin)``. A message's log time
is its header stamp, but no later than the wall time at which the next clock epoch starts: the
model extrapolates an epoch past it (the last spikes and decoder steps of a replay's trial are
stamped after the trial's samples), those were sent as the next trial began, and so each topic
plays in order. Integer ns since the Unix epoch throughout.
"""

from __future__ import annotations

import bisect
import heapq
import itertools
import math
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype, Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.typesys.store import Typestore

from .. import protocol as P
from ..clock import ClockMap, ClockPoint
from ..session import Session
from . import messages as M
from .types import typestore

METADATA_VERSION = 8  #: rosbag2 metadata version written (9 changes the QoS layout that Humble reads)
DEFAULT_HOP_US = 5000  #: the grid without a hello (the service's shipped hop)

_NO_TIME = QosTime(0, 0)  # deadline, lifespan, lease: unspecified (the middleware's default, infinite)


def _qos(durability: QosDurability, depth: int) -> Qos:
    return Qos(QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE, durability, _NO_TIME, _NO_TIME,
               QosLiveliness.AUTOMATIC, _NO_TIME, False)


#: Offered QoS of ``/touchreal/description`` (latched) and of every other topic.
LATCHED_QOS = _qos(QosDurability.TRANSIENT_LOCAL, 1)
STREAM_QOS = _qos(QosDurability.VOLATILE, 10)

#: (log time ns, topic, message fields) of one message
Item = tuple[int, str, dict[str, Any]]
#: (its header's wire stamp us, topic, message fields) of one message
Stamped = tuple[int, str, dict[str, Any]]


def wall_ns(session: Session) -> M.ToLocalNs:
    """The stamps mapping of the export: wire-clock us (array) -> int ns since the Unix epoch, by the
    recorded clock points, or ``created_wall_us + (t - origin)`` without any (module docstring)."""
    if not session.clock:
        base_us = session.created_wall_us - session.origin_us()
        return lambda t_us: (np.asarray(t_us, np.int64) + base_us) * 1000
    clock = ClockMap(history=len(session.clock))
    for p in session.clock:
        clock.update(p)

    def to_ns(t_us: np.ndarray) -> np.ndarray:
        wall_us = clock.to_server_wall_us(np.atleast_1d(np.asarray(t_us, np.int64)))
        return np.round(wall_us).astype(np.int64) * 1000

    return to_ns


def _table(to_ns: M.ToLocalNs, stamps: np.ndarray) -> M.ToLocalNs:
    """``to_ns`` computed once for ``stamps`` and looked up for those (a stream's stamps are known before
    its messages are made, and a :class:`ClockMap` call costs the same for one stamp as for many)."""
    keys = np.unique(np.asarray(stamps, np.int64))
    values = to_ns(keys)
    return lambda t_us: values[np.searchsorted(keys, np.asarray(t_us, np.int64))]


def topic_types(session: Session) -> dict[str, str]:
    """Topic -> ROS type name of every topic the export of ``session`` has, in the bag's order."""
    out = {M.DESCRIPTION_TOPIC: M.DESCRIPTION_TYPE} if session.hello else {}
    out |= {M.spikes_topic(c): M.SPIKES_TYPE for c in _spans(session)}
    if session.channels is not None:
        out |= {M.CHANNELS_TOPIC: M.CHANNELS_TYPE, M.FORCE_TOPIC: M.FORCE_TYPE}
    return out | {M.decoded_topic(name): M.DECODED_TYPE for name in sorted(session.decoded)}


def write_rosbag2(session: Session, out: str | Path) -> dict[str, int]:
    """Write ``session`` as the rosbag2 folder ``out`` (which must not exist); returns topic -> message
    count. On failure nothing is left at ``out``. ValueError if the session recorded nothing or spans
    several server sessions (their wire clocks overlap)."""
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out} exists already (a bag is written as a new folder)")
    if len(session.sessions) > 1:
        raise ValueError(f"{session.source} spans {len(session.sessions)} server sessions (the server restarted and "
                         "its clock with it); rosbag2 export takes a recording of one session")
    items = heapq.merge(*_streams(session, wall_ns(session)), key=lambda item: item[0])
    first = next(items, None)
    if first is None:
        raise ValueError(f"{session.source}: nothing to export")
    store, types = typestore(), topic_types(session)
    build = _builder(store)
    counts = dict.fromkeys(types, 0)
    writer = Writer(out, version=METADATA_VERSION, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.set_custom_data("touchreal.source", session.source)
    writer.set_custom_data("touchreal.stamps",
                           "clock points" if session.clock else "created_wall_us + (t_us - origin)")
    if session.hello:  # latched, at the bag's first time
        items = itertools.chain([(first[0], M.DESCRIPTION_TOPIC, M.description(session.hello)), first], items)
    else:
        items = itertools.chain([first], items)
    try:
        with writer:
            conns = {topic: writer.add_connection(topic, typ, typestore=store, offered_qos_profiles=[
                LATCHED_QOS if topic == M.DESCRIPTION_TOPIC else STREAM_QOS]) for topic, typ in types.items()}
            for log_ns, topic, fields in items:
                typ = types[topic]
                data = store.serialize_cdr(build(typ, fields), typ, little_endian=True)
                writer.write(conns[topic], log_ns, data)
                counts[topic] += 1
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return counts


# -- the messages of a session, each topic's in time order ------------------------------------------
def _spans(session: Session) -> dict[str, tuple[int, int]]:
    """Class -> [start, stop) (us) of its messages: its coverage, widened to every spike of it."""
    out = {}
    for k, c in enumerate(P.CLASSES):
        t = session.t_us[session.cls == k]
        spans = [session.coverage_us[c]] if c in session.coverage_us else []
        spans += [(int(t.min()), int(t.max()) + 1)] if t.size else []
        lo, hi = min((s for s, _ in spans), default=0), max((e for _, e in spans), default=0)
        if hi > lo:
            out[c] = (lo, hi)
    return out


def _streams(session: Session, to_ns: M.ToLocalNs) -> list[Iterator[Item]]:
    origin = session.origin_us()
    hop = int((session.hello or {}).get("hop_us", DEFAULT_HOP_US))
    rev = int(session.params[-1]["rev"]) if session.params else 0
    changes = _epoch_changes(session)
    gaps = _gaps(changes)
    streams = [_spikes(session, c, span, gaps, origin, hop, rev, to_ns) for c, span in _spans(session).items()]
    if session.channels is not None:
        streams.append(_channels(session, origin, hop, rev, to_ns))
    streams += [_decoded(session, name, origin, hop, rev, to_ns) for name in sorted(session.decoded)]
    return [_logged(s, changes) for s in streams]


def _epoch_changes(session: Session) -> list[tuple[ClockPoint, ClockPoint]]:
    """(the old epoch's last clock point, the new epoch's first) wherever the epoch changes and the wire
    clock runs on (a replay's next trial, a reopened source)."""
    return [(p, q) for p, q in zip(session.clock, session.clock[1:])
            if q.epoch != p.epoch and q.sensor_us > p.sensor_us]


def _gaps(changes: list[tuple[ClockPoint, ClockPoint]]) -> list[tuple[int, int]]:
    """[start, stop) (wire us) that the source never ran: from where the old epoch's mapping reaches the
    new epoch's wall time to the new epoch's first stamp (the wire clock jumps over it between a replay's
    trials)."""
    out = []
    for p, q in changes:
        end = max(p.sensor_us + math.ceil((q.wall_us - p.wall_us) / p.rate), p.sensor_us)
        if end < q.sensor_us:
            out.append((end, q.sensor_us))
    return out


def _logged(items: Iterator[Stamped], changes: list[tuple[ClockPoint, ClockPoint]]) -> Iterator[Item]:
    """Log times: the header stamp, but no later than the wall time at which the next clock epoch starts.
    The model extrapolates an epoch past it (the last spikes and decoder steps of a replay's trial are
    stamped after the trial's samples); those were sent as the next epoch began, and so each topic
    plays in order."""
    starts = [q.sensor_us for _, q in changes]
    for t_us, topic, fields in items:
        stamp = fields["header"]["stamp"]
        log = stamp["sec"] * 1_000_000_000 + stamp["nanosec"]
        i = bisect.bisect_right(starts, t_us)
        yield (min(log, changes[i][1].wall_us * 1000) if i < len(changes) else log), topic, fields


def _spikes(session: Session, cls: str, span: tuple[int, int], gaps: list[tuple[int, int]], origin: int, hop: int,
            rev: int, to_ns: M.ToLocalNs) -> Iterator[Stamped]:
    """One Spikes message per hop of ``span`` (the class's spikes in [start, final_us)) but for the
    hops without a spike that lie in ``gaps``."""
    k = P.CLASSES.index(cls)
    mine = session.cls == k
    t, taxel = session.t_us[mine], session.taxel[mine]
    lo, hi = span
    first, last = (lo - origin) // hop, (hi - 1 - origin) // hop
    # hop first + i: [edges[i], edges[i + 1])
    edges = np.clip(origin + hop * np.arange(first, last + 2, dtype=np.int64), lo, hi)
    cuts = np.searchsorted(t, edges)
    to_ns = _table(to_ns, np.concatenate([t, edges[1:]]))
    idle = np.zeros(edges.size - 1, bool)
    for g0, g1 in gaps:
        idle |= (edges[:-1] >= g0) & (edges[1:] <= g1)
    idle &= cuts[1:] == cuts[:-1]
    for update, end, start, stop, skip in zip(range(first, last + 1), edges[1:].tolist(), cuts[:-1].tolist(),
                                              cuts[1:].tolist(), idle.tolist()):
        if skip:
            continue
        frame = P.SpikesFrame(P.Header(P.KIND_SPIKES, update=update, params_rev=rev), t[start:stop], taxel[start:stop],
                              np.full(stop - start, k, np.uint8), {cls: end})
        fields = M.spikes(frame, cls, to_ns)
        assert fields is not None  # a finality for the class: always a message
        yield end, M.spikes_topic(cls), fields


def _runs(t_us: np.ndarray, origin: int, hop: int, period: int | None = None) -> Iterator[tuple[int, int, int]]:
    """(hop index, start, stop) of the runs of ``t_us`` within one hop (and ``period`` apart, if given)."""
    hops = (t_us - origin) // hop
    cut = np.diff(hops) != 0
    if period is not None:
        cut |= np.diff(t_us) != period
    bounds = [0, *(np.flatnonzero(cut) + 1).tolist(), t_us.size]
    for start, stop in zip(bounds[:-1], bounds[1:]):
        yield int(hops[start]), start, stop


def _period_us(t_us: np.ndarray) -> int:
    """The most common interval of the samples (us); 0 for a single sample."""
    if t_us.size < 2:
        return 0
    gaps, n = np.unique(np.diff(t_us), return_counts=True)
    return int(gaps[n.argmax()])


def _channels(session: Session, origin: int, hop: int, rev: int, to_ns: M.ToLocalNs) -> Iterator[Stamped]:
    """A Channels and a Force message per block of evenly spaced samples within one hop."""
    ch = session.channels
    assert ch is not None
    period = _period_us(ch.t_us)
    to_ns = _table(to_ns, ch.t_us)
    for update, start, stop in _runs(ch.t_us, origin, hop, period):
        frame = P.ChannelsFrame(P.Header(P.KIND_CHANNELS, update=update, params_rev=rev), int(ch.t_us[start]), period,
                                ch.taxels, ch.data[start:stop])
        yield frame.t0_us, M.CHANNELS_TOPIC, M.channels(frame, to_ns)
        yield frame.t0_us, M.FORCE_TOPIC, M.force(frame, to_ns)


def _decoded(session: Session, name: str, origin: int, hop: int, rev: int, to_ns: M.ToLocalNs) -> Iterator[Stamped]:
    """A Decoded message per step."""
    d = session.decoded[name]
    topic = M.decoded_topic(name)
    to_ns = _table(to_ns, d.t_us)
    for update, start, stop in _runs(d.t_us, origin, hop):
        # ``decoder`` indexes the hello's decoders on the wire; the messages take the name instead
        frame = P.DecodedFrame(P.Header(P.KIND_DECODED, update=update, params_rev=rev), 0, d.taxels,
                               d.t_us[start:stop], d.values[start:stop])
        for fields in M.decoded(name, d.outputs, frame, to_ns):
            yield fields["t_us"], topic, fields


# -- message fields -> rosbags message objects --------------------------------------------------------
def _builder(store: Typestore) -> Callable[[str, dict[str, Any]], Any]:
    """(type name, :mod:`.messages`' fields) -> the message object of ``store``: nested dicts become
    nested messages, arrays and lists are taken as they are."""
    plans: dict[str, list[tuple[str, str | None, bool]]] = {}

    def plan(typename: str) -> list[tuple[str, str | None, bool]]:
        """(field, its message type or None, whether it is a sequence of them) per field."""
        if typename not in plans:
            plans[typename] = []
            for name, (node, detail) in store.fielddefs[typename][1]:
                many = node in (Nodetype.ARRAY, Nodetype.SEQUENCE)
                inner_node, inner = detail[0] if many else (node, detail)
                plans[typename].append((name, inner if inner_node == Nodetype.NAME else None, many))
        return plans[typename]

    def build(typename: str, fields: dict[str, Any]) -> Any:
        values = {}
        for name, nested, many in plan(typename):
            v = fields[name]
            if nested is not None:
                v = [build(nested, x) for x in v] if many else build(nested, v)
            values[name] = v
        return store.types[typename](**values)

    return build
