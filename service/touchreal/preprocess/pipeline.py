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
(:func:`preprocess_trial`, :func:`preprocess_trial_windows`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from ..params import PreprocessParams
from ..recording import Trial
from ..settings import OUT_FS_HZ, PVDF_FS_HZ, PVDF_RANGE_V, ST_FS_HZ, ST_RANGE_N
from .filters import HUM_PRIME_S, AlphaBeta, butter_lowpass, mains_frequencies, prime_with_hum
from .gate import gate_thresholds, pvdf_filter
from .resample import CausalPchip, first_grid_index
from .sanitize import Sanitizer
from .stft_gate import StftGate, frame_length

_ST_LP_ORDER = 2

Source = float | None  #: a consumer of the preprocessing: its PVDF window (ms), or None = SingleTact only

ST_HISTORY_S = 0.5  #: raw SingleTact history kept for a restart of its branch (s; > 5x the alpha-beta settling)
ST_LOOKAHEAD_KNOTS = 2  #: PCHIP needs the knot after the next one: up to 2 knot intervals of look-ahead


@dataclass
class Channels:
    """A block of encoder input: sample k of ``data`` is at ``t0_s + k / fs_hz`` (s).

    ``data`` is (T, n_taxels, 4) float64 with channels ST [N], dST [N/s], PVDF [V], dPVDF [V/s].
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



class _History:
    """The last ``size`` samples of a regular grid (n, n_taxels), by grid slot (a ring buffer)."""

    def __init__(self, size: int, n_taxels: int):
        self.buf = np.zeros((size, n_taxels))
        self.end = 0  # slot after the newest sample
        self.count = 0

    def push(self, slot: int, x: np.ndarray) -> None:
        """Append samples of slots ``slot ...`` (contiguous with the newest, unless empty)."""
        if x.shape[0] == 0:
            return
        if self.count and slot != self.end:
            raise ValueError(f"history is contiguous: expected slot {self.end}, got {slot}")
        size = self.buf.shape[0]
        end = slot + x.shape[0]
        x = x[-size:]
        self.buf[np.arange(end - x.shape[0], end) % size] = x
        self.count = min(self.count + x.shape[0], size)
        self.end = end

    def since(self, slot: int) -> tuple[int, np.ndarray]:
        """(first slot, samples) from ``slot`` (or the oldest kept) to the newest."""
        first = max(slot, self.end - self.count)
        return first, self.buf[np.arange(first, self.end) % self.buf.shape[0]]

    @property
    def first(self) -> int | None:
        return self.end - self.count if self.count else None

    def clear(self) -> None:
        self.count = 0


class _Grid:
    """A branch's 5 kHz output (T, n_taxels, 2) not yet read by every source, as a list of blocks."""

    def __init__(self, n_taxels: int):
        self.n_taxels = n_taxels
        self.blocks: list[tuple[int, np.ndarray]] = []
        self.start: int | None = None  # first grid index ever emitted
        self.end: int | None = None  # grid index after the newest emitted sample

    def add(self, emitted: tuple[int, np.ndarray]) -> None:
        k0, v = emitted
        if v.shape[0] == 0:
            return
        self.blocks.append((k0, v.reshape(v.shape[0], 2, self.n_taxels).transpose(0, 2, 1)))
        self.start = k0 if self.start is None else self.start
        self.end = k0 + v.shape[0]

    @property
    def k0(self) -> int | None:
        return self.blocks[0][0] if self.blocks else self.end

    def read(self, a: int, b: int) -> np.ndarray:
        """Samples a ... b - 1 (all held)."""
        parts = [blk[max(a - k, 0) : b - k] for k, blk in self.blocks if k < b and k + blk.shape[0] > a]
        return np.concatenate(parts, axis=0) if len(parts) != 1 else parts[0]

    def drop_before(self, k: int) -> None:
        keep = []
        for k0, blk in self.blocks:
            if k0 + blk.shape[0] <= k:
                continue
            keep.append((k, blk[k - k0 :]) if k0 < k else (k0, blk))
        self.blocks = keep

    def arrays(self) -> list[np.ndarray]:
        return [blk for _, blk in self.blocks]


class _SingleTactBranch:
    """SingleTact: Butterworth low-pass -> alpha-beta -> PCHIP onto the 5 kHz grid (ST [N], dST [N/s])."""

    def __init__(self, params: PreprocessParams, n_taxels: int, dtype: np.dtype, slot_time: Callable):
        self.lp = butter_lowpass(params.st_lowpass_hz, ST_FS_HZ, _ST_LP_ORDER, n_taxels, dtype)
        self.ab = AlphaBeta(params.st_alpha, params.st_beta, ST_FS_HZ, n_taxels)
        self.rs = CausalPchip(OUT_FS_HZ, 2 * n_taxels)
        self.slot_time = slot_time
        self.out = _Grid(n_taxels)

    def process(self, first: int, x: np.ndarray) -> None:
        if x.shape[0] == 0:
            return
        force, rate = self.ab.process(self.lp.process(x))
        t = self.slot_time(np.arange(first, first + x.shape[0]))
        self.out.add(self.rs.process(t, np.concatenate((force, rate), axis=1)))

    def finish(self, until_s: float) -> None:
        self.out.add(self.rs.finish(until_s))

    def state_arrays(self) -> dict[str, np.ndarray]:
        out = {"st_ab_v": self.ab.v, "st_rs": self.rs._y}
        if self.lp.zi is not None:
            out["st_lp"] = self.lp.zi
        if self.ab.x is not None:
            out["st_ab_x"] = self.ab.x
        return out


class _PvdfFilter:
    """PVDF low-pass + mains notches (one cascade), started at grid slot ``slot``: its first
    :data:`HUM_PRIME_S` are held and the filter is primed with the hum fitted to them (no notch
    ringing at the start), then everything flows through."""

    def __init__(self, params: PreprocessParams, n_taxels: int, dtype: np.dtype, slot: int):
        self.filt = pvdf_filter(params, PVDF_FS_HZ, n_taxels, dtype)
        self.hum_hz = mains_frequencies(params.mains_hz, params.notch_harmonics, PVDF_FS_HZ)
        self.held: list[np.ndarray] | None = []
        self.slot = slot  # slot of the next output sample
        self.n_taxels = n_taxels

    def process(self, x: np.ndarray, final: bool = False) -> tuple[int, np.ndarray]:
        """Filter ``x`` (the samples from the next slot on); returns (first slot, filtered samples)."""
        if self.held is not None:
            self.held.append(x)
            n_prime = int(round(HUM_PRIME_S * PVDF_FS_HZ))
            held = np.concatenate(self.held)
            if held.shape[0] < n_prime and not final:
                return self.slot, held[:0]
            self.held = None
            if held.shape[0] == 0:
                return self.slot, held
            prime_with_hum(self.filt, held[:n_prime], PVDF_FS_HZ, self.hum_hz)
            x = held
        first = self.slot
        self.slot += x.shape[0]
        return first, self.filt.process(x)

    def state_arrays(self) -> dict[str, np.ndarray]:
        out = {} if self.filt.zi is None else {"pv_filter": self.filt.zi}
        if self.held:
            out["pv_held"] = np.concatenate(self.held)
        return out


class _PvdfWindowBranch:
    """One causal window: STFT gate (OLA) -> (PVDF [V], dPVDF = backward difference [V/s]) -> PCHIP.

    Frames lie on the absolute slot grid (a frame starts at every multiple of the hop), so a branch
    started at any slot gives, once its first frame is full of real samples, exactly the output of a
    branch that ran all along on the same filtered input."""

    def __init__(self, params: PreprocessParams, window_ms: float, n_taxels: int, dtype: np.dtype, slot_time: Callable, slot: int):
        n = frame_length(window_ms, PVDF_FS_HZ)
        gate = StftGate(n, n_taxels, dtype=dtype)
        if params.gate is not None:
            thresholds = gate_thresholds(params.gate, gate.window.astype(np.float64), PVDF_FS_HZ)
            gate = StftGate(n, n_taxels, thresholds, params.gate.attenuation, dtype=dtype)
        self.gate = gate
        self.n_taxels = n_taxels
        self.in_slot = -(-slot // gate.hop) * gate.hop  # first input slot: the next frame boundary
        self.out_slot = self.in_slot  # slot of the next gate output sample
        self.prev: np.ndarray | None = None  # last gate output (for the derivative)
        self.rs = CausalPchip(OUT_FS_HZ, 2 * n_taxels)
        self.slot_time = slot_time
        self.out = _Grid(n_taxels)

    def process(self, first: int, y: np.ndarray) -> None:
        """Filtered PVDF samples from slot ``first`` on (contiguous with the previous call)."""
        skip = self.in_slot - first
        if skip < 0:
            raise ValueError(f"PVDF branch expected slot {self.in_slot}, got {first}")
        y = y[skip:]
        self.in_slot += y.shape[0]
        self._emit(self.gate.process(y))

    def finish(self, until_s: float) -> None:
        self._emit(self.gate.process(np.zeros((self.gate.n, self.n_taxels))))
        self.out.add(self.rs.finish(until_s))

    def _emit(self, y: np.ndarray) -> None:
        if y.shape[0] == 0:
            return
        prev = y[:1] if self.prev is None else self.prev[None, :]
        dy = np.diff(np.concatenate((prev, y), axis=0), axis=0) * PVDF_FS_HZ
        self.prev = y[-1].copy()
        slots = np.arange(self.out_slot, self.out_slot + y.shape[0])
        self.out_slot += y.shape[0]
        self.out.add(self.rs.process(self.slot_time(slots), np.concatenate((y, dy), axis=1)))

    @property
    def latency_s(self) -> float:
        """Worst case: the gate finalises slot n once slot n + N - 1 arrived (n on a frame boundary),
        and PCHIP needs the knot after the next one (2 slots)."""
        return (self.gate.n - 1 + 2) / PVDF_FS_HZ

    def state_arrays(self, name: str) -> dict[str, np.ndarray]:
        out = {f"{name}_gate_buf": self.gate._buf, f"{name}_gate_acc": self.gate._acc, f"{name}_rs": self.rs._y}
        if self.prev is not None:
            out[f"{name}_prev"] = self.prev
        return out


class Preprocessor:
    """Causal, chunk-wise, stateful preprocessing of N taxels for a set of sources (module docstring).

    ``sources`` are the initially active sources (default: ``params.window_ms``); ``max_window_ms``
    sizes the raw history kept for restarts (default: the longest window of ``sources``).
    """

    def __init__(
        self,
        params: PreprocessParams | None = None,
        n_taxels: int = 1,
        dtype: type = np.float64,
        sources: Iterable[Source] | None = None,
        max_window_ms: float | None = None,
    ):
        self.params = params = params or PreprocessParams()
        self.n_taxels = n_taxels
        self.dtype = np.dtype(dtype)  # arithmetic of the filters and the STFT gate
        sources = [params.window_ms] if sources is None else list(sources)
        windows = [s for s in sources if s is not None]
        if max_window_ms is None:
            max_window_ms = max(windows, default=params.window_ms)
        self.st_in = Sanitizer(ST_FS_HZ, ST_RANGE_N, n_taxels)
        self.pv_in = Sanitizer(PVDF_FS_HZ, PVDF_RANGE_V, n_taxels)
        # acquisition keeps this much raw history for branch restarts (hum estimate + two frames + margin)
        n_pv = int(round(HUM_PRIME_S * PVDF_FS_HZ)) + 2 * frame_length(max_window_ms, PVDF_FS_HZ) + 16
        self.st_hist = _History(int(round(ST_HISTORY_S * ST_FS_HZ)), n_taxels)
        self.pv_hist = _History(n_pv, n_taxels)
        self.pv_filtered = _History(n_pv, n_taxels)  # the running PVDF filter's output (window restarts)
        self.st: _SingleTactBranch | None = None
        self.pv_filter: _PvdfFilter | None = None
        self.pv_windows: dict[float, _PvdfWindowBranch] = {}
        self.cursor: dict[Source, int | None] = {}  # per active source: next grid index to deliver
        self.set_sources(sources)

    # -- demand ---------------------------------------------------------------------------------
    @property
    def sources(self) -> tuple[Source, ...]:
        return tuple(self.cursor)

    def set_sources(self, sources: Iterable[Source]) -> None:
        """Make ``sources`` the active ones: branches no active source needs stop (their state is
        dropped); a branch that (re)starts is rebuilt from the raw history acquisition keeps
        (SingleTact: the last :data:`ST_HISTORY_S`; PVDF: the hum estimate plus two frames of the
        longest window): a restarted PVDF filter is primed on the hum of that history's first
        100 ms as at stream start, and a restarted window's gate replays the filtered history, so
        its output from one frame after the history start on is the one of a branch that never
        stopped (exactly so when the PVDF filter kept running). A source that (re)starts delivers
        from the first grid index after the newest raw sample received (:meth:`restart_index`),
        or from the stream start before any data."""
        sources = list(dict.fromkeys(float(s) if s is not None else None for s in sources))
        k_r = self.restart_index()
        self.cursor = {s: self.cursor[s] if s in self.cursor else k_r for s in sources}
        windows = {s for s in sources if s is not None}
        if not sources:
            self.st = None
        elif self.st is None:
            self.st = _SingleTactBranch(self.params, self.n_taxels, self.dtype, self.st_in.slot_time)
            first = self.st_hist.first
            if first is not None:
                self.st.process(*self.st_hist.since(first))
        if not windows:
            self.pv_filter = None
            self.pv_filtered.clear()
        elif self.pv_filter is None:
            first = self.pv_hist.first
            self.pv_filter = _PvdfFilter(self.params, self.n_taxels, self.dtype, self.pv_in.next_slot if first is None else first)
            self.pv_filtered.clear()
            if first is not None:
                self.pv_filtered.push(*self.pv_filter.process(self.pv_hist.since(first)[1]))
        self.pv_windows = {w: b for w, b in self.pv_windows.items() if w in windows}
        for w in windows - set(self.pv_windows):
            first = self.pv_filtered.first
            start = self.pv_filter.slot if first is None else first
            branch = _PvdfWindowBranch(self.params, w, self.n_taxels, self.dtype, self.pv_in.slot_time, start)
            if first is not None:
                branch.process(*self.pv_filtered.since(first))
            self.pv_windows[w] = branch
        self._trim()

    def restart_index(self) -> int | None:
        """First grid index after the newest raw sample of either sensor (None before any data)."""
        newest = [float(s.slot_time(s.next_slot - 1)) for s in (self.st_in, self.pv_in) if s.t0 is not None]
        return first_grid_index(max(newest), OUT_FS_HZ) if newest else None

    def first_index(self) -> int | None:
        """First grid index both sensors cover (the stream start of every source), once known."""
        if self.st_in.t0 is None or self.pv_in.t0 is None:
            return None
        return max(first_grid_index(float(s.slot_time(1)), OUT_FS_HZ) for s in (self.st_in, self.pv_in))

    # -- data -----------------------------------------------------------------------------------
    def feed(self, st_t=None, st=None, pvdf_t=None, pvdf=None) -> None:
        """Feed raw samples (either sensor may be absent in a call)."""
        if st_t is not None and len(st_t):
            first, x = self.st_in.push(st_t, st)
            self.st_hist.push(first, x)
            if self.st is not None:
                self.st.process(first, x)
        if pvdf_t is not None and len(pvdf_t):
            first, x = self.pv_in.push(pvdf_t, pvdf)
            self.pv_hist.push(first, x)
            if self.pv_filter is not None:
                self._pv_windows(*self.pv_filter.process(x))

    def _pv_windows(self, first: int, y: np.ndarray) -> None:
        self.pv_filtered.push(first, y)
        for branch in self.pv_windows.values():
            branch.process(first, y)

    def flush(self) -> None:
        """End of stream: finish every running branch up to the last sample both sensors delivered."""
        if self.st_in.t0 is None or self.pv_in.t0 is None:
            return
        until = min(float(s.slot_time(s.next_slot - 1)) for s in (self.st_in, self.pv_in))
        if self.pv_filter is not None:
            self._pv_windows(*self.pv_filter.process(np.zeros((0, self.n_taxels)), final=True))
        for branch in self.pv_windows.values():
            branch.finish(until)
        if self.st is not None:
            self.st.finish(until)

    def take(self, source: Source) -> Channels:
        """The newly final 5 kHz channels of an active ``source`` (PVDF and dPVDF zero for None)."""
        source = float(source) if source is not None else None
        if source not in self.cursor:
            raise KeyError(f"source {source} is not active")
        k_first = self.first_index()
        if k_first is None or self.st is None:
            return Channels(self.cursor[source] or 0, np.zeros((0, self.n_taxels, 4)))
        start = max(k_first, self.cursor[source] if self.cursor[source] is not None else k_first)
        grids = [self.st.out] if source is None else [self.st.out, self.pv_windows[source].out]
        ends = [g.end for g in grids]
        end = None if None in ends else min(ends)
        start = max([start] + [g.k0 for g in grids if g.k0 is not None])
        if end is None or end <= start:
            self.cursor[source] = start
            return Channels(start, np.zeros((0, self.n_taxels, 4)))
        pv = np.zeros((end - start, self.n_taxels, 2)) if source is None else grids[1].read(start, end)
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
    def latency_s(self, source: Source | None = None) -> float:
        """Algorithmic latency (s) of a source: the longest look-ahead of the branches it reads, i.e.
        the time from a grid point to the arrival of the last raw sample it needs. SingleTact: PCHIP
        needs up to two knot intervals (20 ms); a window of N PVDF samples: (N + 1) / 2 kHz."""
        source = self._only_source() if source is None and len(self.cursor) == 1 else source
        st = ST_LOOKAHEAD_KNOTS / ST_FS_HZ
        if source is None:
            return st
        return max(st, (frame_length(float(source), PVDF_FS_HZ) + 1) / PVDF_FS_HZ)

    @property
    def stats(self) -> dict[str, dict[str, int]]:
        return {"singletact": self.st_in.stats.as_dict(), "pvdf": self.pv_in.stats.as_dict()}

    @property
    def running(self) -> dict[str, bool | tuple[float, ...]]:
        """Which branches run: SingleTact, the PVDF filter, the PVDF windows (ms)."""
        return {"singletact": self.st is not None, "pvdf_filter": self.pv_filter is not None, "pvdf_windows": tuple(sorted(self.pv_windows))}

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Every numeric state variable of the running stages and buffers (stability checks, monitoring)."""
        out = {"st_last": self.st_in.last, "pv_last": self.pv_in.last, "st_hist": self.st_hist.buf, "pv_hist": self.pv_hist.buf}
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
