"""TouchReal encoder: four 5 kHz channels -> SA1/RA/PC-like spikes, TouchSim-style LIF per class.

For afferent class a and channels x_c (ST, dST, PVDF, dPVDF), the input current is

    x_c <- HP_a(LP_a(x_c))       (optional per-class 3rd-order Butterworth low-pass, 1st-order high-pass)
    I_a[k] = sum_c  w_a[2c] * max(x_c[k - L_a], 0) + w_a[2c+1] * max(-x_c[k], 0)       (w1..w8)
    I_a <- I_sat * I_a / (I_sat + |I_a|)                                       (when I_sat > 0)

with L_a the class's negative-part lead (``negative_lead_ms``, 0 by default). I_a drives the LIF of
:mod:`touchreal.encoding.lif` with the class's tau and post-spike current. A spike at grid sample k
is reported at ``(k + 1) / 5000 + delay`` seconds on the recording clock.

:class:`Encoder` is stateful and handles N taxels x the selected classes as one neuron population;
``encode_population`` runs many parameter sets on one taxel's channels at once (used by fitting).
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np
from scipy import signal

from ..params import ClassParams, EncoderParams
from ..preprocess.filters import SosFilter, sos_step
from ..preprocess.parallel import split_run
from ..settings import CHANNELS, CLASSES, OUT_FS_HZ, PACKAGE_DATA
from .lif import REFRACTORY_SAMPLES, RESET, THRESHOLD, LifPopulation


@lru_cache(maxsize=1)
def ih_basis() -> np.ndarray:
    """TouchSim's two post-spike current basis functions, (2, 190) at 5 kHz."""
    data = json.loads((PACKAGE_DATA / "touchsim_constants.json").read_text())
    return np.asarray(data["ihbasis"], dtype=np.float64)


N_CHANNELS = len(CHANNELS)  #: ST, dST, PVDF, dPVDF (a compile-time constant of the input kernel)
LOWPASS_ORDER = 3  #: order of the per-class input Butterworth (TouchSim's input filter)
LOWPASS_SECTIONS = (LOWPASS_ORDER + 1) // 2
HIGHPASS_ORDER = 1  #: order of the optional per-class input high-pass (one section)
_IDENTITY_SECTION = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0])  #: y = 1 x + 0: exact, bit for bit


@lru_cache(maxsize=1024)
def _lowpass_design(cutoff_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Class low-pass at ``cutoff_hz`` (Hz) on the 5 kHz grid: (sections, 6) SOS and its unit-step
    steady state ``sosfilt_zi`` (sections, 2); cached, since the fit rebuilds it per trial."""
    sos = signal.butter(LOWPASS_ORDER, cutoff_hz, btype="low", fs=OUT_FS_HZ, output="sos")
    return sos, signal.sosfilt_zi(sos)


@lru_cache(maxsize=1024)
def _input_design(lowpass_hz: float | None, highpass_hz: float | None) -> tuple[np.ndarray, np.ndarray]:
    """A class's input cascade on the 5 kHz grid: the low-pass's :data:`LOWPASS_SECTIONS` (identity
    sections without one), then the high-pass's section when it has one. Returns the SOS and its
    unit-step steady state (``sosfilt_zi``: a high-pass settles at 0)."""
    if highpass_hz is None:
        return _lowpass_design(float(lowpass_hz)) if lowpass_hz is not None else (np.zeros((0, 6)), np.zeros((0, 2)))
    lp = _lowpass_design(float(lowpass_hz))[0] if lowpass_hz is not None else np.tile(_IDENTITY_SECTION, (LOWPASS_SECTIONS, 1))
    sos = np.vstack([lp, signal.butter(HIGHPASS_ORDER, float(highpass_hz), btype="high", fs=OUT_FS_HZ, output="sos")])
    return sos, signal.sosfilt_zi(sos)


def class_filtered(channels: np.ndarray, lowpass_hz: float | None, highpass_hz: float | None = None) -> np.ndarray:
    """(T, ..., 4) channels through a fresh class input filter (unchanged when it has none)."""
    if lowpass_hz is None and highpass_hz is None:
        return channels
    flat = np.asarray(channels, np.float64).reshape(channels.shape[0], -1)
    return SosFilter(_input_design(lowpass_hz, highpass_hz)[0], flat.shape[1]).process(flat).reshape(channels.shape)


def rectify(channels: np.ndarray) -> np.ndarray:
    """(..., 4) channels -> (..., 8) [max(x,0), max(-x,0)] per channel, in w1..w8 order."""
    pos = np.maximum(channels, 0.0)
    neg = np.maximum(-channels, 0.0)
    return np.stack((pos, neg), axis=-1).reshape(*channels.shape[:-1], 8)


TILE_TAXELS = 16  #: taxels the fused kernel copies at once (contiguous rows of 16 x 4 channels)


@numba.njit(cache=True, nogil=True)
def _encode_columns(channels, src, w, i_sat, sos, has_lp, zi, hp_sos, has_hp, hp_zi, lead, ring, head,
                    tau, ih, v_mem, counter, spikes, n_spikes, out, a, b):  # pragma: no cover - compiled
    """Input stage and LIF of columns a ... b - 1 fused: no current array; column n's spikes (grid
    sample within the block) go to ``spikes[n, :n_spikes[n]]``. With a non-empty ``out`` (N, T)
    the input current goes there instead and the LIF does not run (:meth:`InputStage.process`).

    Per column: the class low-pass (when has_lp[n]: the cascade sos[n], state zi[n]) and high-pass
    (when has_hp[n]: the section hp_sos[n], state hp_zi[n]), each stepped by
    :func:`~touchreal.preprocess.filters.sos_step` like every :class:`SosFilter`;
    pos / neg = sum_j w[n, 2j] max(x_j, 0) / w[n, 2j+1] max(-x_j, 0); with lead[n] = L > 0 the
    positive part passes through ring[n, :L] (so it is taken from sample k - L); then
    ``I_sat I / (I_sat + |I|)`` where ``I_sat > 0``; then the LIF (tau, post-spike current ih,
    state v_mem and counter). State is updated in place.

    The channels of a tile of :data:`TILE_TAXELS` taxels are first copied to a contiguous buffer,
    so a column runs over its samples without striding across the whole (T, X, 4) array (which
    cost a TLB miss per sample at thousands of taxels); one column's state stays local while it
    runs over the block (faster, measured, than advancing a tile's columns side by side)."""
    n_t, n_x = channels.shape[0], channels.shape[1]
    nh = ih.shape[1]
    currents = out.shape[1] > 0
    tile = np.empty((n_t, TILE_TAXELS, N_CHANNELS))
    loaded = -1
    z = np.empty((1, sos.shape[1], 2, N_CHANNELS))
    zh = np.empty((1, hp_sos.shape[1], 2, N_CHANNELS))
    v = np.empty(N_CHANNELS)
    for n in range(a, b):
        x0 = src[n] - src[n] % TILE_TAXELS
        if x0 != loaded:
            width = min(TILE_TAXELS, n_x - x0)
            for k in range(n_t):
                for t in range(width):
                    for j in range(N_CHANNELS):
                        tile[k, t, j] = channels[k, x0 + t, j]
            loaded = x0
        x = src[n] - x0
        lp = has_lp[n]
        hp = has_hp[n]
        z[0] = zi[n]
        zh[0] = hp_zi[n]
        n_lead = lead[n]
        h = head[n]
        s_max = i_sat[n]
        tau_n = tau[n]
        vm = v_mem[n]
        c = counter[n]
        count = 0
        for k in range(n_t):
            for j in range(N_CHANNELS):
                v[j] = tile[k, x, j]
            if lp:
                sos_step(sos, n, v, z, 0, N_CHANNELS)
            if hp:
                sos_step(hp_sos, n, v, zh, 0, N_CHANNELS)
            pos = 0.0
            neg = 0.0
            for j in range(N_CHANNELS):  # branch-free (noise flips signs unpredictably); adding 0 keeps the bits
                pos += w[n, 2 * j] * max(v[j], 0.0)
                neg -= w[n, 2 * j + 1] * min(v[j], 0.0)
            if n_lead > 0:
                old = ring[n, h]
                ring[n, h] = pos
                pos = old
                h = h + 1 if h + 1 < n_lead else 0
            acc = pos + neg
            if s_max > 0.0:
                acc = s_max * acc / (s_max + abs(acc))
            if currents:
                out[n, k] = acc
                continue
            # the LIF step of touchreal.encoding.lif._lif_run, written out (tested equal): sharing it as a
            # numba function (inline="always", with or without a spiked flag) made this kernel ~20 % slower
            # (4096 taxels x 3 classes, a 32 ms chunk, one thread: 52 against 43.5 ms of CPU, A/B on the AMD
            # EPYC VM 2026-11-29); called per column rather than per sample, ~26 %
            vm = vm - vm / tau_n + acc
            if c < nh:
                vm += ih[n, c]
                c += 1
            if vm > THRESHOLD and c > REFRACTORY_SAMPLES:
                vm = RESET
                c = 0
                if count < spikes.shape[1]:
                    spikes[n, count] = k
                count += 1
        zi[n] = z[0]
        hp_zi[n] = zh[0]
        head[n] = h
        v_mem[n] = vm
        counter[n] = c
        n_spikes[n] = count


class InputStage:
    """Stateful class input stages of N columns: (T, X, 4) channels -> (T, N) input current.

    Column n applies ``params[n]`` to taxel ``taxels[n]``:

    1. optional class input filter, steady state at the first sample: a low-pass (``lowpass_hz``:
       3rd-order Butterworth) and a high-pass (``highpass_hz``: 1st-order Butterworth; it removes a
       constant, so a column starts at 0 current on a steady baseline);
    2. rectified weights: positive parts ``w[2c] max(x_c, 0)``, negative parts ``w[2c+1] max(-x_c, 0)``;
    3. optional lead of the negative parts: the positive-part current is delayed by
       ``negative_lead_ms`` (its history starts at the first sample's value), the negative parts are not;
    4. TouchSim's saturation ``I_sat I / (I_sat + |I|)`` (when ``I_sat > 0``).

    The encoder uses one column per (taxel, class), the fit one column per candidate. Chunks of any
    size give the same current as the whole signal.
    """

    def __init__(self, params: Sequence[ClassParams], taxels: Sequence[int] | np.ndarray):
        self.src = np.ascontiguousarray(taxels, dtype=np.int64)
        self._n_taxels = int(self.src.max(initial=-1)) + 1  #: taxels the channels must have at least
        if self.src.shape != (len(params),):
            raise ValueError("one taxel index per column is required")
        n = len(params)
        self.w = np.array([p.weights for p in params], dtype=np.float64).reshape(n, 8)
        self.i_sat = np.array([p.i_sat for p in params], dtype=np.float64)
        # per column the low-pass's sections and the high-pass's one, stepped only where the column
        # has that filter; the steady states are those of the whole cascade
        self.has_lp = np.array([p.lowpass_hz is not None for p in params], dtype=np.bool_)
        self.has_hp = np.array([p.highpass_hz is not None for p in params], dtype=np.bool_)
        self.sos = np.zeros((n, LOWPASS_SECTIONS, 6))
        self._zi_unit = np.zeros((n, LOWPASS_SECTIONS, 2))
        self.hp_sos = np.zeros((n, 1, 6))
        self._hp_zi_unit = np.zeros((n, 1, 2))
        rows: dict[tuple[float | None, float | None], list[int]] = {}  # columns by input filter (a class's share one)
        for j, p in enumerate(params):
            rows.setdefault((p.lowpass_hz, p.highpass_hz), []).append(j)
        for (lowpass_hz, highpass_hz), js in rows.items():
            sos, zi = _input_design(lowpass_hz, highpass_hz)
            if lowpass_hz is not None:
                self.sos[js], self._zi_unit[js] = sos[:LOWPASS_SECTIONS], zi[:LOWPASS_SECTIONS]
            if highpass_hz is not None:
                self.hp_sos[js], self._hp_zi_unit[js] = sos[LOWPASS_SECTIONS:], zi[LOWPASS_SECTIONS:]
        self.lead = np.array([int(round(p.negative_lead_ms * OUT_FS_HZ / 1000.0)) for p in params], dtype=np.int64)
        self.zi = np.zeros((n, LOWPASS_SECTIONS, 2, N_CHANNELS))
        self.hp_zi = np.zeros((n, 1, 2, N_CHANNELS))
        self.ring = np.zeros((n, int(self.lead.max(initial=0))))
        self.head = np.zeros(n, dtype=np.int64)
        self.fresh = np.ones(n, dtype=np.bool_)  # columns whose state starts at their next first sample

    @property
    def n_columns(self) -> int:
        return self.src.size

    def carry(self, old: "InputStage", old_rows: np.ndarray, new_rows: np.ndarray) -> None:
        """Continue columns ``old_rows`` of ``old`` as this stage's ``new_rows`` (same class
        parameters): their state is copied bit-exactly; the other columns start fresh."""
        self.zi[new_rows] = old.zi[old_rows]
        self.hp_zi[new_rows] = old.hp_zi[old_rows]
        lead = min(old.ring.shape[1], self.ring.shape[1])  # a column uses its own lead's first entries only
        self.ring[new_rows, :lead] = old.ring[old_rows, :lead]
        self.head[new_rows] = old.head[old_rows]
        self.fresh[new_rows] = old.fresh[old_rows]

    #: per-column arrays (first axis: the column), copied row by row when stages are gathered
    _COLUMN_ARRAYS = ("src", "w", "i_sat", "has_lp", "has_hp", "sos", "_zi_unit", "hp_sos", "_hp_zi_unit", "lead", "zi", "hp_zi",
                      "head", "fresh")

    @staticmethod
    def gather(parts: Sequence[tuple["InputStage", np.ndarray]], src: np.ndarray) -> "InputStage":
        """One stage of the columns ``rows`` of each part, in order, reading the taxels ``src``
        (one per column): parameters and state copied bit for bit."""
        out = copy.copy(parts[0][0])
        for name in InputStage._COLUMN_ARRAYS:
            setattr(out, name, np.concatenate([getattr(st, name)[rows] for st, rows in parts]))
        out.src = np.ascontiguousarray(src, dtype=np.int64)
        out._n_taxels = int(out.src.max(initial=-1)) + 1
        width = int(out.lead.max(initial=0))  # a column uses its own lead's first entries only
        out.ring = np.zeros((out.src.size, width))
        at = 0
        for st, rows in parts:
            k = min(width, st.ring.shape[1])
            out.ring[at : at + len(rows), :k] = st.ring[rows, :k]
            at += len(rows)
        return out

    def _start(self, first: np.ndarray) -> None:
        """Fresh columns start in steady state at their first sample ``first`` (X, 4): the input
        filter at that sample (the low-pass's DC gain is 1, the high-pass's 0), the lead's history at its positive-part current."""
        rows = np.flatnonzero(self.fresh)
        x = first[self.src[rows]]  # (R, 4)
        self.zi[rows] = self._zi_unit[rows, :, :, None] * x[:, None, None, :]
        self.hp_zi[rows] = self._hp_zi_unit[rows, :, :, None] * x[:, None, None, :]
        pos = np.zeros(rows.size)
        for j in range(N_CHANNELS):  # left to right, as a row sum: the same bits for any set of rows
            pos = pos + np.maximum(x[:, j], 0.0) * self.w[rows, 2 * j]
        self.ring[rows] = pos[:, None]
        self.head[rows] = 0
        self.fresh[rows] = False

    def prepare(self, channels: np.ndarray) -> np.ndarray:
        """The channels as the kernel takes them ((T, X, 4) float64 or float32, in any memory layout:
        the kernel copies taxel tiles, converting to float64, so neither the preprocessing's layout
        nor its dtype is copied first; shape checked), with fresh columns started at their first sample."""
        x = np.asarray(channels)
        if x.dtype not in (np.float64, np.float32):
            x = x.astype(np.float64)
        if x.ndim != 3 or x.shape[2] != N_CHANNELS or x.shape[1] < self._n_taxels:
            raise ValueError(f"channels must be (T, >= {self._n_taxels} taxels, {N_CHANNELS}), got {x.shape}")
        if x.shape[0] and self.fresh.any():
            self._start(x[0])
        return x

    def _run(self, x: np.ndarray, lif: LifPopulation | None, spikes: np.ndarray, counts: np.ndarray, out: np.ndarray) -> None:
        """The fused kernel over every column (``spikes`` (N, cap), ``counts`` (N,), ``out`` (N, T) or
        (N, 0): the kernel does no bounds checks). The encoder's large blocks (``lif`` given) run on
        both cores; the currents alone (:func:`encode_population`, whose callers run their own
        processes) stay on the calling thread."""
        n = self.src.size
        if lif is None:  # currents only: the kernel never touches the neuron arrays
            lif = LifPopulation(np.ones(n), np.zeros((n, 1)))
            work = 0
        else:
            work = n * x.shape[0]
        st = lif.state
        split_run(lambda a, b: _encode_columns(x, self.src, self.w, self.i_sat, self.sos, self.has_lp, self.zi, self.hp_sos,
                                               self.has_hp, self.hp_zi, self.lead,
                                               self.ring, self.head, lif.tau, lif.ih, st.v, st.counter, spikes, counts, out, a, b),
                  n, work)

    def process(self, channels: np.ndarray) -> np.ndarray:
        x = self.prepare(channels)
        out = np.empty((self.src.size, x.shape[0]))
        if x.shape[0] and self.src.size:
            self._run(x, None, np.empty((self.src.size, 0), np.int64), np.zeros(self.src.size, np.int64), out)
        return out.T  # (T, N) view; the LIF makes it contiguous

    def spikes(self, channels: np.ndarray, lif: LifPopulation) -> tuple[np.ndarray, np.ndarray]:
        """Run the channels through this stage into ``lif`` (one neuron per column) in one fused
        kernel: the spikes as (sample index within the block, column), ordered by sample then
        column, exactly those of :meth:`process` followed by :meth:`LifPopulation.step`."""
        x = self.prepare(channels)
        n, n_t = self.src.size, x.shape[0]
        cap = n_t // (REFRACTORY_SAMPLES + 1) + 1  # spikes are more than REFRACTORY_SAMPLES apart
        spikes = np.empty((n, cap), np.int64)
        counts = np.zeros(n, np.int64)
        if n_t and n:
            self._run(x, lif, spikes, counts, np.empty((n, 0)))
        if not counts.any():  # most short calls: no spike
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        if counts.max() > cap:
            raise RuntimeError("spike buffer overrun: a column spiked more often than its refractory period allows")
        k = spikes[np.arange(cap)[None, :] < counts[:, None]]
        col = np.repeat(np.arange(n), counts)
        order = np.lexsort((col, k))
        return k[order], col[order]

    def state_arrays(self) -> dict[str, np.ndarray]:
        out = {}
        if self.has_lp.any():
            out["lowpass"] = self.zi[self.has_lp]
        if self.has_hp.any():
            out["highpass"] = self.hp_zi[self.has_hp]
        if self.ring.size:
            out["lead"] = self.ring
        return out


def class_columns(params: Sequence[ClassParams]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M,) tau in samples, (M, 190) post-spike current, (M,) delay in s."""
    tau = np.array([p.tau_samples for p in params], dtype=np.float64)
    ih = np.array([p.ih for p in params], dtype=np.float64).reshape(-1, 2) @ ih_basis()  # (M, 190)
    delay = np.array([p.delay_ms for p in params]) / 1000.0
    return tau, ih, delay


def channel_currents(channels: np.ndarray, params: ClassParams) -> np.ndarray:
    """(T, 4) channels -> (T, 4) weighted pre-saturation current of each channel (eq. 11), after
    the class input filter (the lead only shifts the positive parts in time and is left out)."""
    r = rectify(class_filtered(np.asarray(channels, dtype=np.float64), params.lowpass_hz, params.highpass_hz))  # (T, 8)
    w = np.asarray(params.weights)
    return (r * w).reshape(-1, 4, 2).sum(axis=2)


def encode_population(channels: np.ndarray, t0_s: float, params: Sequence[ClassParams]) -> list[np.ndarray]:
    """Run every parameter set as one neuron on one taxel's (T, 4) channels starting at ``t0_s``.

    Returns one array of spike times (s, recording clock, delay included) per parameter set.
    """
    tau, ih, delay = class_columns(params)
    current = InputStage(params, np.zeros(len(params), np.int64)).process(np.asarray(channels, np.float64)[:, None, :])
    k, n = LifPopulation(tau, ih).step(current)
    order = np.argsort(n, kind="stable")  # group by neuron, keeping time order
    bounds = np.searchsorted(n[order], np.arange(len(params) + 1))
    times = t0_s + (k[order] + 1) / OUT_FS_HZ
    return [times[bounds[j] : bounds[j + 1]] + delay[j] for j in range(len(params))]


@dataclass
class SpikeEvents:
    """Spikes of a block, sorted by time: ``t_s`` (s), ``taxel`` and ``cls`` (index into CLASSES)."""

    t_s: np.ndarray
    taxel: np.ndarray
    cls: np.ndarray

    def __len__(self) -> int:
        return self.t_s.size

    def train(self, cls: str, taxel: int = 0) -> np.ndarray:
        c = CLASSES.index(cls)
        return self.t_s[(self.cls == c) & (self.taxel == taxel)]

    @staticmethod
    def concatenate(parts: Sequence["SpikeEvents"]) -> "SpikeEvents":
        if not parts:
            return SpikeEvents(np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64))
        return SpikeEvents(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("t_s", "taxel", "cls")))


class Encoder:
    """Stateful encoder of N taxels x the selected classes, as one neuron population of *columns*
    (taxel, class); only the active columns are computed.

    ``process(channels)`` takes a :class:`~touchreal.preprocess.pipeline.Channels` block (or the raw
    (T, n_taxels, 4) array with its first grid index) and returns the block's :class:`SpikeEvents`.
    All columns are active at first (or ``columns``, class -> taxels); :meth:`set_columns` changes the set: continuing columns keep
    their state bit-exactly (columns are independent, so a column's spikes do not depend on which
    others run), a (re)started column starts from rest at the next sample it is given (membrane at
    0, no recent spike, class input filter and lead history in steady state at that sample).
    """

    def __init__(self, params: EncoderParams, n_taxels: int = 1, classes: Sequence[str] | None = None,
                 columns: Mapping[str, Iterable[int]] | None = None):
        classes = tuple(classes) if classes is not None else tuple(params.classes)
        missing = [c for c in classes if c not in params.classes]
        if missing:
            raise ValueError(f"parameter set has no class {missing}")
        self.params = params
        self.n_taxels = n_taxels
        self.classes = tuple(c for c in CLASSES if c in classes)
        self.class_index = np.array([CLASSES.index(c) for c in self.classes])
        if columns is None:  # every column
            self._build([(x, c) for x in range(self.n_units) for c in self.classes if self._has(x, c)])
        else:
            self._build(self._column_list(columns))

    def _build(self, columns: list[tuple[int, str]]) -> None:
        """Fresh input stages and neurons for ``columns`` [(taxel, class)], taxel-major."""
        self.columns = columns
        cps = [self._column_params(x, c) for x, c in columns]
        tau, ih, self._delay_n = class_columns(cps)
        self._taxel_n = np.array([x for x, _ in columns], dtype=np.int64)
        self._cls_n = np.array([CLASSES.index(c) for _, c in columns], dtype=np.int64)
        self.inputs = InputStage(cps, self._input_rows())
        self.lif = LifPopulation(tau, ih)

    # -- what a subclass with other units than taxels (a population) changes ------------------------
    @property
    def n_units(self) -> int:
        """Units a column can address (the taxels here)."""
        return self.n_taxels

    def _has(self, unit: int, cls: str) -> bool:
        """A (unit, class) column exists (every taxel has every class)."""
        return True

    def _column_params(self, unit: int, cls: str) -> ClassParams:
        return self.params.classes[cls]

    def _input_rows(self) -> np.ndarray:
        """Per column, its row of the array :meth:`_inputs` returns (the taxel)."""
        return self._taxel_n

    def _inputs(self, data: np.ndarray) -> np.ndarray:
        """(T, n_taxels, 4) channels -> the (T, rows, 4) input the columns read (the channels)."""
        return data

    @property
    def n_columns(self) -> int:
        return len(self.columns)

    def _column_list(self, columns: Mapping[str, Iterable[int]]) -> list[tuple[int, str]]:
        """The (unit, class) columns of ``columns`` (class -> units), unit-major, as :meth:`_build` takes them."""
        want = {c: {int(x) for x in columns.get(c, ())} for c in self.classes}
        bad = sorted({x for xs in want.values() for x in xs if not 0 <= x < self.n_units})
        if bad:
            raise ValueError(f"units {bad} out of range 0..{self.n_units - 1}")
        return sorted(((x, c) for c in self.classes for x in want[c] if self._has(x, c)), key=lambda xc: (xc[0], self.classes.index(xc[1])))

    def set_columns(self, columns: Mapping[str, Iterable[int]]) -> None:
        """Make the given (class -> taxels) the active columns (classes of this encoder only)."""
        unknown = set(columns) - set(self.classes)
        if unknown:
            raise ValueError(f"classes {sorted(unknown)} are not encoded here (have {list(self.classes)})")
        new = self._column_list(columns)
        if new == self.columns:
            return
        old_index = {col: i for i, col in enumerate(self.columns)}
        kept = [(old_index[col], j) for j, col in enumerate(new) if col in old_index]
        old_inputs, old_state = self.inputs, self.lif.state
        self._build(new)
        if kept:
            rows_old, rows_new = (np.array(r, dtype=np.int64) for r in zip(*kept))
            self.inputs.carry(old_inputs, rows_old, rows_new)
            self.lif.state.v[rows_new] = old_state.v[rows_old]
            self.lif.state.counter[rows_new] = old_state.counter[rows_old]

    @staticmethod
    def gather(parts: Sequence[tuple["Encoder", np.ndarray]], columns: Mapping[str, Iterable[int]]) -> "Encoder":
        """One encoder over the taxels ``idx`` of each part, in order, with the active ``columns``
        (class -> taxels of the result): a column its part ran continues bit for bit (its arrays
        gathered, nothing rebuilt from the parameters), the others start from rest (:meth:`set_columns`)."""
        out = copy.copy(parts[0][0])
        out.n_taxels = sum(len(idx) for _, idx in parts)
        rows, taxels, offset = [], [], 0
        for enc, idx in parts:  # each part's columns on the taxels idx, renumbered to their place in the result
            place = np.full(enc.n_taxels, -1, np.int64)
            place[np.asarray(idx, np.int64)] = offset + np.arange(len(idx))
            new = place[enc._taxel_n]
            keep = np.flatnonzero(new >= 0)
            order = keep[np.argsort(new[keep], kind="stable")]  # taxel-major; a taxel's classes keep their order
            rows.append(order)
            taxels.append(new[order])
            offset += len(idx)
        parts_rows = [(enc, r) for (enc, _), r in zip(parts, rows)]
        taxel_n = np.concatenate(taxels)
        out._taxel_n = taxel_n
        out._cls_n = np.concatenate([enc._cls_n[r] for enc, r in parts_rows])
        out._delay_n = np.concatenate([enc._delay_n[r] for enc, r in parts_rows])
        out.columns = list(zip(taxel_n.tolist(), [CLASSES[c] for c in out._cls_n.tolist()]))
        out.inputs = InputStage.gather([(enc.inputs, r) for enc, r in parts_rows], out._input_rows())
        out.lif = LifPopulation.gather([(enc.lif, r) for enc, r in parts_rows])
        out.set_columns(columns)
        return out

    def reset(self) -> None:
        self._build(self.columns)

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Membrane potentials and the input stages' states (class input filter, lead)."""
        return {"lif_v": self.lif.state.v, **{f"input_{k}": a for k, a in self.inputs.state_arrays().items()}}

    def currents(self, data: np.ndarray) -> np.ndarray:
        """(T, n_taxels, 4) channels -> (T, n_columns) input current (advances the states)."""
        return self.inputs.process(self._inputs(data))

    def process(self, channels, k0: int | None = None) -> SpikeEvents:
        data = channels.data if k0 is None else channels
        k0 = channels.k0 if k0 is None else k0
        if data.ndim != 3 or data.shape[1:] != (self.n_taxels, 4):
            raise ValueError(f"channels must be (T, {self.n_taxels}, 4), got {data.shape}")
        if data.shape[0] == 0 or not self.columns:
            return SpikeEvents.concatenate([])
        k, n = self.inputs.spikes(self._inputs(data), self.lif)
        if not k.size:
            return SpikeEvents.concatenate([])
        t = (k0 + k + 1) / OUT_FS_HZ + self._delay_n[n]
        order = np.argsort(t, kind="stable")
        return SpikeEvents(t[order], self._taxel_n[n][order], self._cls_n[n][order])
