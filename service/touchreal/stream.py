"""Online encoding as one state machine: raw chunks in, spike events out, computed on demand.

:class:`StreamEncoder` chains the :class:`~touchreal.preprocess.pipeline.Preprocessor` and one
:class:`~touchreal.encoding.encoder.Encoder` per *source* (the PVDF window a group of classes
reads, or the SingleTact alone for classes whose PVDF and dPVDF weights are all zero). The
service, the replay player, the ``encode`` command, the tests and the benchmarks all drive this
same object; offline encoding is the same object fed once.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from .encoding.encoder import Encoder, SpikeEvents
from .population.encoder import Population, PopulationEncoder
from .params import EncoderParams
from .preprocess.activity import ActivityDetector, ActivityPlan
from .preprocess.parallel import split_run
from .preprocess.pipeline import Acquisition, Channels, Preprocessor, Source, preprocess_trial_windows
from .preprocess.stft_gate import frame_length
from .recording import Trial
from .raw import RawChunk
from .sources.replay import ReplaySource
from .settings import CLASSES, OUT_FS_HZ, PVDF_FS_HZ

_BLOCK_MIN_WORK = 1000  #: taxels x PVDF samples per block range from which taxel blocks run on both cores (~0.3 ms of work)
_PVDF_WEIGHTS = slice(4, 8)  #: PVDF+, PVDF-, dPVDF+, dPVDF- in w1..w8


def class_source(params: EncoderParams, cls: str) -> Source:
    """The preprocessing source of a class: its causal window (ms), or None when all its PVDF and
    dPVDF weights are zero (it then reads the SingleTact channels alone and waits for no window)."""
    if not any(params.classes[cls].weights[_PVDF_WEIGHTS]):
        return None
    return float(params.window_ms(cls))


def class_latency_s(params: EncoderParams, cls: str) -> float:
    """Algorithmic latency of a class, the upper bound of emission minus stamp (s) with
    ``delay_ms`` excluded (the look-ahead of the branches its source reads, less the one grid
    sample a spike's stamp is ahead of its sample); a spike's stamp moves by ``delay_ms``."""
    return Preprocessor.latency_s(class_source(params, cls)) - 1.0 / OUT_FS_HZ


class _TaxelBlock:
    """The branches and encoders of a contiguous block of taxels: a Preprocessor on the shared
    acquisition and one Encoder per source. A block none of whose columns is active runs nothing;
    its branches (re)start without touching any other block's columns."""

    def __init__(self, params: EncoderParams, acquisition: Acquisition, taxels: range, groups: dict[Source, list[str]],
                 dtype: type, channels_source: Source, index: int = 0, population: Population | None = None):
        self.taxels = taxels
        self.index = index  #: position in the encoder's blocks
        self.channels_source = channels_source
        self.shows = True  #: channels wanted from this block (every taxel at first, like every column)
        self.encoders = {s: Encoder(params, len(taxels), cs) if population is None else PopulationEncoder(params, population, cs)
                         for s, cs in groups.items()}
        self.pre = Preprocessor(params.preprocess, len(taxels), dtype, sources=list(groups), acquisition=acquisition, taxels=taxels)

    def set_active(self, want: Mapping[str, Sequence[int]], shows: bool) -> None:
        """``want``: per class, the block's own (local) taxel indices (afferent ids with a population); ``shows``: channels are wanted
        from this block (its channels source then runs even when none of its columns is active)."""
        for enc in self.encoders.values():
            enc.set_columns({c: want.get(c, ()) for c in enc.classes})
        self.shows = shows
        self.pre.set_sources([s for s, enc in self.encoders.items() if enc.n_columns] + ([self.channels_source] if shows else []))

    def encode(self, slow: frozenset[Source] = frozenset(), phase: str | None = None) -> tuple[Channels | None, list[SpikeEvents]]:
        """Spikes of every active source (global taxel indices), and the channels of the channels
        source if this block shows them and it ran (else None). A ``slow`` source runs only when its
        gate has a new frame (:meth:`Preprocessor.frame_ready`). ``phase`` "fast" runs only the other
        sources, "slow" only the slow ones (None: both)."""
        channels = None
        parts = []
        for s in self.pre.sources:
            if (phase == "fast" and s in slow) or (phase == "slow" and s not in slow):
                continue
            if s in slow and not self.pre.frame_ready(s):
                continue
            ch = self.pre.take(s)
            ev = self.encoders[s].process(ch)
            parts.append(SpikeEvents(ev.t_s, ev.taxel + self.taxels.start, ev.cls) if self.taxels.start else ev)
            if self.shows and s == self.channels_source:
                channels = ch
        return channels, parts


class StreamEncoder:
    """Raw samples of N taxels -> SA1/RA/PC spike events, chunk by chunk, for the active columns.

    ``classes`` are the classes this encoder can serve (default: all of the parameter set); all
    their (class, taxel) columns and every taxel's channels are active at first (:meth:`set_active`
    changes that). Every spike is stamped on the sensor clock, ``(k + 1) / 5000 + delay_ms`` for a threshold crossing at grid
    sample k, whenever it is emitted; each source emits as soon as its own branches allow.

    ``taxel_block`` splits the taxels into blocks of that many (default: one block) that share the
    acquisition but nothing else: a block with no active column runs nothing, so a few subscribed
    taxels of a large skin cost about one block's preprocessing; with every column active, one
    block is fastest. Spikes do not depend on the blocking (per-taxel processing is independent);
    channels equal to rounding (~1e-15). ``order`` (a permutation of the taxel ids, e.g.
    :func:`~touchreal.raw.spatial_order` of their positions) is the order the blocks take the taxels
    in, so that a block is a patch of the skin rather than a strip of ids: a touch wakes, and a
    region demands, fewer blocks. Spikes and channels stay addressed by taxel id; spikes of one
    instant come sorted by id.

    ``update_s`` (the service's ``preprocess.update_ms``) splits the sources into two cadences: a
    PVDF window whose gate emits at most once per update (window / 4 >= ``update_s``: the 128 ms
    window at 32 ms) runs only in a call that completes one of its gate frames (once per frame,
    32 ms for 128 ms, and then at once); the SingleTact and the short windows run every call. A live
    source calls :meth:`process` on a short hop, so the fast classes go out on the hop and the slow
    ones keep their frame cadence without paying the hop's per-call cost. None (offline, tests):
    every source every call. Spikes are the same either way (chunk invariance); only when they are
    returned changes.

    ``dtype`` np.float32 computes the preprocessing in single precision (PCHIP, the STFT gate in
    complex64, the channels; the PVDF notch cascade, the alpha-beta tracker and the encoder's
    low-pass and membrane stay float64): 20-40 % less CPU than float64 (1024-4096 taxels),
    the channels within 1e-5 of their range and the spikes within the bound of docs/benchmarks.md
    (Encoder). float64 is the reference.

    Not thread-safe: call :meth:`set_active` between :meth:`process` calls (same thread or lock).
    """

    def __init__(
        self,
        params: EncoderParams,
        n_taxels: int = 1,
        classes: Sequence[str] | None = None,
        dtype: type = np.float64,
        taxel_block: int | None = None,
        update_s: float | None = None,
        activity: ActivityPlan | None = None,
        order: np.ndarray | None = None,
        population: Population | None = None,
    ):
        wanted = tuple(params.classes) if classes is None else tuple(classes)
        missing = [c for c in wanted if c not in params.classes]
        if missing:
            raise ValueError(f"parameter set has no class {missing}")
        if taxel_block is not None and taxel_block < 1:
            raise ValueError("taxel_block must be >= 1")
        if update_s is not None and not update_s > 0:
            raise ValueError("update_s must be > 0")
        if population is not None and (taxel_block is not None or activity is not None or order is not None):
            raise ValueError("a population runs on one taxel block (its afferents mix neighbouring taxels): no taxel_block, "
                             "activity or order")
        if population is not None and len(population.taxels_xy_mm) != n_taxels:
            raise ValueError(f"the population is built on {len(population.taxels_xy_mm)} taxels, the stream has {n_taxels}")
        self.population = population
        #: ids spikes address and columns select: taxels, or a population's afferents
        self.n_units = n_taxels if population is None else len(population)
        #: the taxels in the order the blocks take them (None: by id), and each taxel's place in it
        self._order: np.ndarray | None = None
        self._place: np.ndarray | None = None
        if order is not None:
            self._order = np.asarray(order, np.int64)
            if not np.array_equal(np.sort(self._order), np.arange(n_taxels)):
                raise ValueError(f"order must be a permutation of the {n_taxels} taxel ids")
            self._place = np.argsort(self._order)
        self.params = params
        self.n_taxels = n_taxels
        self.dtype = np.dtype(dtype)  #: of the channels and of the preprocessing's arithmetic
        self.classes = tuple(c for c in CLASSES if c in wanted)
        self.source: dict[str, Source] = {c: class_source(params, c) for c in self.classes}
        groups: dict[Source, list[str]] = {}
        for c in self.classes:
            groups.setdefault(self.source[c], []).append(c)
        windows = [s for s in groups if s is not None]
        self.acq = Acquisition(n_taxels, max(windows, default=params.preprocess.window_ms), params.preprocess)
        #: the source :meth:`process_channels` returns: the longest window served, else the SingleTact
        self.channels_source: Source = max(windows) if windows else None
        size = n_taxels if taxel_block is None else taxel_block
        self._block_starts = np.arange(0, n_taxels, n_taxels if taxel_block is None else taxel_block)
        self.blocks = [_TaxelBlock(params, self.acq, range(a, min(a + size, n_taxels)), groups, dtype, self.channels_source, i,
                                   population)
                       for i, a in enumerate(range(0, n_taxels, size))]
        self.active: dict[str, tuple[int, ...]] = {c: tuple(self.units(c)) for c in self.classes}
        #: activity-driven compute (None: dense, every demanded block runs on every chunk)
        self.detector = None if activity is None else ActivityDetector(n_taxels, activity)
        self._wants: list[tuple[dict[str, list[int]], bool]] = [
            ({c: list(range(len(b.taxels))) if population is None else list(self.active[c]) for c in self.classes}, True)
            for b in self.blocks]
        self._awake = np.ones(len(self.blocks), bool)  #: per block: running (all, until the detector says)
        self._spiked_s = np.full(len(self.blocks), -np.inf)  #: per block: sensor time (s) of its latest spikes
        self._delay_s = {c: params.classes[c].delay_ms / 1000.0 for c in self.classes}
        #: sources run only in a call that completes one of their gate frames (the others every call)
        self._work = 0  #: size of the last chunk for split_run (see _feed)
        self.slow: frozenset[Source] = frozenset(
            s for s in windows if update_s is not None and frame_length(s, PVDF_FS_HZ) / 4 / PVDF_FS_HZ >= update_s - 1e-9)

    def units(self, cls: str) -> range | np.ndarray:
        """The ids of ``cls``'s columns: every taxel, or the population's afferents of that class."""
        return range(self.n_taxels) if self.population is None else self.population.layout.ids(cls)

    # -- demand ---------------------------------------------------------------------------------
    def set_active(self, columns: Mapping[str, Iterable[int]], channels: Iterable[int] = ()) -> None:
        """Demand: per class, the taxels whose spikes are wanted (a class absent or with no taxels is
        off), and the taxels whose channels are wanted (:meth:`process_channels`).

        * Continuing columns keep their state bit-exactly: a column's spikes never depend on which
          other columns, classes or windows run.
        * A column that (re)starts starts from rest (:class:`~touchreal.encoding.encoder.Encoder`)
          at the next grid sample its source delivers: for a source that kept running, the sample
          after the last one delivered; for a source that (re)starts, the first grid sample after
          the newest raw sample received (:meth:`restart_index`).
        * A PVDF window branch runs only while an active column reads it; the PVDF filter only
          while some window runs; the SingleTact branch only while any column is active (per taxel
          block). A branch that restarts is rebuilt from the raw history acquisition keeps (no
          waiting: its class emits after its usual latency), see :meth:`Preprocessor.set_sources`.
        * Channels are always those of :attr:`channels_source` (the longest window served), which
          runs in every taxel block with channels wanted, whatever spikes are wanted.
        * With everything off, :meth:`process` only runs acquisition: the sanitizers (input
          policy and counters) and the raw history rings (the last 0.5 s of SingleTact, the last
          100 ms + two frames of the longest window of PVDF) that restarts are rebuilt from.
        """
        unknown = set(columns) - set(self.classes)
        if unknown:
            raise ValueError(f"classes {sorted(unknown)} are not served (have {list(self.classes)})")
        want = {c: tuple(sorted({int(x) for x in columns.get(c, ())})) for c in self.classes}
        shown = {int(x) for x in channels}
        bad = sorted({x for xs in want.values() for x in xs if not 0 <= x < self.n_units})
        if bad:
            raise ValueError(f"{'taxels' if self.population is None else 'afferents'} {bad} out of range 0..{self.n_units - 1}")
        bad = sorted(x for x in shown if not 0 <= x < self.n_taxels)
        if bad:
            raise ValueError(f"taxels {bad} out of range 0..{self.n_taxels - 1}")
        if self.population is not None:  # one block: afferent ids are its columns' ids; an id of another class is no column
            cls = self.population.layout.cls
            want = {c: tuple(x for x in xs if cls[x] == CLASSES.index(c)) for c, xs in want.items()}
            self._wants[0] = ({c: list(xs) for c, xs in want.items()}, bool(shown))
            self._set_block(0)
            self.active = {c: xs for c, xs in want.items() if xs}
            return
        placed, shown_at = want, shown  # by place in the blocks' order
        if self._place is not None:
            placed = {c: sorted(self._place[list(xs)].tolist()) for c, xs in want.items()}
            shown_at = set(self._place[sorted(shown)].tolist())
        for i, block in enumerate(self.blocks):
            self._wants[i] = ({c: [x - block.taxels.start for x in xs if x in block.taxels] for c, xs in placed.items()},
                              bool(shown_at.intersection(block.taxels)))
            self._set_block(i)
        self.active = {c: xs for c, xs in want.items() if xs}

    def _set_block(self, i: int) -> None:
        """Block ``i`` runs its demanded columns while awake (always, dense), and its channels source
        while channels are wanted from it, awake or not."""
        want, shows = self._wants[i]
        self.blocks[i].set_active(want if self._awake[i] else {}, shows)

    def _follow_activity(self, chunk: RawChunk) -> None:
        """Before the chunk is processed: wake the blocks in which a taxel left its band (rebuilt from
        the raw history, so this chunk's samples run through the whole chain), and stop those all of
        whose taxels have been quiet for the plan's ``hold_s``."""
        awake = self.detector.push(chunk)
        blocks = np.logical_or.reduceat(awake, self._block_starts) if self.n_taxels else awake
        ends = [a[-1] for a in (chunk.st_t, chunk.pvdf_t) if a.size]
        if ends:  # a block whose columns spiked within hold_s stays awake (its LIF has not settled)
            blocks |= self._spiked_s >= max(ends) - self.detector.plan.hold_s
        for i in np.flatnonzero(blocks != self._awake):
            self._awake[i] = blocks[i]
            self._set_block(int(i))

    def continue_activity(self, previous: StreamEncoder) -> None:
        """Take over ``previous``'s detector and awake blocks (a restart after shedding load: the scene
        did not change, so neither its learned noise nor which blocks it keeps awake starts again)."""
        if self.detector is None or previous.detector is None or len(previous.blocks) != len(self.blocks):
            return
        self.detector, self._awake, self._spiked_s = previous.detector, previous._awake.copy(), previous._spiked_s.copy()
        for i in range(len(self.blocks)):
            self._set_block(i)

    @property
    def awake_taxels(self) -> int:
        """Taxels in blocks the activity detector keeps running (all of them when dense)."""
        return int(sum(len(b.taxels) for b, a in zip(self.blocks, self._awake) if a))

    def restart_index(self) -> int | None:
        """The grid index a source that (re)started now would deliver from (None before any data)."""
        return self.acq.restart_index()

    # -- data -----------------------------------------------------------------------------------
    def process(self, chunk: RawChunk) -> SpikeEvents:
        """Spikes of the active columns that became final with this chunk, sorted by time (within
        the call; a later call may return spikes of another class stamped earlier, see :attr:`final_s`)."""
        self._feed(chunk)
        return self._encode()[1]

    def process_channels(self, chunk: RawChunk) -> tuple[Channels, SpikeEvents]:
        """Like :meth:`process`, also returning the new 5 kHz channels (for dashboards and analysis) of
        :attr:`channels_source` (its ST and dST are the SingleTact channels every source shares),
        for all taxels: NaN for taxels of blocks without channels wanted (:meth:`set_active`) and for
        samples a block that just (re)started does not have. Empty when no channels are wanted."""
        self._feed(chunk)
        return self._encode()

    def process_fast(self, chunk: RawChunk) -> tuple[Channels, SpikeEvents]:
        """The first of two phases (:meth:`process_channels` = this then :meth:`process_slow`, same
        spikes): feed ``chunk`` and run only the sources on the hop cadence, so that a live service
        can send the fast classes before it computes a slow source's frame."""
        self._feed(chunk)
        return self._encode(phase="fast")

    def slow_due(self) -> bool:
        """Whether a slow source of an active column or of the shown channels has a new frame to run."""
        return any(s in b.pre.sources and b.pre.frame_ready(s) for b in self.blocks for s in self.slow)

    def process_slow(self) -> tuple[Channels, SpikeEvents]:
        """The second phase: the slow sources whose gate completed a frame with the chunks fed so far."""
        return self._encode(phase="slow")

    def finish(self) -> SpikeEvents:
        """End of stream: flush every running branch and return the last spikes (of every source)."""
        for block in self.blocks:
            block.pre.flush()
        return self._encode(final=True)[1]

    def _feed(self, chunk: RawChunk) -> None:
        if self._order is not None:  # the blocks' order from here on; spikes and channels go back to ids in _encode
            chunk = RawChunk(chunk.st_t, chunk.st[:, self._order], chunk.pvdf_t, chunk.pvdf[:, self._order])
        if self.detector is not None:
            self._follow_activity(chunk)
        new = self.acq.push(chunk.st_t, chunk.st, chunk.pvdf_t, chunk.pvdf)
        # size of this call for split_run over blocks (taxels x new PVDF samples): blocks run on both
        # cores from ~200 taxels per 5 ms hop on (each block's kernels then run serially)
        self._work = self.n_taxels * (0 if new[1] is None else new[1][1].shape[0])
        blocks = [b for b in self.blocks if b.pre.sources]  # a stopped block has nothing to consume
        self._work = self._work * sum(len(b.taxels) for b in blocks) // max(self.n_taxels, 1)
        if len(blocks) == 1:
            blocks[0].pre.consume(*new)
            return

        def consume(a: int, b: int) -> None:
            for block in blocks[a:b]:
                block.pre.consume(*new)

        split_run(consume, len(blocks), self._work, _BLOCK_MIN_WORK)

    def _encode(self, final: bool = False, phase: str | None = None) -> tuple[Channels, SpikeEvents]:
        slow, phase = (frozenset(), None) if final else (self.slow, phase)
        running = [b for b in self.blocks if b.pre.sources]
        if len(running) == 1:
            results = [running[0].encode(slow, phase)]
        else:
            results = [(None, [])] * len(running)

            def encode(a: int, b: int) -> None:
                for i in range(a, b):
                    results[i] = running[i].encode(slow, phase)

            split_run(encode, len(running), self._work, _BLOCK_MIN_WORK)
        shown, parts = [], []
        if self.detector is not None:
            for block, (_, evs) in zip(running, results):
                if any(ev.t_s.size for ev in evs):
                    self._spiked_s[block.index] = max(float(ev.t_s.max()) for ev in evs if ev.t_s.size)
        for block, (ch, evs) in zip(running, results):
            if ch is not None:
                shown.append((block.taxels, ch))
            parts += evs
        events = SpikeEvents.concatenate(parts)
        channels = self._assemble(shown)
        if self._order is not None:  # back to taxel ids, an instant's spikes sorted by id
            taxel = self._order[events.taxel].astype(events.taxel.dtype)
            by = np.lexsort((taxel, events.t_s))
            return Channels(channels.k0, channels.data[:, self._place]), SpikeEvents(events.t_s[by], taxel[by], events.cls[by])
        if len(parts) > 1:
            by = np.argsort(events.t_s, kind="stable")
            events = SpikeEvents(events.t_s[by], events.taxel[by], events.cls[by])
        return channels, events

    def _assemble(self, shown: list[tuple[range, Channels]]) -> Channels:
        """One block's channels as they are when it covers every taxel; else the blocks' channels on
        the union of their grid ranges, NaN where a block has no samples."""
        if len(shown) == 1 and len(shown[0][0]) == self.n_taxels:
            return shown[0][1]
        spans = [(ch.k0, ch.k0 + ch.n_samples) for _, ch in shown if ch.n_samples]
        if not spans:
            return Channels(0, np.zeros((0, self.n_taxels, 4), self.dtype))
        k0, k1 = min(a for a, _ in spans), max(b for _, b in spans)
        data = np.full((k1 - k0, self.n_taxels, 4), np.nan, dtype=shown[0][1].data.dtype)
        for taxels, ch in shown:
            data[ch.k0 - k0 : ch.k0 - k0 + ch.n_samples, taxels.start : taxels.stop] = ch.data
        return Channels(k0, data)

    # -- reporting ------------------------------------------------------------------------------
    @property
    def running(self) -> dict[str, bool | tuple[float, ...] | int]:
        """Which branches run in any block: SingleTact, the PVDF filter, the PVDF windows (ms), and
        in how many taxel blocks something runs."""
        runs = [b.pre.running for b in self.blocks]
        return {
            "singletact": any(r["singletact"] for r in runs),
            "pvdf_filter": any(r["pvdf_filter"] for r in runs),
            "pvdf_windows": tuple(sorted({w for r in runs for w in r["pvdf_windows"]})),
            "blocks": sum(bool(r["singletact"]) for r in runs),
        }

    @property
    def final_s(self) -> dict[str, float]:
        """Per active class: every spike of that class stamped before this time (s, sensor clock,
        delay included) has been returned (-inf before its source has started)."""
        out = {}
        for c, xs in self.active.items():
            ks = [b.pre.cursor.get(self.source[c]) for b in self.blocks if self.source[c] in b.pre.cursor]
            if not ks:  # every block of the class is asleep: a block that wakes delivers from the restart index
                k = self.acq.restart_index()
                out[c] = -np.inf if k is None else k / OUT_FS_HZ + self._delay_s[c]
                continue
            out[c] = -np.inf if None in ks else (min(ks) + 1) / OUT_FS_HZ + self._delay_s[c]
        return out

    @property
    def latency_s(self) -> dict[str, float]:
        """Per class: :func:`class_latency_s`."""
        return {c: class_latency_s(self.params, c) for c in self.classes}

    @property
    def stats(self) -> dict[str, dict[str, int]]:
        """Input-policy counters per sensor, over all taxels (see docs/architecture.md)."""
        return self.acq.stats

    @property
    def mains_hz(self) -> float | None:
        """The stream's mains frequency (Hz) its PVDF notches follow, resolved from its first 0.1 s
        of PVDF (:mod:`touchreal.preprocess.mains`); None before."""
        return self.acq.mains.hz

    def state_arrays(self) -> dict[str, np.ndarray]:
        """All state: preprocessing stages and buffers, class input filters and membrane potentials."""
        out = self.acq.state_arrays()
        for i, block in enumerate(self.blocks):
            prefix = f"b{i}_" if len(self.blocks) > 1 else ""
            out.update({prefix + k: a for k, a in block.pre.state_arrays().items()})
            for s, enc in block.encoders.items():
                name = "st" if s is None else f"{s:g}ms"
                out.update({f"{prefix}{name}_{k}": a for k, a in enc.state_arrays().items()})
        return out

    def state_report(self) -> tuple[bool, float, int]:
        """(all finite, largest magnitude, total bytes) over :meth:`state_arrays`."""
        arrays = self.state_arrays().values()
        finite = all(bool(np.all(np.isfinite(a))) for a in arrays)
        peak = max((float(np.max(np.abs(a))) for a in arrays if a.size), default=0.0)
        return finite, peak, sum(a.nbytes for a in arrays)


def class_channels(trial: Trial, params: EncoderParams, classes: Sequence[str] | None = None) -> dict[str, Channels]:
    """One taxel's whole-recording channels per class, each on its own source (window, or the
    SingleTact alone), every distinct source computed once: the offline counterpart of the
    stream for fitting and evaluation (``encode_population`` on a class's channels gives the
    spikes :func:`encode_trial` gives)."""
    classes = [c for c in CLASSES if c in params.classes and (classes is None or c in classes)]
    sources = {c: class_source(params, c) for c in classes}
    channels = preprocess_trial_windows(trial, params.preprocess, list(sources.values()))
    return {c: channels[sources[c]] for c in classes}


def encode_chunks(
    params: EncoderParams, chunks: Iterable[RawChunk], n_taxels: int = 1, dtype: type = np.float64, classes: Sequence[str] | None = None,
    update_s: float | None = None, population: Population | None = None,
) -> SpikeEvents:
    """Encode a finite stream of chunks (flushing at the end), every class on its own window
    (``update_s``: the slow sources' cadence, see :class:`StreamEncoder`; it never changes the spikes;
    ``population``: spikes of its afferents instead of one per taxel and class)."""
    se = StreamEncoder(params, n_taxels, classes, dtype=dtype, update_s=update_s, population=population)
    parts = [se.process(c) for c in chunks]
    parts.append(se.finish())
    return SpikeEvents.concatenate(parts)


def encode_trial(
    trial: Trial, params: EncoderParams, update_s: float | None = None, dtype: type = np.float64, classes: Sequence[str] | None = None
) -> dict[str, np.ndarray]:
    """Spike times (s, recording clock) per class for one recorded trial, every class on its own window.

    ``update_s=None`` feeds the whole recording at once; otherwise it is replayed in chunks of
    ``update_s`` seconds. Both give identical spikes (one code path).
    """
    src = ReplaySource(trial)
    chunks = [src.read(trial.duration_s + 1.0)] if update_s is None else src.chunks(update_s)
    events = encode_chunks(params, chunks, dtype=dtype, classes=classes)
    return {c: events.train(c) for c in CLASSES if c in params.classes and (classes is None or c in classes)}
