"""Online encoding as one state machine: raw chunks in, spike events out, computed on demand.

:class:`StreamEncoder` chains the :class:`~touchreal.preprocess.pipeline.Preprocessor` and one
:class:`~touchreal.encoding.encoder.Encoder` per *source* (the PVDF window a group of classes
reads, or the SingleTact alone for classes whose PVDF and dPVDF weights are all zero). The
service, the replay player, the ``encode`` command, the tests and the benchmarks all drive this
same object; offline encoding is the same object fed once.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace

import numpy as np

from .encoding.encoder import Encoder, SpikeEvents, ih_basis
from .population.encoder import Population, PopulationEncoder
from .params import EncoderParams
from .preprocess.activity import ActivityDetector, ActivityPlan
from .preprocess.parallel import split_run
from .preprocess.pipeline import MIN_LAG_S, Acquisition, Channels, Preprocessor, Source, preprocess_trial_windows
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


MEMORY_TAUS = 5.0  #: a decay has left e^-5 (0.7 %) of its start after this many time constants


def chain_memory_s(params: EncoderParams, classes: Sequence[str]) -> float:
    """How long (s) the chain of ``classes`` may still act on an input after its raw samples went
    quiet: per class, its source's longest window (a loud sample stays in the gate's frames that
    long), its negative-part lead, its post-spike current and :data:`MEMORY_TAUS` time constants of
    its membrane and of its input high-pass (their residues fall below 1 % of where they started).
    Activity-driven compute holds a taxel awake at least this long after its last loud chunk or
    spike, so a neuron that restarts from rest has forgotten nothing the dense chain remembers."""
    longest = 0.0
    ih_s = ih_basis().shape[1] / OUT_FS_HZ
    for c in classes:
        cp = params.classes[c]
        window_s = (class_source(params, c) or 0.0) / 1000.0
        highpass_s = 0.0 if cp.highpass_hz is None else 1.0 / (2.0 * np.pi * cp.highpass_hz)
        longest = max(longest, window_s + cp.negative_lead_ms / 1000.0 + ih_s
                      + MEMORY_TAUS * (cp.tau_ms / 1000.0 + highpass_s))
    return longest


class _TaxelBlock:
    """The branches and encoders of a block of taxels (a contiguous range, or any array of taxel
    places): a Preprocessor on the shared acquisition and one Encoder per source. A block none of
    whose columns is active runs nothing; its branches (re)start without touching any other
    block's columns. ``start``: per source, the grid index it delivers from (see :class:`Preprocessor`)."""

    def __init__(self, params: EncoderParams, acquisition: Acquisition, taxels: range | np.ndarray, groups: dict[Source, list[str]],
                 dtype: type, channels_source: Source, population: Population | None = None,
                 start: dict[Source, int | None] | None = None, want: Mapping[str, Sequence[int]] | None = None,
                 shows: bool = True, sources: Sequence[Source] | None = None):
        self.taxels = taxels
        self.channels_source = channels_source
        self.shows = shows  #: channels wanted from this block (every taxel at first, like every column)
        if population is not None:
            self.encoders = {s: PopulationEncoder(params, population, cs) for s, cs in groups.items()}
        else:  # every column at first, or ``want``
            self.encoders = {s: Encoder(params, len(taxels), cs, None if want is None else {c: want.get(c, ()) for c in cs})
                             for s, cs in groups.items()}
        self.pre = Preprocessor(params.preprocess, len(taxels), dtype, sources=list(groups) if sources is None else sources,
                                acquisition=acquisition, taxels=taxels, start=start)

    @staticmethod
    def gather(parts: list[tuple["_TaxelBlock", np.ndarray]], want: Mapping[str, Sequence[int]], shows: bool) -> "_TaxelBlock":
        """One block over the local taxels ``idx`` of each part, in order (parts with the same sources
        at the same read positions), running ``want`` (per class, the result's local taxels): the
        branches and the continuing columns keep their state bit for bit (:meth:`Preprocessor.gather`,
        :meth:`Encoder.gather`)."""
        out = copy.copy(parts[0][0])
        out.taxels = np.concatenate([np.asarray(b.taxels, np.int64)[idx] for b, idx in parts])
        out.pre = Preprocessor.gather([(b.pre, idx) for b, idx in parts])
        out.encoders = {s: Encoder.gather([(b.encoders[s], idx) for b, idx in parts], {c: want.get(c, ()) for c in enc.classes})
                        for s, enc in parts[0][0].encoders.items()}
        out.shows = shows
        return out

    def set_active(self, want: Mapping[str, Sequence[int]], shows: bool, sources: Sequence[Source] | None = None) -> None:
        """``want``: per class, the block's own (local) taxel indices (afferent ids with a population); ``shows``: channels are wanted
        from this block (its channels source then runs even when none of its columns is active); ``sources``: the
        sources it runs (default: those of its active columns, and the channels source when it shows channels)."""
        for enc in self.encoders.values():
            enc.set_columns({c: want.get(c, ()) for c in enc.classes})
        self.shows = shows
        if sources is None:
            sources = [s for s, enc in self.encoders.items() if enc.n_columns] + ([self.channels_source] if shows else [])
        self.pre.set_sources(sources)

    def ids(self, local: np.ndarray) -> np.ndarray:
        """Taxel places of local indices."""
        if isinstance(self.taxels, range):
            return local + self.taxels.start if self.taxels.start else local
        return self.taxels[local]

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
            parts.append(SpikeEvents(ev.t_s, self.ids(ev.taxel), ev.cls))
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
    in, so that a block is a patch of the skin rather than a strip of ids: a
    region demands fewer blocks. ``activity`` (an :class:`ActivityPlan`) instead runs only the
    taxels a contact keeps awake, grouped by the encoder itself (no ``taxel_block`` or ``order``;
    :meth:`_follow_activity`). ``continues``, the pipeline this one replaces after shedding load,
    hands over the source's mains frequency and, activity-driven, its detector and the taxels it
    keeps awake (only those start). Spikes and channels stay addressed by taxel id; spikes of one
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
        continues: "StreamEncoder | None" = None,
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
        if activity is not None and (taxel_block is not None or order is not None):
            raise ValueError("activity-driven compute groups the awake taxels itself: no taxel_block or order")
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
        carried = continues is not None and continues.n_taxels == n_taxels  #: a restart after a shed, of the same skin
        # the mains resolved on this source, unless the restart brings preprocessing of other candidates or notches
        mains_hz = continues.acq.mains.hz if carried and continues.params.preprocess == params.preprocess else None
        self.acq = Acquisition(n_taxels, max(windows, default=params.preprocess.window_ms), params.preprocess, mains_hz)
        #: the source :meth:`process_channels` returns: the longest window served, else the SingleTact
        self.channels_source: Source = max(windows) if windows else None
        self._groups = groups
        size = n_taxels if taxel_block is None else taxel_block
        self.blocks = [] if activity is not None else [
            _TaxelBlock(params, self.acq, range(a, min(a + size, n_taxels)), groups, dtype, self.channels_source, population)
            for a in range(0, n_taxels, size)]
        self.active: dict[str, tuple[int, ...]] = {c: tuple(self.units(c)) for c in self.classes}
        #: dense: per block, its demand (per class its local columns; whether it shows channels)
        self._wants: list[tuple[dict[str, list[int]], bool]] = [
            ({c: list(range(len(b.taxels))) if population is None else list(self.active[c]) for c in self.classes}, True)
            for b in self.blocks]
        if activity is not None:  # the hold covers the chain's memory of these parameters
            activity = replace(activity, hold_s=max(activity.hold_s, chain_memory_s(params, self.classes)))
        #: activity-driven compute (None: dense, every demanded block runs on every chunk)
        self.detector = None if activity is None else ActivityDetector(n_taxels, activity)
        #: activity-driven: per class, the taxels whose spikes are wanted; the taxels whose channels are wanted
        self._demand = {c: np.ones(n_taxels, bool) for c in self.classes}
        self._shown = np.ones(n_taxels, bool)
        self._young = False  #: activity-driven: the last block holds the taxels woken since the last regrouping
        self._member = np.ones(n_taxels, bool)  #: taxels in a running block (activity-driven compute)
        if self.detector is not None:
            if carried and continues.detector is not None:
                # a restart after shedding load: the scene did not change, so neither its learned noise nor its
                # contacts start again. Taxels kept running only by their recent spikes stop (these neurons
                # start from rest, and each restart's first spikes would keep them running through the next)
                self.detector = continues.detector
                self.detector.plan = activity  # resolved for this pipeline's parameters
                self._member = continues._member & self.detector.awake
            self.blocks = self._start_blocks(np.flatnonzero(self._member))  # at a start, every taxel until judged
        self._spiked_s = np.full(n_taxels, -np.inf)  #: per taxel: sensor time (s) of its latest spike
        self._regroup_at = -np.inf  #: sensor time (s) of the next regrouping of the awake taxels
        #: per taxel woken but not started yet: the newest sample time before it woke (-inf: before any), else inf
        self._woken_s = np.full(n_taxels, np.inf)
        self._newest_s = -np.inf  #: the newest raw sample time (s) seen by the detector
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
        if self.detector is not None:
            self._demand = {c: np.isin(np.arange(self.n_taxels), xs) for c, xs in want.items()}
            self._shown = np.isin(np.arange(self.n_taxels), sorted(shown))
            for block in self.blocks:
                block.set_active(*self._local_want(block.taxels), self._awake_sources())
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
        """Block ``i`` runs its demanded columns, and its channels source while channels are wanted from it."""
        self.blocks[i].set_active(*self._wants[i])

    # -- activity-driven compute ------------------------------------------------------------------
    #: the awake taxels are regrouped this often (s, sensor clock): the ones a contact woke since (run
    #: meanwhile as a second block) join the main block, and the ones that went quiet leave it
    REGROUP_S = 0.25

    #: taxels per block while every taxel runs (a stream's start, before the detector has judged them):
    #: one block of 65,536 taxels held ~3 GiB of temporaries per call, blocks of 4096 a sixteenth
    START_BLOCK = 4096

    def _start_blocks(self, taxels: np.ndarray) -> list[_TaxelBlock]:
        """``taxels`` from rest, in blocks of at most :attr:`START_BLOCK`."""
        return [_TaxelBlock(self.params, self.acq, taxels[a : a + self.START_BLOCK], self._groups, self.dtype, self.channels_source,
                            **dict(zip(("want", "shows"), self._local_want(taxels[a : a + self.START_BLOCK]))),
                            sources=self._awake_sources())
                for a in range(0, taxels.size, self.START_BLOCK)]

    def _local_want(self, taxels: np.ndarray) -> tuple[dict[str, list[int]], bool]:
        """The demand on a block of ``taxels``: per class its local columns, and whether it shows channels."""
        return {c: np.flatnonzero(w[taxels]).tolist() for c, w in self._demand.items()}, bool(self._shown[taxels].any())

    def _awake_sources(self) -> list[Source]:
        """The sources every awake block runs (blocks that merge must run the same): those of the
        demanded classes, and the channels source while channels are wanted."""
        sources = {self.source[c] for c, w in self._demand.items() if w.any()}
        if self._shown.any():
            sources.add(self.channels_source)
        return sorted(sources, key=lambda s: -1.0 if s is None else s)

    def _follow_activity(self, chunk: RawChunk) -> None:
        """Before the chunk is processed: the demanded taxels that left their band, or spiked within
        the plan's ``hold_s`` (their LIF has not settled), or whose channels are wanted, run.

        A taxel that wakes joins a second block, rebuilt from the raw history and reading from the
        main block's positions, so that its columns start (from rest) before the first sample that
        woke it: the chain delivers no sample before it has seen the
        :data:`~touchreal.preprocess.pipeline.MIN_LAG_S` after it, so
        the taxels that woke within the last two hops or so start together, in the last chunk before
        the main block's positions could pass their waking samples (fewer rebuilds for a moving
        contact, the same spikes). Every :attr:`REGROUP_S` that block and the main block's taxels
        still needed become one block, bit for bit (:meth:`_TaxelBlock.gather`), so compute follows
        the awake taxels, not blocks of them, at one block's fixed cost per call. (At the stream's
        start every taxel runs, in blocks of :attr:`START_BLOCK`, until the detector has judged them.)"""
        awake = self.detector.push(chunk)
        ends = [a[-1] for a in (chunk.st_t, chunk.pvdf_t) if a.size]
        if not ends:
            return
        now, before = float(max(ends)), self._newest_s
        self._newest_s = now
        awake |= self._spiked_s >= now - self.detector.plan.hold_s
        demanded = np.logical_or.reduce(list(self._demand.values())) if self._demand else np.zeros(self.n_taxels, bool)
        need = (awake & demanded) | self._shown
        woken = need & ~self._member
        self._woken_s[~woken] = np.inf  # a taxel that woke and went quiet again before it started does not start
        self._woken_s[woken & (self._woken_s == np.inf)] = before
        if woken.any() and (not self.blocks or now - MIN_LAG_S > self._woken_s[woken].min()):
            self._start_woken()
        if now >= self._regroup_at:
            self._regroup_at = now + self.REGROUP_S
            self._regroup(need)

    def _start_woken(self) -> None:
        """Run the taxels that woke since the last start."""
        woken = self._woken_s < np.inf
        self._woken_s[woken] = np.inf
        self._wake(np.flatnonzero(woken))

    def _wake(self, taxels: np.ndarray) -> None:
        """Run ``taxels`` from now on, in the second block."""
        main = self.blocks[0] if self.blocks else None
        want, shows = self._local_want(taxels)
        block = _TaxelBlock(self.params, self.acq, taxels, self._groups, self.dtype, self.channels_source,
                            start=None if main is None else dict(main.pre.cursor), want=want, shows=shows,
                            sources=self._awake_sources())
        self._member[taxels] = True
        if main is None:
            self.blocks = [block]
            return
        if self._young:
            young = self.blocks.pop()
            ids = np.concatenate((young.taxels, taxels))
            block = _TaxelBlock.gather([(young, np.arange(len(young.taxels))), (block, np.arange(len(taxels)))],
                                       *self._local_want(ids))
        self.blocks.append(block)
        self._young = True

    def _regroup(self, need: np.ndarray) -> None:
        """One block of the running taxels still ``need`` ed (none when no taxel is)."""
        parts = [(b, np.flatnonzero(need[b.taxels])) for b in self.blocks]
        if not self._young and all(idx.size == len(b.taxels) for b, idx in parts):
            return  # nothing leaves, nothing joins
        parts = [(b, idx) for b, idx in parts if idx.size]
        self._member[:] = False
        self._young = False
        if not parts:
            self.blocks = []
            return
        ids = np.concatenate([b.taxels[idx] for b, idx in parts])
        self.blocks = [_TaxelBlock.gather(parts, *self._local_want(ids))]
        self._member[ids] = True

    def observe(self, chunk: RawChunk) -> None:
        """A chunk that is not processed (a shed drops its compute): the activity detector still learns
        from it, so a pipeline that restarts after a shed runs the taxels a contact holds awake, not every
        taxel of a detector that saw too little to judge them."""
        if self.detector is not None:
            self.detector.push(chunk)

    @property
    def awake_taxels(self) -> int:
        """Taxels the encoder runs: those a contact woke, and those whose channels are wanted (all of
        them when dense)."""
        return int(sum(len(b.taxels) for b in self.blocks)) if self.detector is not None else self.n_taxels

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
        """End of stream: flush every running branch and return the last spikes (of every source; a taxel
        that woke in the last two hops or so has not started and stays silent)."""
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
        if len(blocks) == 1 or self.detector is not None:  # the awake set's two blocks are unequal: each splits its own kernels
            for block in blocks:
                block.pre.consume(*new)
            return

        def consume(a: int, b: int) -> None:
            for block in blocks[a:b]:
                block.pre.consume(*new)

        split_run(consume, len(blocks), self._work, _BLOCK_MIN_WORK)

    def _encode(self, final: bool = False, phase: str | None = None) -> tuple[Channels, SpikeEvents]:
        slow, phase = (frozenset(), None) if final else (self.slow, phase)
        running = [b for b in self.blocks if b.pre.sources]
        if len(running) == 1 or self.detector is not None:
            results = [block.encode(slow, phase) for block in running]
        else:
            results = [(None, [])] * len(running)

            def encode(a: int, b: int) -> None:
                for i in range(a, b):
                    results[i] = running[i].encode(slow, phase)

            split_run(encode, len(running), self._work, _BLOCK_MIN_WORK)
        shown, parts = [], []
        for block, (ch, evs) in zip(running, results):
            if ch is not None:
                shown.append((block.taxels, ch))
            parts += evs
        events = SpikeEvents.concatenate(parts)
        if self.detector is not None and events.t_s.size:
            np.maximum.at(self._spiked_s, events.taxel, events.t_s)
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
        if len(shown) == 1 and isinstance(shown[0][0], range) and len(shown[0][0]) == self.n_taxels:
            return shown[0][1]
        spans = [(ch.k0, ch.k0 + ch.n_samples) for _, ch in shown if ch.n_samples]
        if not spans:
            return Channels(0, np.zeros((0, self.n_taxels, 4), self.dtype))
        k0, k1 = min(a for a, _ in spans), max(b for _, b in spans)
        data = np.full((k1 - k0, self.n_taxels, 4), np.nan, dtype=shown[0][1].data.dtype)
        for taxels, ch in shown:
            data[ch.k0 - k0 : ch.k0 - k0 + ch.n_samples, slice(taxels.start, taxels.stop) if isinstance(taxels, range) else taxels] = ch.data
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
