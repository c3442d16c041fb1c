"""The preprocessing pipeline: raw SingleTact (N, 100 Hz) + PVDF (V, 2 kHz) -> 4 channels at 5 kHz.

::

    SingleTact -> sanitize -> Butterworth low-pass -> alpha-beta -> (ST [N], dST [N/s]) -+
                                                                                        +-> PCHIP -> 5 kHz
    PVDF -> sanitize -> low-pass + mains notches -> STFT gate (OLA) -> (PVDF [V],      |
                                                           dPVDF = backward diff [V/s]) -+

:class:`Preprocessor` is a sans-I/O state machine: ``process(...)`` takes whatever raw samples
arrived (any chunk size, any number of taxels) and returns the newly final 5 kHz samples, aligned
on the absolute grid ``k / 5000`` s of the recording clock; ``finish()`` flushes at end of stream.
Offline processing of a whole recording is the same two calls (:func:`preprocess_trial`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..params import PreprocessParams
from ..recording import Trial
from ..settings import OUT_FS_HZ, PVDF_FS_HZ, PVDF_RANGE_V, ST_FS_HZ, ST_RANGE_N
from .filters import HUM_PRIME_S, AlphaBeta, butter_lowpass, mains_frequencies, prime_with_hum
from .gate import gate_thresholds, pvdf_filter
from .resample import CausalPchip
from .sanitize import Sanitizer
from .stft_gate import StftGate, frame_length

_ST_LP_ORDER = 2


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


class _Aligner:
    """Holds each branch's 5 kHz output until the other branch has covered the same grid points."""

    def __init__(self, n_taxels: int):
        self.parts: list[tuple[int, np.ndarray]] = [(0, np.zeros((0, n_taxels, 2)))] * 2
        self.started = [False, False]
        self.next_k: int | None = None

    def add(self, branch: int, k0: int, block: np.ndarray) -> None:
        if block.shape[0] == 0:
            return
        start, held = self.parts[branch]
        if not self.started[branch]:
            self.parts[branch], self.started[branch] = (k0, block), True
        else:
            self.parts[branch] = (start, np.concatenate((held, block), axis=0))

    def pop(self) -> tuple[int, np.ndarray] | None:
        if not all(self.started):
            return None
        (s0, a), (s1, b) = self.parts
        start = max(s0, s1) if self.next_k is None else self.next_k
        end = min(s0 + a.shape[0], s1 + b.shape[0])
        if end <= start:
            return None
        out = np.concatenate((a[start - s0 : end - s0], b[start - s1 : end - s1]), axis=2)
        self.parts = [(end, a[end - s0 :]), (end, b[end - s1 :])]
        self.next_k = end
        return start, out


class Preprocessor:
    """Causal, chunk-wise, stateful preprocessing of N taxels (see the module docstring)."""

    def __init__(self, params: PreprocessParams | None = None, n_taxels: int = 1, dtype: type = np.float64):
        self.params = params = params or PreprocessParams()
        self.n_taxels = n_taxels
        self.dtype = dt = np.dtype(dtype)  # arithmetic of the filters and the STFT gate
        # SingleTact branch (100 Hz)
        self.st_in = Sanitizer(ST_FS_HZ, ST_RANGE_N, n_taxels)
        self.st_lp = butter_lowpass(params.st_lowpass_hz, ST_FS_HZ, _ST_LP_ORDER, n_taxels, dt)
        self.st_ab = AlphaBeta(params.st_alpha, params.st_beta, ST_FS_HZ, n_taxels)
        self.st_rs = CausalPchip(OUT_FS_HZ, 2 * n_taxels)
        # PVDF branch (2 kHz)
        self.pv_in = Sanitizer(PVDF_FS_HZ, PVDF_RANGE_V, n_taxels)
        self.pv_filter = pvdf_filter(params, PVDF_FS_HZ, n_taxels, dt)  # low-pass + mains notch comb, one cascade
        self.hum_hz = mains_frequencies(params.mains_hz, params.notch_harmonics, PVDF_FS_HZ)
        self.pv_held: list[np.ndarray] | None = []  # raw PVDF of the stream start, until the filter is primed
        n = frame_length(params.window_ms, PVDF_FS_HZ)
        gate = StftGate(n, n_taxels, dtype=dt)
        if params.gate is not None:
            thresholds = gate_thresholds(params.gate, gate.window.astype(np.float64), PVDF_FS_HZ)
            gate = StftGate(n, n_taxels, thresholds, params.gate.attenuation, dtype=dt)
        self.pv_gate = gate
        self.pv_slot = 0  # PVDF grid slot of the next gate output sample
        self.pv_prev: np.ndarray | None = None  # last reconstructed PVDF sample (for the derivative)
        self.pv_rs = CausalPchip(OUT_FS_HZ, 2 * n_taxels)
        self.align = _Aligner(n_taxels)

    @property
    def latency_s(self) -> float:
        """Algorithmic latency: PVDF frame plus one PCHIP knot interval of SingleTact."""
        return self.pv_gate.n / PVDF_FS_HZ + 2.0 / ST_FS_HZ

    @property
    def stats(self) -> dict[str, dict[str, int]]:
        return {"singletact": self.st_in.stats.as_dict(), "pvdf": self.pv_in.stats.as_dict()}

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Every numeric state variable of the stages (for stability checks and monitoring)."""
        out = {"st_last": self.st_in.last, "pv_last": self.pv_in.last, "st_ab_v": self.st_ab.v}
        for name, f in (("st_lp", self.st_lp), ("pv_filter", self.pv_filter)):
            if f.zi is not None:
                out[name] = f.zi
        if self.st_ab.x is not None:
            out["st_ab_x"] = self.st_ab.x
        out["pv_gate_buf"], out["pv_gate_acc"] = self.pv_gate._buf, self.pv_gate._acc
        for name, rs in (("st_rs", self.st_rs), ("pv_rs", self.pv_rs)):
            out[name] = rs._y
        for b, (_, held) in enumerate(self.align.parts):
            out[f"align_{b}"] = held
        if self.pv_prev is not None:
            out["pv_prev"] = self.pv_prev
        if self.pv_held:
            out["pv_held"] = np.concatenate(self.pv_held)
        return out

    def process(self, st_t=None, st=None, pvdf_t=None, pvdf=None) -> Channels:
        """Feed raw samples (either sensor may be absent in a call); return new 5 kHz channels."""
        if st_t is not None and len(st_t):
            first, x = self.st_in.push(st_t, st)
            self._st_branch(self.st_in.slot_time(np.arange(first, first + x.shape[0])), x)
        if pvdf_t is not None and len(pvdf_t):
            _, x = self.pv_in.push(pvdf_t, pvdf)
            self._pv_filter(x)
        return self._pop()

    def finish(self) -> Channels:
        """End of stream: flush the buffered tail up to the last sample both sensors delivered."""
        if self.st_in.t0 is None or self.pv_in.t0 is None:
            return self._pop()
        until = min(
            float(self.st_in.slot_time(self.st_in.next_slot - 1)),
            float(self.pv_in.slot_time(self.pv_in.next_slot - 1)),
        )
        self._pv_filter(np.zeros((0, self.n_taxels)), final=True)
        self._pv_branch(self.pv_gate.process(np.zeros((self.pv_gate.n, self.n_taxels))))
        self.align.add(0, *self._split(self.st_rs.finish(until)))
        self.align.add(1, *self._split(self.pv_rs.finish(until)))
        return self._pop()

    # -- branches -------------------------------------------------------------------------------
    def _st_branch(self, t: np.ndarray, x: np.ndarray) -> None:
        force, rate = self.st_ab.process(self.st_lp.process(x))
        self.align.add(0, *self._split(self.st_rs.process(t, np.concatenate((force, rate), axis=1))))

    def _pv_filter(self, x: np.ndarray, final: bool = False) -> None:
        """Low-pass + notches, then the gate. The first :data:`HUM_PRIME_S` of the stream are held
        and the filter is primed with the hum fitted to them (no notch ringing at stream start); the
        gate's first frame needs at least as long, so with windows >= 100 ms no output is later."""
        if self.pv_held is not None:
            self.pv_held.append(x)
            n_prime = int(round(HUM_PRIME_S * PVDF_FS_HZ))
            held = np.concatenate(self.pv_held)
            if held.shape[0] < n_prime and not final:
                return
            self.pv_held = None
            if held.shape[0] == 0:
                return
            prime_with_hum(self.pv_filter, held[:n_prime], PVDF_FS_HZ, self.hum_hz)
            x = held
        self._pv_branch(self.pv_gate.process(self.pv_filter.process(x)))

    def _pv_branch(self, y: np.ndarray) -> None:
        if y.shape[0] == 0:
            return
        prev = y[:1] if self.pv_prev is None else self.pv_prev[None, :]
        dy = np.diff(np.concatenate((prev, y), axis=0), axis=0) * PVDF_FS_HZ
        self.pv_prev = y[-1].copy()
        slots = np.arange(self.pv_slot, self.pv_slot + y.shape[0])
        self.pv_slot += y.shape[0]
        self.align.add(1, *self._split(self.pv_rs.process(self.pv_in.slot_time(slots), np.concatenate((y, dy), axis=1))))

    def _split(self, emitted: tuple[int, np.ndarray]) -> tuple[int, np.ndarray]:
        k0, v = emitted
        return k0, v.reshape(v.shape[0], 2, self.n_taxels).transpose(0, 2, 1)

    def _pop(self) -> Channels:
        got = self.align.pop()
        if got is None:
            k = self.align.next_k or 0
            return Channels(k, np.zeros((0, self.n_taxels, 4)))
        return Channels(got[0], got[1])


def preprocess_trial(trial: Trial, params: PreprocessParams | None = None) -> Channels:
    """Whole-recording preprocessing of one taxel: the online pipeline fed everything at once."""
    pre = Preprocessor(params, n_taxels=1)
    head = pre.process(trial.st_t, trial.st, trial.pvdf_t, trial.pvdf)
    tail = pre.finish()
    return Channels.concatenate([head, tail], 1)
