"""The acquisition + encoding loop, on its own thread.

Once per hop (``serve --hop-ms``) it reads the source's next chunk (the source paces itself: real
time, a replay's speed, or the serial device), looks at the current :class:`~.demand.Demand`, runs
the :class:`~touchreal.stream.StreamEncoder` on exactly that (short windows every hop, long ones
once per gate frame: ``update_s``), and hands an :class:`Update` to
``publish`` (which must not block: the service posts it to the event loop). The decoders run after
that, on the update's spikes, and their outputs follow as an update of their own (same number), so
spikes never wait for a decoder. The network side can
therefore never stall acquisition, and compute never stalls the network side.

What runs follows the demand (``StreamEncoder.set_active``): only the demanded (taxel, class)
columns and the branches they read; while nobody wants anything, only acquisition (the input
policy and the raw history a branch restarts from, so a returning subscriber waits for no warm-up). A new
parameter revision is swapped in between two updates: every update is made by one revision, which
its frames carry (``params_rev``).

Real time, or honest about it: a chunk whose spikes would leave more than ``max_lag_s`` after its
oldest sample is dropped with the backlog behind it, and the pipeline restarts (:meth:`Runtime._shed`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from touchreal_client.clock import ClockMap, ClockPoint
from touchreal_client.protocol import FLAG_PARAMS_CHANGED, FLAG_RESTARTED, FLAG_SOURCE_GAP

from ..encoding.encoder import SpikeEvents
from ..params import EncoderParams
from ..population.encoder import Population
from ..preprocess.activity import ActivityPlan
from ..preprocess.pipeline import Channels
from ..sources.live import LiveSource
from ..raw import RawChunk, spatial_order
from ..settings import CLASSES, PVDF_FS_HZ, ST_FS_HZ
from ..stream import StreamEncoder
from .demand import Demand

log = logging.getLogger("touchreal.server")

_SOURCE_FAULTS = ("gaps", "crc_errors", "resyncs", "reconnects", "bad_times")  # source counters that flag a gap
_SANITIZER_FAULTS = ("non_finite", "gaps", "bad_time", "duplicate", "out_of_range")
_DRAIN_TO = 0.25  #: a shed drops chunks until one is less than this fraction of max_lag_s old
_RTF_AVERAGE_S = 1.0  #: the compute cost (and so the real-time factor) averages over about this much signal (s)


def wall_us() -> int:
    return time.time_ns() // 1000


class _ComputeCost:
    """What a chunk will cost to encode (s of wall time), learned from the chunks before it: the fast
    phase in proportion to the chunk's signal time, plus, once a slow source's frame falls due (every
    ``update_s`` of signal or so), the slow phase in proportion to the signal since its last run. A
    slow frame costs many fast hops on a large skin, so one average per second of signal would
    promise a chunk the time its slow frame then takes."""

    def __init__(self, average_s: float = _RTF_AVERAGE_S):
        self.average_s = average_s
        self.fast_per_s = 0.0  #: fast phase: wall s per s of signal
        self.slow_per_s = 0.0  #: slow phase: wall s per s of signal since its previous run
        self.slow_every_s = float("inf")  #: signal between two slow runs (s), as last seen
        self._since_slow_s = 0.0

    def predict_s(self, span_s: float) -> float:
        """The compute (s) a chunk of ``span_s`` of signal will take, its slow frame included if one falls due."""
        slow = self._since_slow_s + span_s >= self.slow_every_s
        return self.fast_per_s * span_s + (self.slow_per_s * (self._since_slow_s + span_s) if slow else 0.0)

    def restart(self) -> None:
        """A new pipeline: nothing fed since its (first) slow frame."""
        self._since_slow_s = 0.0

    def fast(self, span_s: float, spent_s: float) -> None:
        if span_s > 0:
            self.fast_per_s += min(1.0, span_s / self.average_s) * (spent_s / span_s - self.fast_per_s)
            self._since_slow_s += span_s

    def slow(self, spent_s: float) -> None:
        if self._since_slow_s > 0:
            self.slow_per_s += min(1.0, self._since_slow_s / self.average_s) * (spent_s / self._since_slow_s - self.slow_per_s)
            self.slow_every_s = self._since_slow_s
        self._since_slow_s = 0.0


@dataclass
class Update:
    """What one update produced, on the wire clock (integer us; sensor clock + segment offset)."""

    update: int
    params_rev: int
    flags: int
    acq_us: int  #: wall clock when the chunk was read from the source
    emit_us: int  #: wall clock when the update was handed to the hub
    t_us: np.ndarray  #: (n,) uint64 spike stamps, sorted
    taxel: np.ndarray  #: (n,) uint16
    cls: np.ndarray  #: (n,) uint8 index into CLASSES
    final_us: dict[str, int]  #: per computed class: all its spikes stamped before this are out
    channels: Channels | None = None
    offset_us: int = 0
    decoded: list[tuple[str, tuple[int, ...], np.ndarray, np.ndarray]] = field(default_factory=list)
    compute_s: float = 0.0
    #: per class, per spike: emit minus the acquisition of its causing sample (s, clock model)
    latency_us: dict[str, np.ndarray] = field(default_factory=dict)
    #: False for an update that carries only channels (a gateway's channels frame) or only decoded outputs
    spikes: bool = True
    clock: ClockPoint | None = None  #: the source's clock model after this update's chunk

    @classmethod
    def without_spikes(cls, update: int, params_rev: int, flags: int, acq_us: int, emit_us: int,
                       channels: Channels | None = None, offset_us: int = 0, decoded: list | None = None,
                       clock: ClockPoint | None = None) -> Update:
        """An update that carries only channels or only decoded outputs (``spikes`` False)."""
        none = np.zeros(0, np.uint64)
        return cls(update, params_rev, flags, acq_us, emit_us, none, none.astype(np.uint16), none.astype(np.uint8), {},
                   channels, offset_us, decoded or [], spikes=False, clock=clock)


class Runtime:
    """The acquisition thread of one source. ``demand()`` returns the current Demand, ``params()``
    the active (revision, EncoderParams), ``publish(update)`` must return at once."""

    def __init__(
        self,
        source: LiveSource,
        demand: Callable[[], Demand],
        params: Callable[[], tuple[int, EncoderParams]],
        publish: Callable[[Update], None],
        make_decoder: Callable[[str, tuple[int, ...]], object] | None = None,
        taxel_block: int | None = None,
        fallback: Callable[[int, int | None, Exception], bool] | None = None,
        on_end: Callable[[], None] | None = None,
        dtype: str = "float64",
        activity: ActivityPlan | None = None,
        max_lag_s: float = 0.25,
        on_shed: Callable[[float, bool], None] | None = None,
        population: Population | None = None,
        scan_speed: Callable[[], float | None] = lambda: None,
    ):
        self.source = source
        #: the scanning speed (mm/s) decoders that read one get with every update (None: not scanning)
        self._scan_speed = scan_speed
        #: the afferents spikes address (None: one per taxel and class); a population runs on one block
        self.population = population
        if population is not None:
            taxel_block = None
        #: activity-driven compute for the StreamEncoder (None: dense); only a skin larger than one taxel block
        #: uses it (it then runs the awake taxels, grouped by itself): a single block always runs, so its spikes
        #: are the offline encoder's bit for bit
        blocks = taxel_block is not None and source.n_taxels > taxel_block
        self.activity = activity if blocks else None
        #: the order dense blocks take the taxels in: patches of the skin (:func:`~touchreal.raw.spatial_order`)
        self.order = spatial_order(source.positions_mm) if blocks and self.activity is None else None
        #: a chunk whose spikes would leave more than this (s) after its oldest sample is shed (:meth:`_shed`)
        self.max_lag_s = max_lag_s
        #: a replay is never shed: its frames stay ``touchreal encode``'s, and one that falls behind catches up
        #: (its pace hands the missed chunks over back to back); its lag is reported all the same
        self._sheds = not getattr(source, "replayed", False)
        #: told (seconds of signal, whether a new shed began) of every dropped chunk (on this thread; must not block)
        self._on_shed = on_shed
        self._draining = False  #: a shed is dropping the backlog
        self.lag_s = 0.0  #: age (s, clock model) of the latest chunk's oldest sample when its compute started
        self._cost = _ComputeCost()  #: what the next chunk will cost, from what the recent ones did
        self.shed_s = 0.0  #: seconds of signal acquired but not encoded because compute was behind
        self.sheds = 0  #: chunks shed
        self.last_shed_us: int | None = None  #: wall clock (us) of the latest shed
        #: StreamEncoder's taxel_block (None: one block, or the awake set's blocks with activity-driven compute)
        self.taxel_block = None if self.activity is not None else taxel_block
        self.dtype = np.dtype(dtype)  #: StreamEncoder's dtype (the preprocessing's arithmetic)
        self._demand, self._params, self._publish = demand, params, publish
        self._make_decoder = make_decoder
        #: ``fallback(failed rev, last good rev or None, error)``: on a pipeline failure, activate
        #: other parameters and return True to keep streaming (False: the runtime fails)
        self._fallback = fallback
        self.good_rev: int | None = None  #: the last revision that completed an update
        self._on_end = on_end  #: called on this thread once the source has ended and its last spikes are published
        self.decoders: dict[str, object] = {}  #: name -> StreamingDecoder for the demanded taxels
        self.encoder: StreamEncoder | None = None
        self.enc_rev = 0
        self.enc_segment = source.segment
        self.enc_offset_us = source.offset_us  #: wire offset of the segment the encoder runs on
        self.active: dict[str, tuple[int, ...]] | None = None
        self.active_channels: tuple[int, ...] = ()
        self.update_no = 0
        self.state = "starting"  #: starting | idle | waiting (a replay, for demand) | running | shedding | ended | stopped | failed
        self.error: str | None = None
        #: the source's clock model (maps a spike's cause to the moment its sample was acquired)
        self.clocks = ClockMap()
        self.clock: ClockPoint | None = None
        self.counters: dict[str, int] = {}  #: cumulative sanitizer + source fault counters
        self._enc_stats: dict[str, int] = {}
        self._src_faults = self._source_faults()
        self._pending_flags = FLAG_RESTARTED
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="touchreal-acquisition", daemon=True)

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self.source.close()
        self._thread.join(timeout)
        self.state = "stopped"

    def _run(self) -> None:
        waits = getattr(self.source, "waits_for_demand", False)
        paused = False
        try:
            while not self._stop.is_set():
                if waits and self._demand().empty:  # a replay holds still until somebody subscribes
                    self.state, paused = "waiting", True
                    self._stop.wait(0.01)
                    continue
                if paused:
                    self.source.resume()
                    paused = False
                chunk = self.source.next_chunk()
                if chunk is None:
                    self._end_of_stream()
                    break
                clock = getattr(self.source, "clock", None)  # a source without a clock model: see step()
                self._step_or_fall_back(chunk, clock() if clock is not None else None)
        except Exception as exc:  # the service reports it (ready goes false); clients stay connected
            log.exception("acquisition thread failed")
            self.state, self.error = "failed", f"{type(exc).__name__}: {exc}"

    def _step_or_fall_back(self, chunk: RawChunk, clock: ClockPoint | None) -> None:
        """One update; if the encoder fails, let ``fallback`` swap the parameters and go on with a
        fresh encoder from the next chunk (the failed chunk's spikes are lost, flagged as a restart)."""
        try:
            self.step(chunk, wall_us(), clock)
            self.good_rev = self.enc_rev
        except Exception as exc:
            failed = self.enc_rev
            if self._fallback is None or not self._fallback(failed, self.good_rev, exc):
                raise
            log.error("parameter revision %d failed in the pipeline (%s: %s); fell back", failed, type(exc).__name__, exc,
                      exc_info=True)
            self.encoder, self.decoders = None, {}
            self._pending_flags |= FLAG_RESTARTED

    # -- one update -----------------------------------------------------------------------------
    def step(self, chunk: RawChunk, acq_us: int, clock: ClockPoint | None = None) -> Update | None:
        """Process one chunk read at ``acq_us`` (wall clock, us); ``clock``: the source's clock model
        after it (default: the chunk's newest sample acquired at ``acq_us``). Returns the published update."""
        if self.source.segment != self.enc_segment:  # a new replayed trial: flush, restart from rest
            self._flush_segment(acq_us)
        self._follow_clock(chunk, acq_us, clock)
        flags = self._pending_flags | self._source_flags()
        demand = self._demand()
        if not demand.empty:  # real time, or honest about it: before anything is built or computed
            self.lag_s = self._lag_s(chunk, wall_us())
            # the chunk's spikes would leave this late: its lag plus its predicted compute (while a shed drops
            # the backlog, the lag alone: nothing is computed then)
            due_s = self.lag_s + (0.0 if self._draining else self._cost.predict_s(self._span_s(chunk)))
            if self._sheds and due_s > (self.max_lag_s * _DRAIN_TO if self._draining else self.max_lag_s):
                if self.encoder is not None:  # its compute is dropped, not what the activity detector learns from it
                    self.encoder.observe(chunk)
                self._shed(chunk)
                return None
            self._draining = False
        rev, params = self._params()
        if self.encoder is not None and rev != self.enc_rev:
            flags |= FLAG_PARAMS_CHANGED | FLAG_RESTARTED
            self.encoder = None
        if self.encoder is None:
            self._new_encoder(rev, params)
        self._follow_decoder_demand(demand)
        self._apply_demand(demand)
        if demand.empty:  # acquisition only (input policy, raw history for a warm restart)
            self.encoder.process(chunk)
            flags |= self._count_sanitizer()
            self.state = "idle"
            return None
        # two phases: the hop's fast classes go out before a slow source (PC's 128 ms window) runs its frame
        t0 = time.perf_counter()
        ch, ev = self.encoder.process_fast(chunk)
        compute = time.perf_counter() - t0
        self._cost.fast(self._span_s(chunk), compute)
        flags |= self._count_sanitizer()
        if self._late(chunk):  # the estimate fell short: these spikes would leave after the bound
            self._pending_flags |= flags
            return None
        self._pending_flags = 0
        self.state = "running"
        upd = self._emit(ev, flags, acq_us, compute, ch if demand.channel_taxels else None)
        if self.encoder.slow_due():
            t0 = time.perf_counter()
            ch, ev = self.encoder.process_slow()
            self._cost.slow(time.perf_counter() - t0)
            if self._late(chunk):
                return None
            upd = self._emit(ev, 0, acq_us, time.perf_counter() - t0, ch if demand.channel_taxels else None)
        return upd

    def _late(self, chunk: RawChunk) -> bool:
        """After a phase's compute: if its spikes would now leave more than ``max_lag_s`` after the chunk's
        oldest sample, they are dropped and the pipeline sheds (:meth:`_shed`), so no spike leaves later
        than the bound whatever the estimate said."""
        if not self._sheds:
            return False
        self.lag_s = self._lag_s(chunk, wall_us())
        if self.lag_s <= self.max_lag_s:
            return False
        self._shed(chunk)
        return True

    # -- real time, or honest about it ----------------------------------------------------------
    def _lag_s(self, chunk: RawChunk, now_us: int) -> float:
        """How old the chunk's oldest sample is (s) now, by the clock model: what its spikes have
        lost before any compute (0 without a clock model)."""
        starts = [a[0] for a in (chunk.st_t, chunk.pvdf_t) if a.size]
        if not starts or self.clocks.last is None:
            return 0.0
        oldest_us = min(starts) * 1e6 + self.source.offset_us
        return max(0.0, (now_us - float(self.clocks.to_server_wall_us(oldest_us))) / 1e6)

    def _shed(self, chunk: RawChunk) -> None:
        """Compute fell behind: this chunk's spikes would leave more than ``max_lag_s`` after its oldest
        sample (its lag plus its compute at the recent real-time factor). This chunk, and every chunk after it until
        one is less than ``max_lag_s * _DRAIN_TO`` old (the backlog), is dropped, and the pipeline
        starts again from rest at the next one, as at a stream's start (flagged ``restarted`` and
        ``source_gap``; warm-up follows). Restarting from rest costs a constructor, where rebuilding
        the branches from the raw history would cost about as much compute as the history is long
        and would keep an overloaded pipeline behind. ``on_shed`` tells the clients (a ``seq`` gap,
        counted as ``upstream_loss``) and the metrics."""
        seconds = self._span_s(chunk)
        self.shed_s += seconds
        self.last_shed_us = wall_us()
        self._pending_flags |= FLAG_RESTARTED | FLAG_SOURCE_GAP
        self.state = "shedding"
        if self._draining:  # the same shed: the backlog is being dropped
            if self._on_shed is not None:
                self._on_shed(seconds, False)
            return
        self._draining = True
        self.sheds += 1
        # the new pipeline is built now (keeping what the activity detector learned of the scene): the chunks
        # acquired meanwhile are part of the backlog dropped
        self._new_encoder(*self._params(), continues=self.encoder)
        self._apply_demand(self._demand())
        log.warning("compute is %.0f ms behind acquisition (max_lag_ms %.0f): %.0f ms of signal shed, the pipeline "
                    "restarts from rest", self.lag_s * 1e3, self.max_lag_s * 1e3, seconds * 1e3)
        if self._on_shed is not None:
            self._on_shed(seconds, True)

    @staticmethod
    def _span_s(chunk: RawChunk) -> float:
        """The chunk's signal time (s): its PVDF samples at the PVDF rate, else its SingleTact samples."""
        return chunk.pvdf_t.size / PVDF_FS_HZ if chunk.pvdf_t.size else chunk.st_t.size / ST_FS_HZ

    @property
    def real_time_factor(self) -> float:
        """Wall time spent computing per second of signal, about a 1 s average (< 1 keeps up)."""
        return self._cost.fast_per_s + self._cost.slow_per_s

    def _apply_demand(self, demand: Demand) -> None:
        """Make the encoder compute what ``demand`` asks of the classes it serves."""
        columns = {c: t for c, t in demand.columns.items() if c in self.encoder.classes}
        if columns != self.active or demand.channel_taxels != self.active_channels:
            self.encoder.set_active(columns, demand.channel_taxels)
            self.active, self.active_channels = columns, demand.channel_taxels

    def _new_encoder(self, rev: int, params: EncoderParams, continues: StreamEncoder | None = None) -> None:
        """A pipeline from rest for parameter revision ``rev`` (every column demanded until set_active);
        ``continues``: the one it replaces after a shed (its mains and activity detector carry over)."""
        self.enc_rev, self.active, self._enc_stats = rev, None, {}
        self.encoder = StreamEncoder(params, self.source.n_taxels, taxel_block=self.taxel_block, dtype=self.dtype,
                                     update_s=params.preprocess.update_ms / 1000.0, activity=self.activity,
                                     order=self.order, population=self.population, continues=continues)
        self.decoders = {}
        self._cost.restart()

    def _flush_segment(self, acq_us: int) -> None:
        """The source began its next segment (a replayed trial): the encoder's last spikes go out
        stamped on the segment they belong to, with the decoders that read it; the next frame, the
        new segment's first, is flagged restarted."""
        tail = self._finish_encoder()
        if tail is not None:
            self._emit(tail, 0, acq_us, 0.0, None)
        self.decoders = {}
        self.enc_segment, self.enc_offset_us = self.source.segment, self.source.offset_us
        self._pending_flags |= FLAG_RESTARTED

    def _follow_clock(self, chunk: RawChunk, acq_us: int, clock: ClockPoint | None) -> None:
        if clock is None:  # a source without a clock model: its newest sample arrived when the chunk was read
            ends = [a[-1] for a in (chunk.st_t, chunk.pvdf_t) if a.size]
            if not ends:
                return
            last = self.clocks.last
            clock = ClockPoint(int(round(max(ends) * 1e6)) + self.source.offset_us, acq_us, 1.0, 0,
                               last.epoch if last is not None else 0)
        if self.clocks.update(clock) is not None:
            self.clock = clock

    def _finish_encoder(self) -> tuple[SpikeEvents, int, dict[str, float], dict[str, float]] | None:
        if self.encoder is None:
            return None
        ev = self.encoder.finish()
        out = (ev, self.enc_offset_us, dict(self.encoder.final_s), self._delays())
        self.encoder = None
        return out

    def _end_of_stream(self) -> None:
        if self._stop.is_set():
            return
        tail = self._finish_encoder()
        if tail is not None:
            self._emit(tail, 0, wall_us(), 0.0, None)
        self.state = "ended"
        if self._on_end is not None:
            self._on_end()

    def _delays(self) -> dict[str, float]:
        p = self.encoder.params if self.encoder is not None else self._params()[1]
        return {c: p.classes[c].delay_ms / 1000.0 for c in p.classes}

    def _emit(self, ev, flags: int, acq_us: int, compute_s: float, channels: Channels | None) -> Update:
        if isinstance(ev, tuple):  # a flushed segment tail: (events, its offset, its finals, its delays)
            ev, offset_us, final_s, delays = ev
        else:
            offset_us, final_s, delays = self.source.offset_us, dict(self.encoder.final_s), self._delays()
        # stamps are >= 0: grid samples count from the clock's zero and class delays are >= 0
        t_us = (np.round(ev.t_s * 1e6).astype(np.int64) + offset_us).astype(np.uint64)
        taxel, cls = ev.taxel.astype(np.uint16), ev.cls.astype(np.uint8)
        final_us = {c: int(round(v * 1e6)) + offset_us if np.isfinite(v) else 0 for c, v in final_s.items()}
        self.update_no += 1
        emit = wall_us()
        latency = {}
        if self.clocks.last is not None:
            for i, c in enumerate(CLASSES):
                sel = cls == i
                if sel.any():
                    cause_us = (ev.t_s[sel] - delays.get(c, 0.0)) * 1e6 + offset_us
                    latency[c] = (emit - self.clocks.to_server_wall_us(cause_us)) / 1e6
        upd = Update(self.update_no, self.enc_rev, flags, acq_us, emit, t_us, taxel, cls, final_us, channels, offset_us,
                     [], compute_s, latency, clock=self.clock)
        self._publish(upd)
        decoded = self._decode(upd)  # after the spikes went out: they never wait for the decoders
        if decoded:
            self._publish(Update.without_spikes(self.update_no, self.enc_rev, flags, acq_us, wall_us(), offset_us=offset_us,
                                                decoded=decoded, clock=self.clock))
        return upd

    def _follow_decoder_demand(self, demand: Demand) -> None:
        """Keep one streaming decoder per demanded model, for its demanded taxels (a decoder whose
        taxels change starts afresh; one nobody wants is dropped)."""
        if self._make_decoder is None:
            return
        for name in [n for n in self.decoders if n not in demand.decoders]:
            del self.decoders[name]
        for name, taxels in demand.decoders.items():
            dec = self.decoders.get(name)
            if dec is None or tuple(dec.taxels) != taxels:
                self.decoders[name] = self._make_decoder(name, taxels)

    def _decode(self, upd: Update) -> list:
        """Decoded outputs completed by this update: (name, taxels, step times (n,), values (n, taxels, outputs))."""
        out = []
        for name, dec in self.decoders.items():
            steps = dec.push(upd.t_us, upd.taxel, upd.cls, upd.final_us, self._scan_speed())
            if steps:
                t_us = np.array([t for t, _ in steps], np.uint64)
                out.append((name, tuple(int(t) for t in dec.taxels), t_us,
                            np.stack([v for _, v in steps])))
        return out

    # -- counters -------------------------------------------------------------------------------
    def _source_faults(self) -> dict[str, int]:
        st = self.source.status()
        return {k: int(st.get(k, 0)) for k in _SOURCE_FAULTS}

    def _source_flags(self) -> int:
        now = self._source_faults()
        flag = FLAG_SOURCE_GAP if any(now[k] > self._src_faults[k] for k in now) else 0
        for k in now:
            self.counters[f"source_{k}"] = now[k]
        self._src_faults = now
        return flag

    def _count_sanitizer(self) -> int:
        """Accumulate the encoder's sanitizer counters; FLAG_SOURCE_GAP when samples were missing or
        non-finite (repaired by the input policy)."""
        flag = 0
        for sensor, stats in self.encoder.stats.items():
            for k in _SANITIZER_FAULTS:
                key = f"{sensor}_{k}"
                v = int(stats.get(k, 0))
                delta = v - self._enc_stats.get(key, 0)
                if delta > 0:
                    self.counters[key] = self.counters.get(key, 0) + delta
                    flag |= FLAG_SOURCE_GAP if k in ("gaps", "non_finite") else 0
                self._enc_stats[key] = v
        return flag
