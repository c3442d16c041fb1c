"""Stateful leaky integrate-and-fire kernel with TouchSim's post-spike current and refractory rule.

One kernel serves both the TouchReal encoder and the TouchSim reference model. For every 5 kHz
sample k and neuron n (input current already weighted and saturated):

    V[k] = V[k-1] - V[k-1] / tau + I[k] + ih[c]      (ih[c] only while c < len(ih); then c += 1)
    spike at k  if  V[k] > threshold  and  c > REFRACTORY_SAMPLES;  then V[k] = reset, c = 0

``c`` counts samples since the last spike (it starts "long ago", i.e. at len(ih)), so spikes are at
least REFRACTORY_SAMPLES + 1 samples (1.2 ms at 5 kHz) apart and the post-spike current ``ih``
(sum of the two basis functions weighted per neuron) is injected after every spike.

State lives in :class:`LifState`, so feeding a current in chunks of any size gives exactly the
same spikes as feeding it whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

REFRACTORY_SAMPLES = 5
THRESHOLD = 1.0
RESET = 0.0


@numba.njit(cache=True, nogil=True)
def _lif_run(current, tau, ih, v, counter, out_t, out_n):  # pragma: no cover - compiled
    n_samples, n_neurons = current.shape
    nh = ih.shape[1]
    n_spikes = 0
    for k in range(n_samples):
        for n in range(n_neurons):
            vk = v[n] - v[n] / tau[n] + current[k, n]
            c = counter[n]
            if c < nh:
                vk += ih[n, c]
                c += 1
            if vk > THRESHOLD and c > REFRACTORY_SAMPLES:
                vk = RESET
                c = 0
                if n_spikes < out_t.shape[0]:
                    out_t[n_spikes] = k
                    out_n[n_spikes] = n
                n_spikes += 1
            v[n] = vk
            counter[n] = c
    return n_spikes


@dataclass
class LifState:
    """Membrane potential and samples-since-spike counter of N neurons."""

    v: np.ndarray  # (N,) float64, dimensionless (threshold 1)
    counter: np.ndarray  # (N,) int64, samples since the last spike

    @classmethod
    def rest(cls, n_neurons: int, ih_len: int) -> "LifState":
        return cls(np.zeros(n_neurons), np.full(n_neurons, ih_len, dtype=np.int64))

    def copy(self) -> "LifState":
        return LifState(self.v.copy(), self.counter.copy())


class LifPopulation:
    """N independent LIF neurons with per-neuron tau (samples) and post-spike current (N, L).

    ``step(current)`` takes a (T, N) float64 current chunk at 5 kHz and returns the spikes as
    (sample index within the chunk, neuron index) arrays, ordered by time.
    """

    def __init__(self, tau_samples: np.ndarray, ih: np.ndarray):
        tau = np.ascontiguousarray(tau_samples, dtype=np.float64).ravel()
        ih = np.ascontiguousarray(np.atleast_2d(ih), dtype=np.float64)
        if ih.shape[0] != tau.size:
            raise ValueError(f"ih has {ih.shape[0]} rows for {tau.size} neurons")
        if not np.all(np.isfinite(tau)) or np.any(tau < 1.0):
            raise ValueError("tau must be finite and >= 1 sample")
        if not np.all(np.isfinite(ih)):
            raise ValueError("post-spike current must be finite")
        self.tau = tau
        self.ih = ih
        self.state = LifState.rest(tau.size, ih.shape[1])

    @staticmethod
    def gather(parts: "list[tuple[LifPopulation, np.ndarray]]") -> "LifPopulation":
        """The neurons ``rows`` of each part, in order (parameters and state copied)."""
        out = LifPopulation.__new__(LifPopulation)
        out.tau = np.concatenate([p.tau[r] for p, r in parts])
        out.ih = np.concatenate([p.ih[r] for p, r in parts])
        out.state = LifState(np.concatenate([p.state.v[r] for p, r in parts]), np.concatenate([p.state.counter[r] for p, r in parts]))
        return out

    @property
    def n_neurons(self) -> int:
        return self.tau.size

    def reset(self) -> None:
        self.state = LifState.rest(self.n_neurons, self.ih.shape[1])

    def step(self, current: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        current = np.ascontiguousarray(current, dtype=np.float64)
        if current.ndim != 2 or current.shape[1] != self.n_neurons:
            raise ValueError(f"current must be (T, {self.n_neurons}), got {current.shape}")
        # Upper bound: one spike per refractory period per neuron; grow only if exceeded.
        cap = current.shape[0] * self.n_neurons // (REFRACTORY_SAMPLES + 1) + self.n_neurons
        out_t = np.empty(cap, dtype=np.int64)
        out_n = np.empty(cap, dtype=np.int64)
        s = self.state
        n = _lif_run(current, self.tau, self.ih, s.v, s.counter, out_t, out_n)
        return out_t[:n], out_n[:n]

