"""The preprocessing pipeline: raw SingleTact (N, 100 Hz) + PVDF (V, 2 kHz) -> 4 channels at 5 kHz.

::

    SingleTact -> sanitize -> Butterworth low-pass -> alpha-beta -> PCHIP -> (ST [N], dST [N/s])      --+
                                                                                                          +-> source
    PVDF -> sanitize -> low-pass + mains notches -+-> STFT gate (window w1) -> PCHIP -> (PVDF, dPVDF) --+   (4 ch, 5 kHz)
                                                  +-> STFT gate (window w2) -> ...

A *source* is what one group of encoder columns reads: the SingleTact channels with the PVDF
channels of one causal window (``window_ms``), or the SingleTact channels alone (``None``: PVDF and
dPVDF are zero, for classes whose PVDF and dPVDF weights are all zero). Each distinct window is
computed once and shared; each source has its own read cursor, so a short window (or the
SingleTact alone) is not held back by a long one.

:class:`Preprocessor` is a sans-I/O state machine: ``feed(...)`` takes whatever raw samples arrived
(any chunk size, any number of taxels), ``take(source)`` returns that source's newly final 5 kHz
samples, aligned on the absolute grid ``k / 5000`` s of the recording clock; ``flush()`` ends the
stream. Only the branches the active sources need run (``set_sources``); acquisition (sanitizers
and a short raw history) always runs, and a branch that (re)starts is rebuilt from that history
(see :meth:`Preprocessor.set_sources`). Offline processing of a whole recording is the same calls
(:func:`preprocess_trial`, :func:`preprocess_trial_windows`). The branches are in :mod:`.branches`.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..params import PreprocessParams
from ..recording import Trial
from ..settings import OUT_FS_HZ, PVDF_FS_HZ, PVDF_RANGE_V, ST_FS_HZ, ST_RANGE_N
from .branches import History, PvdfFilter, PvdfWindowBranch, SingleTactBranch
from .filters import HUM_PRIME_S
from .mains import MainsResolver
from .resample import first_grid_index
from .sanitize import Sanitizer
from .stft_gate import frame_length

Source = float | None  #: a consumer of the preprocessing: its PVDF window (ms), or None = SingleTact only

ST_HISTORY_S = 0.5  #: raw SingleTact history kept for a restart of its branch (s; > 5x the alpha-beta settling)
ST_LOOKAHEAD_KNOTS = 2  #: PCHIP needs the knot after the next one: up to 2 knot intervals of look-ahead
#: the least any source's read position lags the newest raw sample (s): the SingleTact PCHIP emits nothing
#: past its second-newest knot (one knot interval); the PVDF windows' gates lag more
MIN_LAG_S = 1.0 / ST_FS_HZ


@dataclass
class Channels:
    """A block of encoder input: sample k of ``data`` is at ``t0_s + k / fs_hz`` (s).

    ``data`` is (T, n_taxels, 4), float64 or float32 (the preprocessor's dtype), with channels
    ST [N], dST [N/s], PVDF [V], dPVDF [V/s].
    """

    k0: int  # absolute 5 kHz grid index of the first sample
    data: np.ndarray
    fs_hz: float = OUT_FS_HZ

    @property
    def t0_s(self) -> float:
        return self.k0 / self.fs_hz

    @property
    def n_samples(self) -> int:
        return self.data.shape[0]

    @property
    def t_s(self) -> np.ndarray:
        return (self.k0 + np.arange(self.n_samples)) / self.fs_hz

    @staticmethod
    def concatenate(blocks: list["Channels"], n_taxels: int) -> "Channels":
        blocks = [b for b in blocks if b.n_samples]
        if not blocks:
            return Channels(0, np.zeros((0, n_taxels, 4)))
        for a, b in zip(blocks, blocks[1:]):
            if b.k0 != a.k0 + a.n_samples:
                raise ValueError("channel blocks are not contiguous")
        return Channels(blocks[0].k0, np.concatenate([b.data for b in blocks], axis=0))


def _valid_taxels(taxels: range | np.ndarray | None, n_taxels: int) -> bool:
    """A contiguous block (range, step 1) or an array of distinct ids of ``n_taxels`` taxels."""
    if isinstance(taxels, range):
        return taxels.step == 1 and 0 <= taxels.start < taxels.stop <= n_taxels
    if taxels is None:
        return False
    ids = np.asarray(taxels)
    return (ids.ndim == 1 and ids.dtype.kind in "iu" and (not ids.size or (ids.min() >= 0 and ids.max() < n_taxels))
            and np.unique(ids).size == ids.size)


def check_raw(st_t, st, pvdf_t, pvdf, n_taxels: int) -> None:
    """Raise ValueError unless each sensor's values are (n, n_taxels) (or (n,) for one taxel) for
    its n timestamps."""
    for name, t, x in (("SingleTact", st_t, st), ("PVDF", pvdf_t, pvdf)):
        if t is not None and len(t):
            shape = np.shape(x)
            if shape not in ((len(t), n_taxels),) + (((len(t),),) if n_taxels == 1 else ()):
                raise ValueError(f"{name}: expected values of shape ({len(t)}, {n_taxels}), got {shape}")


class Acquisition:
    """What always runs, for all N taxels: the sanitizers of both sensors (input policy, counters)
    and the raw history rings that a (re)starting branch is rebuilt from (the last
    :data:`ST_HISTORY_S` of SingleTact; the hum estimate plus two frames of ``max_window_ms`` of PVDF),
    and the stream's mains frequency, resolved from its first PVDF samples (:attr:`mains`, for
    ``params``) unless ``mains_hz`` gives it. Several :class:`Preprocessor` s (taxel blocks) can share one."""

    def __init__(self, n_taxels: int = 1, max_window_ms: float = 128.0, params: PreprocessParams | None = None,
                 mains_hz: float | None = None):
        self.n_taxels = n_taxels
        self.mains = MainsResolver(params or PreprocessParams(), PVDF_FS_HZ, mains_hz)
        self.st_in = Sanitizer(ST_FS_HZ, ST_RANGE_N, n_taxels)
        self.pv_in = Sanitizer(PVDF_FS_HZ, PVDF_RANGE_V, n_taxels)
        self.n_pv = int(round(HUM_PRIME_S * PVDF_FS_HZ)) + 2 * frame_length(max_window_ms, PVDF_FS_HZ) + 16
        self.st_hist = History(int(round(ST_HISTORY_S * ST_FS_HZ)), n_taxels)
        self.pv_hist = History(self.n_pv, n_taxels)

    def push(self, st_t=None, st=None, pvdf_t=None, pvdf=None) -> tuple[tuple[int, np.ndarray] | None, ...]:
        """Sanitize raw samples (both parts checked before either is used, so a malformed chunk
        raises ValueError and changes nothing); return (first slot, (n, N) samples) or None per sensor."""
        check_raw(st_t, st, pvdf_t, pvdf, self.n_taxels)
        out: list[tuple[int, np.ndarray] | None] = [None, None]
        for j, (san, hist, t, x) in enumerate(((self.st_in, self.st_hist, st_t, st), (self.pv_in, self.pv_hist, pvdf_t, pvdf))):
            if t is not None and len(t):
                first, clean = san.push(t, x)
                hist.push(first, clean)
                out[j] = (first, clean)
        if out[1] is not None:
            self.mains.push(out[1][1])
        return tuple(out)

    def restart_index(self) -> int | None:
        """First grid index after the newest raw sample of either sensor (None before any data)."""
        newest = [float(s.slot_time(s.next_slot - 1)) for s in (self.st_in, self.pv_in) if s.t0 is not None]
        return first_grid_index(max(newest), OUT_FS_HZ) if newest else None

    def first_index(self) -> int | None:
        """First grid index both sensors cover (the stream start of every source), once known."""
        if self.st_in.t0 is None or self.pv_in.t0 is None:
            return None
        return max(first_grid_index(float(s.slot_time(1)), OUT_FS_HZ) for s in (self.st_in, self.pv_in))

    def until_s(self) -> float | None:
        """Time of the last sample both sensors delivered (s; None before both started)."""
        if self.st_in.t0 is None or self.pv_in.t0 is None:
            return None
        return min(float(s.slot_time(s.next_slot - 1)) for s in (self.st_in, self.pv_in))

    @property
    def stats(self) -> dict[str, dict[str, int]]:
        return {"singletact": self.st_in.stats.as_dict(), "pvdf": self.pv_in.stats.as_dict()}

    def state_arrays(self) -> dict[str, np.ndarray]:
        return {"st_last": self.st_in.last, "pv_last": self.pv_in.last, "st_hist": self.st_hist.buf, "pv_hist": self.pv_hist.buf}


class Preprocessor:
    """Causal, chunk-wise, stateful preprocessing of N taxels for a set of sources (module docstring).

    ``sources`` are the initially active sources (default: ``params.window_ms``); ``max_window_ms``
    sizes the raw history kept for restarts (default: the longest window of ``sources``). With a
    shared ``acquisition``, the preprocessor serves its ``taxels`` (a contiguous block of the
    acquisition's taxels, or any array of them) and is fed by :meth:`consume` after the owner's
    :meth:`Acquisition.push`; ``start`` (per source, a grid index) delivers a source from there
    instead of the restart index, as far as the raw history reaches (see :meth:`set_sources`).
    """

    def __init__(
        self,
        params: PreprocessParams | None = None,
        n_taxels: int = 1,
        dtype: type = np.float64,
        sources: Iterable[Source] | None = None,
        max_window_ms: float | None = None,
        acquisition: Acquisition | None = None,
        taxels: range | np.ndarray | None = None,
        start: dict[Source, int | None] | None = None,
    ):
        self.params = params = params or PreprocessParams()
        self.dtype = np.dtype(dtype)  # arithmetic of the filters, the STFT gate and PCHIP; dtype of the channels
        sources = [params.window_ms] if sources is None else list(sources)
        if max_window_ms is None:
            max_window_ms = max((s for s in sources if s is not None), default=params.window_ms)
        self._owns_acquisition = acquisition is None
        if acquisition is None:
            acquisition, taxels = Acquisition(n_taxels, max_window_ms, params), range(n_taxels)
        elif not _valid_taxels(taxels, acquisition.n_taxels):
            raise ValueError("a preprocessor on a shared acquisition needs a contiguous block or an array of its taxels")
        self.acq = acquisition
        self.taxels = taxels
        self.n_taxels = len(taxels)
        self._cols = slice(taxels.start, taxels.stop) if isinstance(taxels, range) else np.asarray(taxels, np.int64)
        self.pv_filtered = History(acquisition.n_pv, self.n_taxels, self.dtype)  # the running PVDF filter's output (window restarts)
        self.st: SingleTactBranch | None = None
        self.pv_filter: PvdfFilter | None = None
        self.pv_windows: dict[float, PvdfWindowBranch] = {}
        self.cursor: dict[Source, int | None] = {}  # per active source: next grid index to deliver
        self.set_sources(sources, start)

    # -- demand ---------------------------------------------------------------------------------
    @property
    def sources(self) -> tuple[Source, ...]:
        return tuple(self.cursor)

    def set_sources(self, sources: Iterable[Source], start: dict[Source, int | None] | None = None) -> None:
        """Make ``sources`` the active ones: branches no active source needs stop (their state is
        dropped); a branch that (re)starts is rebuilt from the raw history the acquisition keeps
        (SingleTact: the last :data:`ST_HISTORY_S`; PVDF: the hum estimate plus two frames of the
        longest window): a restarted PVDF filter is primed on the hum of that history's first
        100 ms as at stream start, and a restarted window's gate replays the filtered history, so
        its output from one frame after the history start on is the one of a branch that never
        stopped (exactly so when the PVDF filter kept running). A source that (re)starts delivers
        from the first grid index after the newest raw sample received
        (:meth:`Acquisition.restart_index`), or from the stream start before any data; or from
        ``start[source]`` when given (a source that joins another's taxels at their read position)."""
        sources = list(dict.fromkeys(float(s) if s is not None else None for s in sources))
        acq, cols = self.acq, self._cols
        k_r = acq.restart_index()
        start = start or {}
        self.cursor = {s: self.cursor[s] if s in self.cursor else start.get(s, k_r) for s in sources}
        windows = {s for s in sources if s is not None}
        if not sources:
            self.st = None
        elif self.st is None:
            self.st = SingleTactBranch(self.params, self.n_taxels, self.dtype, acq.st_in.slot_time)
            first = acq.st_hist.first
            if first is not None:
                self.st.process(*acq.st_hist.since(first, cols))
        if not windows:
            self.pv_filter = None
            self.pv_filtered.clear()
        elif self.pv_filter is None:
            first = acq.pv_hist.first
            self.pv_filter = PvdfFilter(self.params, self.n_taxels, self.dtype, acq.pv_in.next_slot if first is None else first,
                                        acq.mains)
            self.pv_filtered.clear()
            if first is not None:
                self.pv_filtered.push(*self.pv_filter.process(acq.pv_hist.since(first, cols)[1]))
        self.pv_windows = {w: b for w, b in self.pv_windows.items() if w in windows}
        for w in windows - set(self.pv_windows):
            first = self.pv_filtered.first
            start = self.pv_filter.slot if first is None else first
            branch = PvdfWindowBranch(self.params, w, self.n_taxels, self.dtype, acq.pv_in.slot_time, start)
            if first is not None:
                branch.process(*self.pv_filtered.since(first))
            self.pv_windows[w] = branch
        self._trim()

    def restart_index(self) -> int | None:
        """First grid index after the newest raw sample of either sensor (None before any data)."""
        return self.acq.restart_index()

    @staticmethod
    def gather(parts: "list[tuple[Preprocessor, np.ndarray]]") -> "Preprocessor":
        """One preprocessor over the local taxels ``idx`` of each part, in order (parts on one
        acquisition, with the same sources at the same read positions): every branch's state is
        copied bit for bit, so the result continues exactly as the parts would have. Window
        branches first read all the filtered PVDF they hold (a gate run earlier than its take, with
        the same output)."""
        first = parts[0][0]
        if any(p.acq is not first.acq or p.cursor != first.cursor or p.dtype != first.dtype for p, _ in parts):
            raise ValueError("preprocessors gathered into one must share the acquisition, sources and read positions")
        for p, _ in parts:
            for branch in p.pv_windows.values():
                p._catch_up(branch)
        out = copy.copy(first)
        out.taxels = out._cols = np.concatenate([np.asarray(p.taxels, np.int64)[idx] for p, idx in parts])
        out.n_taxels = out.taxels.size
        out.cursor = dict(first.cursor)
        if first.st is not None:
            out.st = SingleTactBranch.gather([(p.st, idx) for p, idx in parts])
        if first.pv_filter is not None:
            out.pv_filter = PvdfFilter.gather([(p.pv_filter, idx) for p, idx in parts])
        out.pv_filtered = History.gather([(p.pv_filtered, idx) for p, idx in parts])
        out.pv_windows = {w: PvdfWindowBranch.gather([(p.pv_windows[w], idx) for p, idx in parts]) for w in first.pv_windows}
        return out

    # -- data -----------------------------------------------------------------------------------
    def feed(self, st_t=None, st=None, pvdf_t=None, pvdf=None) -> None:
        """Feed raw samples (either sensor may be absent in a call). Both parts are checked before
        either is used, so a malformed chunk raises ValueError and changes nothing."""
        if not self._owns_acquisition:
            raise RuntimeError("a preprocessor on a shared acquisition is fed by consume()")
        self.consume(*self.acq.push(st_t, st, pvdf_t, pvdf))

    def consume(self, st_new: tuple[int, np.ndarray] | None, pv_new: tuple[int, np.ndarray] | None) -> None:
        """Run the branches on newly sanitized samples (:meth:`Acquisition.push`'s result)."""
        if st_new is not None and self.st is not None:
            self.st.process(st_new[0], st_new[1][:, self._cols])
        if pv_new is not None and self.pv_filter is not None:
            self._pv_windows(*self.pv_filter.process(pv_new[1][:, self._cols]))

    def _pv_windows(self, first: int, y: np.ndarray) -> None:
        """Keep filtered PVDF for the window branches, which read it when their source is taken
        (:meth:`take`); a branch whose unread samples the ring would overwrite reads them now."""
        lost_before = first + y.shape[0] - self.pv_filtered.buf.shape[0]
        for branch in self.pv_windows.values():
            if branch.in_slot < lost_before:
                self._catch_up(branch)
                branch.process(first, y)
        self.pv_filtered.push(first, y)

    def _catch_up(self, branch: PvdfWindowBranch) -> None:
        """Run a window branch on the filtered PVDF it has not read yet."""
        if self.pv_filtered.count and branch.in_slot < self.pv_filtered.end:
            branch.process(*self.pv_filtered.since(branch.in_slot))

    def flush(self) -> None:
        """End of stream: finish every running branch up to the last sample both sensors delivered."""
        until = self.acq.until_s()
        if until is None:
            return
        if self.pv_filter is not None:
            self._pv_windows(*self.pv_filter.process(np.zeros((0, self.n_taxels), self.dtype), final=True))
        for branch in self.pv_windows.values():
            self._catch_up(branch)
            branch.finish(until)
        if self.st is not None:
            self.st.finish(until)

    def frame_ready(self, source: Source) -> bool:
        """Whether a window source's gate has a new frame to run on the filtered PVDF received (a
        source taken only then costs one gate call per frame and waits for nothing); True for the
        SingleTact alone."""
        if source is None:
            return True
        branch = self.pv_windows[float(source)]
        unread = self.pv_filtered.end - branch.in_slot if self.pv_filtered.count else 0
        return unread >= branch.gate.to_next_frame

    def take(self, source: Source) -> Channels:
        """The newly final 5 kHz channels of an active ``source`` (PVDF and dPVDF zero for None).
        A window's gate runs here, on the filtered PVDF received since its last take: a source
        taken less often (a long window, on the update interval) costs one gate call per take."""
        source = float(source) if source is not None else None
        if source not in self.cursor:
            raise KeyError(f"source {source} is not active")
        k_first = self.acq.first_index()
        if k_first is None or self.st is None:
            return Channels(self.cursor[source] or 0, np.zeros((0, self.n_taxels, 4), self.dtype))
        start = max(k_first, self.cursor[source] if self.cursor[source] is not None else k_first)
        if source is not None:
            self._catch_up(self.pv_windows[source])
        grids = [self.st.out] if source is None else [self.st.out, self.pv_windows[source].out]
        ends = [g.end for g in grids]
        end = None if None in ends else min(ends)
        start = max([start] + [g.k0 for g in grids if g.k0 is not None])
        if end is None or end <= start:
            self.cursor[source] = start
            return Channels(start, np.zeros((0, self.n_taxels, 4), self.dtype))
        pv = np.zeros((end - start, self.n_taxels, 2), self.dtype) if source is None else grids[1].read(start, end)
        out = Channels(start, np.concatenate((grids[0].read(start, end), pv), axis=2))
        self.cursor[source] = end
        self._trim()
        return out

    def _trim(self) -> None:
        """Drop branch output every active source has read."""
        cursors = [k for k in self.cursor.values() if k is not None]
        if self.st is not None and cursors and len(cursors) == len(self.cursor):
            self.st.out.drop_before(min(cursors))
        for w, branch in self.pv_windows.items():
            if self.cursor.get(w) is not None:
                branch.out.drop_before(self.cursor[w])

    # -- single-source use (one window, as before) ----------------------------------------------
    def process(self, st_t=None, st=None, pvdf_t=None, pvdf=None) -> Channels:
        """Feed raw samples and return the newly final channels of the single active source."""
        self.feed(st_t, st, pvdf_t, pvdf)
        return self.take(self._only_source())

    def finish(self) -> Channels:
        """End of stream for the single active source: flush and return its last channels."""
        self.flush()
        return self.take(self._only_source())

    def _only_source(self) -> Source:
        if len(self.cursor) != 1:
            raise ValueError(f"process()/finish() need exactly one active source, have {list(self.cursor)}")
        return next(iter(self.cursor))

    # -- reporting ------------------------------------------------------------------------------
    @staticmethod
    def latency_s(source: Source) -> float:
        """Algorithmic latency (s) of a source: the longest look-ahead of the branches it reads, i.e.
        the time from a grid point to the arrival of the last raw sample it needs. The branches run
        side by side, so a source waits for the slower one, not for their sum. SingleTact: PCHIP
        needs up to :data:`ST_LOOKAHEAD_KNOTS` knot intervals (20 ms); a window of N PVDF samples:
        the gate finalises a sample once the last frame covering it is complete (up to N - 1
        samples later) and PCHIP needs up to 2 more samples: (N + 1) / 2 kHz."""
        st = ST_LOOKAHEAD_KNOTS / ST_FS_HZ
        if source is None:
            return st
        return max(st, (frame_length(float(source), PVDF_FS_HZ) + 1) / PVDF_FS_HZ)

    @property
    def stats(self) -> dict[str, dict[str, int]]:
        """Input-policy counters of the acquisition (all its taxels)."""
        return self.acq.stats

    @property
    def running(self) -> dict[str, bool | tuple[float, ...]]:
        """Which branches run: SingleTact, the PVDF filter, the PVDF windows (ms)."""
        return {"singletact": self.st is not None, "pvdf_filter": self.pv_filter is not None, "pvdf_windows": tuple(sorted(self.pv_windows))}

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Every numeric state variable of the running stages and buffers (stability checks, monitoring;
        the acquisition's too when this preprocessor owns it)."""
        out = self.acq.state_arrays() if self._owns_acquisition else {}
        if self.st is not None:
            out.update(self.st.state_arrays())
            out.update({f"st_out_{i}": a for i, a in enumerate(self.st.out.arrays())})
        if self.pv_filter is not None:
            out.update(self.pv_filter.state_arrays())
            out["pv_filtered"] = self.pv_filtered.buf
        for w, branch in self.pv_windows.items():
            name = f"pv{w:g}ms"
            out.update(branch.state_arrays(name))
            out.update({f"{name}_out_{i}": a for i, a in enumerate(branch.out.arrays())})
        return out


def preprocess_trial(trial: Trial, params: PreprocessParams | None = None) -> Channels:
    """Whole-recording preprocessing of one taxel at ``params.window_ms``: the online pipeline fed everything at once."""
    pre = Preprocessor(params, n_taxels=1)
    head = pre.process(trial.st_t, trial.st, trial.pvdf_t, trial.pvdf)
    tail = pre.finish()
    return Channels.concatenate([head, tail], 1)


def preprocess_trial_windows(trial: Trial, params: PreprocessParams, sources: Iterable[Source]) -> dict[Source, Channels]:
    """Whole-recording preprocessing of one taxel for several sources at once (each window once;
    each result equals :func:`preprocess_trial` at that window)."""
    sources = list(dict.fromkeys(float(s) if s is not None else None for s in sources))
    pre = Preprocessor(params, n_taxels=1, sources=sources)
    pre.feed(trial.st_t, trial.st, trial.pvdf_t, trial.pvdf)
    heads = {s: pre.take(s) for s in sources}
    pre.flush()
    return {s: Channels.concatenate([heads[s], pre.take(s)], 1) for s in sources}
