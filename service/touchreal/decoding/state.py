"""Decoder state carried across steps: exponentially filtered spike counts per class.

A stateful decoder sees a short window (its step, e.g. 32 ms) and, beside it, for every class and
every time constant ``tau`` the causal exponential filter of its spike counts, updated once per
step ``dt``::

    state_out = exp(-dt / tau) * state + (spikes of the class in the step's window)

The window equals the step, so every spike enters the state exactly once. ``state`` is zero before
the first step. The same update runs in numpy (training, :meth:`ExpFilter.sequence`) and as ONNX
operators inside the exported graph (:meth:`ExpFilter.nodes`: the graph takes ``state`` and
returns ``state_out``, which the caller feeds back at the next step), so a client running the file
gets the server's numbers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from onnx import NodeProto, TensorProto, ValueInfoProto, helper, numpy_helper

STATE_INPUT = "state"
STATE_OUTPUT = "state_out"


def step_index(groups: np.ndarray) -> np.ndarray:
    """Index of every row within its run of equal ``groups`` (0 at each trial's first step)."""
    g = np.asarray(groups)
    if g.size == 0:
        return np.zeros(0, int)
    new = np.concatenate(([True], g[1:] != g[:-1]))
    return np.arange(g.size) - np.maximum.accumulate(np.where(new, np.arange(g.size), 0))


@dataclass(frozen=True)
class ExpFilter:
    """Filtered counts of ``n_classes`` classes at time constants ``taus_ms``, one update per ``step_ms``.

    State layout: class-major, ``[c0 tau0, c0 tau1, ..., c1 tau0, ...]`` (spikes per ``tau`` of
    recent history, dimensionless counts).
    """

    taus_ms: tuple[float, ...]
    step_ms: float
    n_bins: int
    n_classes: int

    def __post_init__(self) -> None:
        if not self.taus_ms or min(self.taus_ms) <= 0 or self.step_ms <= 0:
            raise ValueError("time constants and the step must be positive (and at least one time constant)")

    @property
    def size(self) -> int:
        return self.n_classes * len(self.taus_ms)

    def names(self, classes: Sequence[str]) -> list[str]:
        return [f"ewma[{c}][tau{t:g}ms]" for c in classes for t in self.taus_ms]

    def decay(self) -> np.ndarray:
        """(size,) float32: ``exp(-step / tau)`` per state entry."""
        return np.tile(np.exp(-self.step_ms / np.asarray(self.taus_ms, float)), self.n_classes).astype(np.float32)

    def gather(self) -> np.ndarray:
        """(n_bins * n_classes, size) float32 of 0/1: flattened counts -> each entry's class total."""
        g = np.zeros((self.n_bins * self.n_classes, self.size), np.float32)
        for b in range(self.n_bins):
            for c in range(self.n_classes):
                g[b * self.n_classes + c, c * len(self.taus_ms):(c + 1) * len(self.taus_ms)] = 1.0
        return g

    def update(self, state: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """One step in numpy: ``(batch, size)`` state and ``(batch, n_bins, n_classes)`` counts -> state_out."""
        flat = np.asarray(counts, np.float32).reshape(counts.shape[0], -1)
        return np.asarray(state, np.float32) * self.decay() + flat @ self.gather()

    def sequence(self, counts: np.ndarray, groups: np.ndarray) -> np.ndarray:
        """state_out of every window of consecutive steps; the state restarts at zero where ``groups``
        (trial index, windows of a trial contiguous and in step order) changes."""
        pos = step_index(groups)
        out = np.zeros((pos.size, self.size), np.float32)
        for k in range(int(pos.max()) + 1 if pos.size else 0):  # one step of every trial at a time
            rows = np.flatnonzero(pos == k)
            prev = out[rows - 1] if k else np.zeros((rows.size, self.size), np.float32)
            out[rows] = self.update(prev, counts[rows])
        return out

    def nodes(self, flat: str, prefix: str = "") -> tuple[list[NodeProto], list[TensorProto]]:
        """ONNX nodes ``(flat counts, STATE_INPUT) -> STATE_OUTPUT`` (default-domain MatMul, Mul, Add)."""
        decay = numpy_helper.from_array(self.decay()[None, :], f"{prefix}decay")
        gather = numpy_helper.from_array(self.gather(), f"{prefix}gather")
        nodes = [
            helper.make_node("MatMul", [flat, gather.name], [f"{prefix}new_counts"]),
            helper.make_node("Mul", [STATE_INPUT, decay.name], [f"{prefix}decayed"]),
            helper.make_node("Add", [f"{prefix}decayed", f"{prefix}new_counts"], [STATE_OUTPUT]),
        ]
        return nodes, [decay, gather]

    def value_info(self, name: str) -> ValueInfoProto:
        """Graph input/output declaration of a ``(batch, size)`` float32 state."""
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, [None, self.size])
