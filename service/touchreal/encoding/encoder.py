"""TouchReal encoder: four 5 kHz channels -> SA1/RA/PC-like spikes, TouchSim-style LIF per class.

For afferent class a and channels x_c (ST, dST, PVDF, dPVDF), the input current is

    I_a = sum_c  w_a[2c] * max(x_c, 0) + w_a[2c+1] * max(-x_c, 0)           (w1..w8)
    I_a <- I_sat * I_a / (I_sat + |I_a|)                                       (when I_sat > 0)

which drives the LIF of :mod:`touchreal.encoding.lif` with the class's tau and post-spike current.
A spike at grid sample k is reported at ``(k + 1) / 5000 + delay`` seconds on the recording clock.

:class:`Encoder` is stateful and handles N taxels x the selected classes as one neuron population;
``encode_population`` runs many parameter sets on one taxel's channels at once (used by fitting).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np

from ..params import ClassParams, EncoderParams
from ..settings import CLASSES, OUT_FS_HZ, PACKAGE_DATA
from .lif import LifPopulation


@lru_cache(maxsize=1)
def ih_basis() -> np.ndarray:
    """TouchSim's two post-spike current basis functions, (2, 190) at 5 kHz."""
    data = json.loads((PACKAGE_DATA / "touchsim_constants.json").read_text())
    return np.asarray(data["ihbasis"], dtype=np.float64)


def rectify(channels: np.ndarray) -> np.ndarray:
    """(..., 4) channels -> (..., 8) [max(x,0), max(-x,0)] per channel, in w1..w8 order."""
    pos = np.maximum(channels, 0.0)
    neg = np.maximum(-channels, 0.0)
    return np.stack((pos, neg), axis=-1).reshape(*channels.shape[:-1], 8)


@numba.njit(cache=True, nogil=True)
def _current(channels, w, i_sat, out):  # pragma: no cover - compiled
    """out[k, x * C + c] = sat_c(sum_j w[2j, c] max(ch[k, x, j], 0) + w[2j+1, c] max(-ch[k, x, j], 0))."""
    n_t, n_x, n_ch = channels.shape
    n_c = w.shape[1]
    for k in range(n_t):
        for x in range(n_x):
            for c in range(n_c):
                acc = 0.0
                for j in range(n_ch):
                    v = channels[k, x, j]
                    if v > 0.0:
                        acc += w[2 * j, c] * v
                    elif v < 0.0:
                        acc -= w[2 * j + 1, c] * v
                s = i_sat[c]
                if s > 0.0:
                    acc = s * acc / (s + abs(acc))
                out[k, x * n_c + c] = acc


def input_current(channels: np.ndarray, w: np.ndarray, i_sat: np.ndarray) -> np.ndarray:
    """(T, X, 4) channels, (8, C) weights, (C,) saturation -> (T, X * C) saturated input current.

    ``I_sat * I / (I_sat + |I|)`` where ``I_sat > 0`` (TouchSim's saturation); input must be finite.
    """
    channels = np.ascontiguousarray(channels, dtype=np.float64)
    out = np.empty((channels.shape[0], channels.shape[1] * w.shape[1]))
    _current(channels, np.ascontiguousarray(w, dtype=np.float64), np.ascontiguousarray(i_sat, dtype=np.float64), out)
    return out


def class_columns(params: Sequence[ClassParams]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(8, M) weights, (M,) i_sat, (M,) tau in samples, (M, 190) post-spike current, (M,) delay in s."""
    w = np.array([p.weights for p in params], dtype=np.float64).T  # (8, M)
    i_sat = np.array([p.i_sat for p in params])
    tau = np.array([p.tau_samples for p in params])
    ih = np.array([p.ih for p in params]) @ ih_basis()  # (M, 190)
    delay = np.array([p.delay_ms for p in params]) / 1000.0
    return w, i_sat, tau, ih, delay


def channel_currents(channels: np.ndarray, params: ClassParams) -> np.ndarray:
    """(T, 4) channels -> (T, 4) weighted pre-saturation current of each channel (eq. 11)."""
    r = rectify(np.asarray(channels, dtype=np.float64))  # (T, 8)
    w = np.asarray(params.weights)
    return (r * w).reshape(-1, 4, 2).sum(axis=2)


def encode_population(channels: np.ndarray, t0_s: float, params: Sequence[ClassParams]) -> list[np.ndarray]:
    """Run every parameter set as one neuron on one taxel's (T, 4) channels starting at ``t0_s``.

    Returns one array of spike times (s, recording clock, delay included) per parameter set.
    """
    w, i_sat, tau, ih, delay = class_columns(params)
    current = input_current(np.asarray(channels)[:, None, :], w, i_sat)
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
    """Stateful encoder of N taxels x the selected classes (only those are computed).

    ``process(channels)`` takes a :class:`~touchreal.preprocess.pipeline.Channels` block (or the raw
    (T, n_taxels, 4) array with its first grid index) and returns the block's :class:`SpikeEvents`.
    """

    def __init__(self, params: EncoderParams, n_taxels: int = 1, classes: Sequence[str] | None = None):
        classes = tuple(classes) if classes is not None else tuple(params.classes)
        missing = [c for c in classes if c not in params.classes]
        if missing:
            raise ValueError(f"parameter set has no class {missing}")
        self.params = params
        self.n_taxels = n_taxels
        self.classes = tuple(c for c in CLASSES if c in classes)
        self.class_index = np.array([CLASSES.index(c) for c in self.classes])
        w, self.i_sat, tau, ih, self.delay = class_columns([params.classes[c] for c in self.classes])
        self.w = w  # (8, n_classes)
        # neuron j = taxel * n_classes + class
        n_cls = len(self.classes)
        self.lif = LifPopulation(np.tile(tau, n_taxels), np.tile(ih, (n_taxels, 1)))
        self._delay_n = np.tile(self.delay, n_taxels)
        self._taxel_n = np.repeat(np.arange(n_taxels), n_cls)
        self._cls_n = np.tile(self.class_index, n_taxels)

    def reset(self) -> None:
        self.lif.reset()

    def currents(self, data: np.ndarray) -> np.ndarray:
        """(T, n_taxels, 4) channels -> (T, n_taxels * n_classes) saturated input current."""
        return input_current(data, self.w, self.i_sat)

    def process(self, channels, k0: int | None = None) -> SpikeEvents:
        data = channels.data if k0 is None else channels
        k0 = channels.k0 if k0 is None else k0
        if data.ndim != 3 or data.shape[1:] != (self.n_taxels, 4):
            raise ValueError(f"channels must be (T, {self.n_taxels}, 4), got {data.shape}")
        if data.shape[0] == 0 or not self.classes:
            return SpikeEvents.concatenate([])
        k, n = self.lif.step(self.currents(data))
        t = (k0 + k + 1) / OUT_FS_HZ + self._delay_n[n]
        order = np.argsort(t, kind="stable")
        return SpikeEvents(t[order], self._taxel_n[n][order], self._cls_n[n][order])
