"""ROS 2 topics of a ``/v1/stream`` over DDS: ``touchreal bridge ros2 --from URL`` (extra ``ros2``:
cyclonedds, rosbags). No ROS 2 installation is needed on this side: the bridge speaks ROS 2's DDS
conventions itself, so ``ros2 topic list`` / ``ros2 topic echo`` on the same network and
``ROS_DOMAIN_ID`` see its topics.

Topics (messages of the ``touchreal_msgs`` package beside :mod:`touchreal_client.ros2.messages`, built
by that module's converters):

* ``/touchreal/spikes/<CLASS>`` (``touchreal_msgs/msg/Spikes``): one message per frame and class;
* ``/touchreal/channels`` (``Channels``) and ``/touchreal/force`` (``Force``): one message per
  channels frame, at 5 kHz / ``decimation``;
* ``/touchreal/decoded/<DECODER>`` (``Decoded``): one message per decoding step, for each decoder of
  the hello whose name is a valid ROS name token;
* ``/touchreal/description`` (``std_msgs/msg/String``): the hello as JSON, latched.

ROS 2 on DDS (what rmw_cyclonedds_cpp does, which this bridge follows):

* DDS topic ``rt`` + the ROS topic name (``rt/touchreal/spikes/SA1``), by the ROS 2 design article
  "Topic and Service name mapping to DDS";
* DDS type ``<pkg>::msg::dds_::<Name>_`` (``touchreal_msgs::msg::dds_::Spikes_``), as rmw_cyclonedds
  names the types it registers; nested types likewise;
* samples in plain little-endian CDR (XCDR1, encapsulation ``CDR_LE``): the only data representation
  rmw_cyclonedds' readers accept; the writers offer only XCDR1;
* QoS: every data topic reliable, volatile, keep-last :data:`DEPTH` (ROS 2's default profile, which a
  default ``create_subscription`` or ``ros2 topic echo`` asks for; a reliable writer also serves
  best-effort readers); the description reliable, transient-local, keep-last 1 (latched: a late
  subscriber asking for transient-local gets the last hello);
* USER_DATA ``typehash=RIHS01_...;`` on every writer (the REP-2011 type hash of its message, from
  rosbags), ``enclave=/;`` on the participant, as rmw_cyclonedds sets them.

The DDS types are cyclonedds ``IdlStruct`` classes generated at start from the ``.msg`` files (parsed
by rosbags), so the ``.msg`` files stay the one definition; :class:`DdsTypes` maps ROS 2 field types
onto IDL by the ROS 2 IDL mapping (``char`` -> ``uint8``, ``byte`` -> ``octet``, ``T[]`` ->
``sequence<T>``...).

Stamps: every ``header.stamp`` (and each spike's ``stamps[i]``) is this machine's wall time (ns since
the Unix epoch) of the wire stamp by the stream's clock model (server wall clock, then this machine's
by the ``time`` offset), not its time of arrival; ``t_us`` fields keep the wire stamps.

Demand-driven: the bridge subscribes upstream to exactly the topics DDS readers are matched to (the
writers' publication-matched status, with a listener for prompt changes), to nothing while none is,
so an idle bridge costs the service nothing. The description is written whatever the demand.

The bridge is a DDS participant, not a ROS node: ``ros2 topic list``/``echo``/``info`` see its
topics, ``ros2 node list`` does not list it (it publishes no ``ros_discovery_info``). DDS is
configured as Cyclone DDS always is (``CYCLONEDDS_URI``: network interface, peers).
"""

from __future__ import annotations

import asyncio
import contextlib
import keyword
import logging
import os
import re
import struct
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from .. import protocol as P
from ..errors import TouchRealError
from ..ros2 import messages as M
from ..ros2.types import typestore
from ..stream import AsyncStream
from ..topics import wanted_subscription
from . import FIRST_SYNC_SAMPLES, follow_demand, forward, publish_by_kind

log = logging.getLogger("touchreal_client.bridges.ros2")

#: The DDS topic prefix of a ROS 2 topic (design.ros2.org, "Topic and Service name mapping to DDS").
ROS_TOPIC_PREFIX = "rt"
#: Keep-last depth of the data topics: ROS 2's default QoS profile (``rmw_qos_profile_default``).
DEPTH = 10
#: The largest ROS_DOMAIN_ID (ROS 2 docs, "The ROS_DOMAIN_ID": 0-101 are safe everywhere, up to 232 on Linux).
MAX_DOMAIN_ID = 232
#: How long a reliable write may wait for room (s); keep-last writers never wait, this only bounds a surprise.
MAX_BLOCKING_S = 0.1
#: The first instant ``builtin_interfaces/Time`` (``int32 sec``) cannot hold, in us since the epoch.
MAX_STAMP_US = 2**31 * 1_000_000
#: A ROS 2 name token: letters, digits and underscores, not starting with a digit, no repeated underscore.
_TOKEN = re.compile(r"(?!.*__)[A-Za-z_][A-Za-z0-9_]*")
#: ROS 2 primitive types -> cyclonedds IDL types (the ROS 2 IDL mapping: char is uint8, byte is octet).
_PRIMITIVES = ("bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
               "float32", "float64")


def dds_topic_name(ros_topic: str) -> str:
    """The DDS topic of a fully qualified ROS 2 topic: ``/a/b`` -> ``rt/a/b``."""
    if not ros_topic.startswith("/"):
        raise ValueError(f"not a fully qualified ROS topic name: {ros_topic!r}")
    return ROS_TOPIC_PREFIX + ros_topic


def dds_type_name(ros_type: str) -> str:
    """The DDS type of a ROS 2 message type: ``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def is_name_token(name: str) -> bool:
    """True if ``name`` can be one token of a ROS 2 topic name (a decoder's topic ends with its name)."""
    return _TOKEN.fullmatch(name) is not None


def default_domain_id(env: Mapping[str, str] = os.environ) -> int:
    """``ROS_DOMAIN_ID`` from ``env`` as ROS 2 reads it (unset or empty: 0); ValueError if it is not an
    integer in 0..:data:`MAX_DOMAIN_ID`."""
    text = env.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit() or int(text) > MAX_DOMAIN_ID:
        raise ValueError(f"ROS_DOMAIN_ID must be an integer in 0..{MAX_DOMAIN_ID}, got {text!r}")
    return int(text)


def _as_list(values: Any) -> list[Any]:
    """A sequence of primitives as the list cyclonedds packs in one ``struct`` call (a numpy array would not)."""
    return values.tolist() if isinstance(values, np.ndarray) else list(values)


class DdsTypes:
    """cyclonedds ``IdlStruct`` classes of ROS 2 message types, generated from ``store``'s field
    definitions (a rosbags typestore): DDS type names by :func:`dds_type_name`, the ROS field names in
    their order, no keys, final extensibility. :meth:`sample` builds a sample from the field values of
    :mod:`touchreal_client.ros2.messages` (nested dicts, numpy arrays)."""

    def __init__(self, store: Any):
        self.store = store
        self._classes: dict[str, type] = {}
        self._converters: dict[str, list[tuple[str, Callable[[Any], Any]]]] = {}

    def struct(self, ros_type: str) -> type:
        """The class of ``ros_type`` (``pkg/msg/Name``), made on first use with those it nests."""
        cls = self._classes.get(ros_type)
        if cls is None:
            from cyclonedds.idl import make_idl_struct

            fields: dict[str, Any] = {}
            converters: list[tuple[str, Callable[[Any], Any]]] = []
            for name, desc in self.store.fielddefs[ros_type][1]:
                if keyword.iskeyword(name):
                    raise TypeError(f"{ros_type}: field name {name!r} is a Python keyword")
                fields[name], convert = self._field(desc)
                converters.append((name, convert))
            cls = make_idl_struct(ros_type.rsplit("/", 1)[1] + "_", dds_type_name(ros_type), fields)
            self._classes[ros_type], self._converters[ros_type] = cls, converters
        return cls

    def sample(self, ros_type: str, values: Mapping[str, Any]) -> Any:
        """An instance of :meth:`struct` of ``ros_type`` from its field values (KeyError if one is missing)."""
        cls = self.struct(ros_type)
        return cls(**{name: convert(values[name]) for name, convert in self._converters[ros_type]})

    def type_hash(self, ros_type: str) -> str:
        """The REP-2011 type hash (``RIHS01_<sha256 hex>``) of ``ros_type``."""
        return str(self.store.hash_rihs01(ros_type))

    def _field(self, desc: tuple[Any, Any]) -> tuple[Any, Callable[[Any], Any]]:
        """(IDL type, value converter) of a rosbags field description."""
        from cyclonedds.idl import types as T
        from rosbags.typesys.base import Nodetype

        kind, detail = desc
        if kind == Nodetype.NAME:
            return self.struct(detail), lambda v, t=detail: self.sample(t, v)
        if kind == Nodetype.BASE:
            return _base_type(*detail), _identity
        inner, size = detail
        element, convert = self._field(inner)
        if kind == Nodetype.ARRAY:
            idl = T.array[element, size]
        elif kind == Nodetype.SEQUENCE:
            idl = T.sequence[element, size] if size else T.sequence[element]
        else:
            raise TypeError(f"unknown rosbags field kind {kind!r}")
        if inner[0] == Nodetype.NAME:
            return idl, lambda v, c=convert: [c(x) for x in v]
        return idl, _as_list


def _identity(value: Any) -> Any:
    return value


def _base_type(name: str, bound: int) -> Any:
    from cyclonedds.idl import types as T

    if name == "string":
        return T.bounded_str[bound] if bound else str
    if name not in _PRIMITIVES:
        raise TypeError(f"ROS type {name!r} has no DDS mapping here")
    if name == "bool":
        return bool
    return {"byte": T.byte, "char": T.uint8}.get(name) or getattr(T, name)


def writer_qos(type_hash: str, *, latched: bool) -> Any:
    """The QoS of a writer as rmw_cyclonedds makes it for ROS 2's default profile (``latched``:
    transient-local, keep-last 1), XCDR1 only, the type hash in USER_DATA."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    depth = 1 if latched else DEPTH
    policies = [Policy.Reliability.Reliable(duration(seconds=MAX_BLOCKING_S)), Policy.History.KeepLast(depth),
                Policy.DataRepresentation(use_cdrv0_representation=True),
                Policy.WriterDataLifecycle(autodispose=False), Policy.Userdata(f"typehash={type_hash};".encode())]
    if latched:  # Cyclone keeps the history a late reader gets by the durability service's history
        policies += [Policy.Durability.TransientLocal,
                     Policy.DurabilityService(cleanup_delay=0, history=Policy.History.KeepLast(depth), max_samples=-1,
                                              max_instances=-1, max_samples_per_instance=-1)]
    else:
        policies.append(Policy.Durability.Volatile)
    return Qos(*policies)


class Ros2Bridge:
    """ROS 2 topics on DDS domain ``domain_id`` (None: ``ROS_DOMAIN_ID``, else 0) fed from the stream
    at ``url`` (``ws://...`` or ``http://HOST:PORT``); channels at 5 kHz / ``decimation``.
    :attr:`ready` is set once the writers exist (:attr:`topics` then names them)."""

    def __init__(self, url: str, *, domain_id: int | None = None, decimation: int = 25):
        domain = default_domain_id() if domain_id is None else domain_id
        if not 0 <= domain <= MAX_DOMAIN_ID:
            raise ValueError(f"domain_id must be in 0..{MAX_DOMAIN_ID}, got {domain}")
        self.url, self.domain_id, self.decimation = url, domain, decimation
        self.ready = asyncio.Event()
        self.stream: AsyncStream | None = None
        self._types: DdsTypes | None = None
        self._participant: Any = None
        self._listener: Any = None
        self._writers: dict[str, Any] = {}  #: ROS topic -> DataWriter
        self._msg_types: dict[str, str] = {}  #: ROS topic -> ROS message type
        self._live: set[str] = set()  #: the data topics DDS readers are matched to
        self._decoders: tuple[Any, dict[int, tuple[str, list[str]]]] = (None, {})  #: (hello, its decoder table)
        self._changed = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None

    @property
    def topics(self) -> dict[str, str]:
        """ROS topic -> ROS message type, of every topic the bridge writes."""
        return dict(self._msg_types)

    # -- life -----------------------------------------------------------------------------------
    async def run(self) -> None:
        """Publish until cancelled or until the upstream stream ends for good (then raises
        :class:`~touchreal_client.errors.StreamClosed`). Raises :class:`TouchRealError` if the DDS
        domain cannot be joined."""
        self._loop = asyncio.get_running_loop()
        async with AsyncStream(self.url, wanted_subscription((), self.decimation)) as stream:
            self.stream = stream
            await stream.sync_clock(FIRST_SYNC_SAMPLES)
            self._join()
            try:
                self._advertise()
                await forward(stream, self._publish, self.ready, self._follow_upstream())
            finally:
                self._leave()

    def _join(self) -> None:
        from cyclonedds.core import DDSException, Listener, Policy, Qos
        from cyclonedds.domain import DomainParticipant

        self._types = DdsTypes(typestore())
        self._listener = Listener(on_publication_matched=lambda _writer, _status: self._demand_changed())
        try:
            self._participant = DomainParticipant(self.domain_id, qos=Qos(Policy.Userdata(b"enclave=/;")))
        except DDSException as exc:
            raise TouchRealError(f"cannot join DDS domain {self.domain_id} (CYCLONEDDS_URI?): {exc}") from exc

    def _leave(self) -> None:
        """Delete the writers, then the participant (each DDS entity goes with its last reference)."""
        self._writers.clear()
        self._live.clear()
        self._participant = None

    # -- writers --------------------------------------------------------------------------------
    def _writer(self, ros_topic: str, ros_type: str, *, latched: bool = False) -> Any:
        from cyclonedds.pub import DataWriter
        from cyclonedds.topic import Topic

        w = self._writers.get(ros_topic)
        if w is None:
            assert self._types is not None
            topic = Topic(self._participant, dds_topic_name(ros_topic), self._types.struct(ros_type))
            w = DataWriter(self._participant, topic, writer_qos(self._types.type_hash(ros_type), latched=latched),
                           listener=None if latched else self._listener)
            self._writers[ros_topic], self._msg_types[ros_topic] = w, ros_type
        return w

    def _advertise(self) -> None:
        """Writers for what the stream's hello offers (those already made stay), and the hello as the
        description. A population's service offers its afferents' spikes only (``taxel`` then holds
        afferent ids; the description lists the afferents)."""
        assert self.stream is not None
        hello = self.stream.hello
        classes = hello.get("classes", list(P.CLASSES))
        for c in P.CLASSES:
            if isinstance(classes, list) and c in classes:
                self._writer(M.spikes_topic(c), M.SPIKES_TYPE)
        if P.hello_afferents(hello) is None:
            self._writer(M.CHANNELS_TOPIC, M.CHANNELS_TYPE)
            self._writer(M.FORCE_TOPIC, M.FORCE_TYPE)
        for name, _ in self._decoder_table().values():
            self._writer(M.decoded_topic(name), M.DECODED_TYPE)
        self._writer(M.DESCRIPTION_TOPIC, M.DESCRIPTION_TYPE, latched=True)
        self._write(M.DESCRIPTION_TOPIC, M.description(hello))

    # -- demand ---------------------------------------------------------------------------------
    def _demand_changed(self) -> None:
        """Called on a DDS thread when a writer's matched readers change."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed in between
                loop.call_soon_threadsafe(self._changed.set)

    def _refresh_live(self) -> set[str]:
        """The data topics at least one DDS reader is matched to now, kept as :attr:`_live` (the topics
        :meth:`_publish` writes on)."""
        self._live = {t for t, w in self._writers.items()
                      if t != M.DESCRIPTION_TOPIC and w.get_publication_matched_status().current_count > 0}
        return self._live

    def _readvertise(self, _hello: dict[str, Any]) -> None:
        """A new hello's topics (new decoders, the description again); the topics already made go on if
        DDS refuses one."""
        from cyclonedds.core import DDSException

        try:
            self._advertise()
        except DDSException as exc:
            log.warning("cannot advertise the new hello's topics: %r", exc)

    async def _follow_upstream(self) -> None:
        """Keep the upstream subscription equal to the topics DDS readers are matched to (retried while
        the stream reconnects); a new hello is advertised (new decoders, the description again)."""
        assert self.stream is not None
        await follow_demand(self.stream, self._changed, self._refresh_live, self.decimation, self._readvertise)

    # -- publishing -----------------------------------------------------------------------------
    def _local_ns(self, t_us: np.ndarray) -> np.ndarray:
        """This machine's wall time (integer ns since the epoch) of wire stamps, by the clock model;
        ValueError for a time ``builtin_interfaces/Time`` cannot hold (before 1970, after 2038)."""
        assert self.stream is not None
        us = np.atleast_1d(np.asarray(self.stream.to_local(np.asarray(t_us, np.float64)), np.float64))
        if not np.all((us >= 0.0) & (us < MAX_STAMP_US)):
            raise ValueError(f"the clock model maps stamps outside builtin_interfaces/Time: {us.min()}..{us.max()} us")
        whole = np.floor(us)  # split: float64 ns since the epoch would round to 256 ns
        return whole.astype(np.int64) * 1000 + np.rint((us - whole) * 1000.0).astype(np.int64)

    def _write(self, ros_topic: str, values: Mapping[str, Any]) -> None:
        """Write the message of ``values`` (fields of :mod:`touchreal_client.ros2.messages`) on
        ``ros_topic``; ValueError for a value its field cannot hold."""
        from cyclonedds.core import DDSException

        assert self._types is not None
        sample = self._types.sample(self._msg_types[ros_topic], values)
        try:
            self._writers[ros_topic].write(sample)
        except DDSException:
            raise
        except Exception as exc:  # cyclonedds reports a value its CDR cannot encode as a bare Exception
            raise ValueError(f"{ros_topic}: {exc}") from exc

    def _publish(self, frame: P.Frame) -> None:
        """One frame's messages on the topics DDS readers want; a frame that cannot be converted or
        written is dropped with a warning (the bridge goes on)."""
        from cyclonedds.core import DDSException

        assert self.stream is not None
        if self.stream.clock.last is None:  # nothing to stamp it by (a new session's first frames)
            log.warning("dropping a %s that came before the stream's first clock point", type(frame).__name__)
            return
        try:
            publish_by_kind(frame, self._publish_spikes, self._publish_channels, self._publish_decoded)
        except (ValueError, OverflowError, TypeError, struct.error, DDSException) as exc:
            log.warning("dropping a %s (update %s): %r", type(frame).__name__, frame.header.update, exc)

    def _publish_spikes(self, f: P.SpikesFrame) -> None:
        for c in P.CLASSES:
            topic = M.spikes_topic(c)
            if topic in self._live:
                msg = M.spikes(f, c, self._local_ns)
                if msg is not None:
                    self._write(topic, msg)

    def _publish_channels(self, f: P.ChannelsFrame) -> None:
        if f.data.shape[0] == 0:
            return
        if M.CHANNELS_TOPIC in self._live:
            self._write(M.CHANNELS_TOPIC, M.channels(f, self._local_ns))
        if M.FORCE_TOPIC in self._live:
            self._write(M.FORCE_TOPIC, M.force(f, self._local_ns))

    def _publish_decoded(self, f: P.DecodedFrame) -> None:
        decoder = self._decoder_table().get(f.decoder)
        if decoder is None:  # not a decoder of the hello with a valid ROS name
            return
        name, outputs = decoder
        topic = M.decoded_topic(name)
        if topic in self._live:
            for msg in M.decoded(name, outputs, f, self._local_ns):
                self._write(topic, msg)

    def _decoder_table(self) -> dict[int, tuple[str, list[str]]]:
        """:func:`decoders_of` the stream's current hello (made once per hello)."""
        assert self.stream is not None
        hello = self.stream.hello
        if self._decoders[0] is not hello:
            self._decoders = (hello, decoders_of(hello))
        return self._decoders[1]


def decoders_of(hello: Mapping[str, Any]) -> dict[int, tuple[str, list[str]]]:
    """The decoders of a hello by the index a decoded frame names them with: (name, output names), for
    those whose name is a valid ROS 2 topic token; the others, and malformed entries, are left out (logged)."""
    streams = hello.get("streams")
    decoded = streams.get("decoded") if isinstance(streams, dict) else None
    entries = decoded.get("decoders") if isinstance(decoded, dict) else None
    entries = entries if isinstance(entries, list) else []
    table: dict[int, tuple[str, list[str]]] = {}
    for i, d in enumerate(entries):
        name = d.get("name") if isinstance(d, dict) else None
        if isinstance(name, str) and is_name_token(name):
            outputs = d.get("outputs")
            table[i] = (name, [str(o) for o in outputs] if isinstance(outputs, list) else [])
    if len(table) < len(entries):
        log.warning("decoders without a valid ROS 2 topic name are not published: %r",
                    [d.get("name") if isinstance(d, dict) else d for i, d in enumerate(entries) if i not in table][:10])
    return table
