"""The branches of the preprocessing and their buffers (used by :mod:`.pipeline`).

* :class:`SingleTactBranch`: sanitized SingleTact (N, 100 Hz) -> Butterworth low-pass -> alpha-beta
  -> PCHIP onto the 5 kHz grid (ST [N], dST [N/s]);
* :class:`PvdfFilter`: sanitized PVDF (V, 2 kHz) -> low-pass + mains notches, hum-primed at its start;
* :class:`PvdfWindowBranch`: filtered PVDF -> STFT gate of one causal window -> (PVDF [V],
  dPVDF [V/s]) -> PCHIP onto the 5 kHz grid;
* :class:`History`: a ring of the last samples of a grid, by slot (restarts are rebuilt from it);
* :class:`Grid`: a branch's 5 kHz output until every source has read it.

Each branch is a sans-I/O state machine fed slot-indexed samples; frame boundaries, knots and grid
points depend only on sample indices, so chunking never changes the output. Per-taxel processing
is independent, so branches fed the same samples can be regrouped by taxel (``gather``: the taxels
``idx`` of each part, in order, into one branch, every state copied bit for bit): the activity-driven
stream merges the taxels a contact woke into the running set and drops those that went quiet.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence

import numpy as np

from ..params import GateCalibration, PreprocessParams
from ..settings import OUT_FS_HZ, PVDF_FS_HZ, ST_FS_HZ
from .filters import HUM_PRIME_S, AlphaBeta, SosFilter, butter_lowpass, mains_frequencies, prime_with_hum
from .gate import gate_thresholds, pvdf_filter
from .mains import MainsResolver
from .resample import CausalPchip
from .stft_gate import StftGate, frame_length, hann_window

_ST_LP_ORDER = 2


class History:
    """The last ``size`` samples of a regular grid (n, n_taxels), by grid slot (a ring buffer of ``dtype``)."""

    def __init__(self, size: int, n_taxels: int, dtype: type = np.float64):
        self.buf = np.zeros((size, n_taxels), dtype)
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

    def since(self, slot: int, cols: slice | np.ndarray = slice(None)) -> tuple[int, np.ndarray]:
        """(first slot, samples of the taxels ``cols``) from ``slot`` (or the oldest kept) to the newest."""
        first = max(slot, self.end - self.count)
        return first, self.buf[:, cols][np.arange(first, self.end) % self.buf.shape[0]]

    @property
    def first(self) -> int | None:
        return self.end - self.count if self.count else None

    @staticmethod
    def gather(parts: Sequence[tuple["History", np.ndarray]]) -> "History":
        """The taxels ``idx`` of each part, in order: the samples every part holds."""
        held = [h for h, _ in parts if h.count]
        if len({h.end for h in held}) > 1:
            raise ValueError("histories gathered into one must end at the same slot")
        out = History(parts[0][0].buf.shape[0], 0, parts[0][0].buf.dtype)
        out.buf = np.concatenate([h.buf[:, idx] for h, idx in parts], axis=1)
        out.count = min(h.count for h, _ in parts)
        out.end = held[0].end if held and out.count else 0
        return out

    def clear(self) -> None:
        self.count = 0


class Grid:
    """A branch's 5 kHz output (T, n_taxels, 2) not yet read by every source, as a list of blocks."""

    def __init__(self, n_taxels: int):
        self.n_taxels = n_taxels
        self.blocks: list[tuple[int, np.ndarray]] = []
        self.end: int | None = None  # grid index after the newest emitted sample

    def add(self, emitted: tuple[int, np.ndarray]) -> None:
        k0, v = emitted
        if v.shape[0] == 0:
            return
        self.blocks.append((k0, v.reshape(v.shape[0], 2, self.n_taxels).transpose(0, 2, 1)))
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

    @staticmethod
    def gather(parts: Sequence[tuple["Grid", np.ndarray]]) -> "Grid":
        """The taxels ``idx`` of each part, in order, as one block from the earliest sample any part
        holds to their common end; a part that starts later (a branch rebuilt from a short raw history)
        holds its first value back to there."""
        ends = {g.end for g, _ in parts}
        if len(ends) > 1:
            raise ValueError(f"grids gathered into one must end at the same index, have {sorted(ends, key=str)}")
        out = Grid(sum(len(idx) for _, idx in parts))
        out.end = end = ends.pop()
        starts = [g.k0 for g, _ in parts if g.blocks]
        if end is None or not starts:
            return out
        k0 = min(starts)
        dtype = next(g.blocks[0][1].dtype for g, _ in parts if g.blocks)
        cols = []
        for g, idx in parts:
            x = g.read(g.k0, end)[:, idx] if g.blocks else np.zeros((0, len(idx), 2), dtype)
            if x.shape[0] < end - k0:
                head = x[:1] if x.shape[0] else np.zeros((1, len(idx), 2), dtype)
                x = np.concatenate((np.repeat(head, end - k0 - x.shape[0], axis=0), x))
            cols.append(x)
        out.blocks = [(k0, np.concatenate(cols, axis=1))]
        return out


class SingleTactBranch:
    """SingleTact: Butterworth low-pass -> alpha-beta -> PCHIP onto the 5 kHz grid (ST [N], dST [N/s])."""

    def __init__(self, params: PreprocessParams, n_taxels: int, dtype: np.dtype, slot_time: Callable):
        self.lp = butter_lowpass(params.st_lowpass_hz, ST_FS_HZ, _ST_LP_ORDER, n_taxels, dtype)
        self.ab = AlphaBeta(params.st_alpha, params.st_beta, ST_FS_HZ, n_taxels)
        self.rs = CausalPchip(OUT_FS_HZ, 2 * n_taxels, dtype)
        self.slot_time = slot_time
        self.out = Grid(n_taxels)

    def process(self, first: int, x: np.ndarray) -> None:
        if x.shape[0] == 0:
            return
        force, rate = self.ab.process(self.lp.process(x))
        t = self.slot_time(np.arange(first, first + x.shape[0]))
        self.out.add(self.rs.process(t, np.concatenate((force, rate), axis=1)))

    def finish(self, until_s: float) -> None:
        self.out.add(self.rs.finish(until_s))

    @staticmethod
    def gather(parts: Sequence[tuple["SingleTactBranch", np.ndarray]]) -> "SingleTactBranch":
        out = copy.copy(parts[0][0])
        out.lp = SosFilter.gather([(b.lp, idx) for b, idx in parts])
        out.ab = AlphaBeta.gather([(b.ab, idx) for b, idx in parts])
        out.rs = CausalPchip.gather([(b.rs, idx) for b, idx in parts], groups=2)
        out.out = Grid.gather([(b.out, idx) for b, idx in parts])
        return out

    def state_arrays(self) -> dict[str, np.ndarray]:
        out = {"st_ab_v": self.ab.v, "st_rs": self.rs._y}
        if self.lp.zi is not None:
            out["st_lp"] = self.lp.zi
        if self.ab.x is not None:
            out["st_ab_x"] = self.ab.x
        return out


class PvdfFilter:
    """PVDF low-pass + mains notches (one cascade), started at grid slot ``slot``: its first
    :data:`HUM_PRIME_S` are held, then the cascade's notches follow the stream's mains (``mains``,
    resolved once per stream from its first samples: :mod:`.mains`), it is primed with the hum
    fitted to them (no notch ringing at the start), and everything flows through. The cascade
    runs in float64 whatever ``dtype`` (the output's): in float32 its notches' poles near the unit
    circle put errors of ~1e-3 of the range into the PVDF channels, in float64 ~2e-7, at the same
    cost (~1.2 ms per update at 4096 taxels)."""

    def __init__(self, params: PreprocessParams, n_taxels: int, dtype: np.dtype, slot: int, mains: MainsResolver):
        self.params = params
        self.mains = mains
        #: built at once with the configured mains (a set whose notches cannot be made fails here), again
        #: with the stream's own mains if that differs once the start is held (:meth:`process`)
        self.filt: SosFilter = pvdf_filter(params, PVDF_FS_HZ, n_taxels, np.float64)
        self.dtype = np.dtype(dtype)
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
            params, mains_hz = self.params, self.mains.resolve()
            if mains_hz != params.mains_hz:
                params = params.model_copy(update={"mains_hz": mains_hz})
                self.filt = pvdf_filter(params, PVDF_FS_HZ, self.n_taxels, np.float64)
            prime_with_hum(self.filt, held[:n_prime], PVDF_FS_HZ,
                           mains_frequencies(params.mains_hz, params.notch_harmonics, PVDF_FS_HZ))
            x = held
        first = self.slot
        self.slot += x.shape[0]
        return first, self.filt.process(x).astype(self.dtype, copy=False)

    @staticmethod
    def gather(parts: Sequence[tuple["PvdfFilter", np.ndarray]]) -> "PvdfFilter":
        """Filters at the same slot, all primed or all still holding the same start."""
        held = [None if f.held is None else np.concatenate(f.held) if f.held else np.zeros((0, f.n_taxels)) for f, _ in parts]
        if any(f.slot != parts[0][0].slot for f, _ in parts) or len({None if h is None else h.shape[0] for h in held}) > 1:
            raise ValueError("PVDF filters gathered into one must be at the same slot, all primed or holding the same samples")
        out = copy.copy(parts[0][0])
        out.filt = SosFilter.gather([(f.filt, idx) for f, idx in parts])
        out.n_taxels = out.filt.n_taxels
        if held[0] is not None:
            out.held = [np.concatenate([h[:, idx] for h, (_, idx) in zip(held, parts)], axis=1)]
        return out

    def state_arrays(self) -> dict[str, np.ndarray]:
        out = {} if self.filt.zi is None else {"pv_filter": self.filt.zi}
        if self.held:
            out["pv_held"] = np.concatenate(self.held)
        return out


_THRESHOLDS: dict[tuple[int, int, str], tuple[GateCalibration, np.ndarray]] = {}  #: by (id of the calibration, frame, dtype)


def _thresholds(gate: GateCalibration, n: int, dtype: np.dtype) -> np.ndarray:
    """The gate's per-bin thresholds for frames of ``n`` samples windowed in ``dtype`` (computed once per
    calibration: a stream that wakes taxels builds branches often)."""
    key = (id(gate), n, dtype.str)
    hit = _THRESHOLDS.get(key)
    if hit is None or hit[0] is not gate:
        if len(_THRESHOLDS) >= 64:
            _THRESHOLDS.clear()
        hit = _THRESHOLDS[key] = (gate, gate_thresholds(gate, hann_window(n, dtype.str).astype(np.float64), PVDF_FS_HZ))
    return hit[1]


class PvdfWindowBranch:
    """One causal window: STFT gate (OLA) -> (PVDF [V], dPVDF = backward difference [V/s]) -> PCHIP.

    Frames lie on the absolute slot grid (a frame starts at every multiple of the hop), so a branch
    started at any slot gives, once its first frame is full of real samples, exactly the output of a
    branch that ran all along on the same filtered input."""

    def __init__(self, params: PreprocessParams, window_ms: float, n_taxels: int, dtype: np.dtype, slot_time: Callable, slot: int):
        n = frame_length(window_ms, PVDF_FS_HZ)
        if params.gate is None:
            self.gate = StftGate(n, n_taxels, dtype=dtype)
        else:
            self.gate = StftGate(n, n_taxels, _thresholds(params.gate, n, np.dtype(dtype)), params.gate.attenuation, dtype=dtype)
        gate = self.gate
        self.n_taxels = n_taxels
        self.in_slot = -(-slot // gate.hop) * gate.hop  # first input slot: the next frame boundary
        self.out_slot = self.in_slot  # slot of the next gate output sample
        self.prev: np.ndarray | None = None  # last gate output (for the derivative)
        self.rs = CausalPchip(OUT_FS_HZ, 2 * n_taxels, dtype)
        self.slot_time = slot_time
        self.out = Grid(n_taxels)

    def process(self, first: int, y: np.ndarray) -> None:
        """Filtered PVDF samples from slot ``first`` on (contiguous with the previous call)."""
        skip = self.in_slot - first
        if skip < 0:
            raise ValueError(f"PVDF branch expected slot {self.in_slot}, got {first}")
        y = y[skip:]
        self.in_slot += y.shape[0]
        self._emit(self.gate.process(y))

    def finish(self, until_s: float) -> None:
        self._emit(self.gate.process(np.zeros((self.gate.n, self.n_taxels), self.gate.dtype)))
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

    @staticmethod
    def gather(parts: Sequence[tuple["PvdfWindowBranch", np.ndarray]]) -> "PvdfWindowBranch":
        """Branches at the same input and output slots."""
        first = parts[0][0]
        if any((b.in_slot, b.out_slot, b.prev is None) != (first.in_slot, first.out_slot, first.prev is None) for b, _ in parts):
            raise ValueError("window branches gathered into one must be at the same slots")
        out = copy.copy(first)
        out.gate = StftGate.gather([(b.gate, idx) for b, idx in parts])
        out.n_taxels = out.gate.n_taxels
        out.prev = None if first.prev is None else np.concatenate([b.prev[idx] for b, idx in parts])
        out.rs = CausalPchip.gather([(b.rs, idx) for b, idx in parts], groups=2)
        out.out = Grid.gather([(b.out, idx) for b, idx in parts])
        return out

    def state_arrays(self, name: str) -> dict[str, np.ndarray]:
        out = {f"{name}_gate_buf": self.gate._buf, f"{name}_gate_acc": self.gate._acc, f"{name}_rs": self.rs._y}
        if self.prev is not None:
            out[f"{name}_prev"] = self.prev
        return out
