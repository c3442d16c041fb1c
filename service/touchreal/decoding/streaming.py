"""Streaming decoder: spike events in, one decoded output per 32 ms step out (sans I/O).

The service calls :meth:`StreamingDecoder.push` once per update from its acquisition thread. The
binning and alignment are :class:`touchreal_client.features.StreamBinner`, the same object a
client runs next to its own onnxruntime session, so the service's and a client's outputs agree,
and both equal the offline windows of a recorded trial exactly (tests/test_decoding_streaming.py).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from touchreal_client.features import StreamBinner

from .model import DecoderModel


class StreamingDecoder:
    """Sliding-window decoding of one model for a set of taxels, one onnxruntime session.

    Steps are the absolute grid ``T = k * step_us`` of the sensor clock (32 ms). Step ``T`` is
    decoded once every class the model reads is complete up to ``T`` (``final_us[c] >= T``), from
    the spikes with ``t < T``; all taxels go through one inference call (batch = taxels).

    * Force models: the window is ``[T - window, T)`` in 10 ms bins counted back from ``T``;
      outputs ``["force_N"]``. A stateful model (metadata ``state``; window = step) also carries
      its filtered counts per taxel from step to step, from zeros at the decoder's first step.
    * Texture models (metadata alignment ``first spike after silence``): per taxel, a PC spike
      after at least 500 ms without one - or the first PC spike seen - is an anchor; the 500 ms
      window is anchored at the latest anchor before ``T`` (bins on ``anchor + j * 10 ms``, ending
      at the last such edge ``<= T``) and slides along it while the touch goes on. A taxel with
      no anchor yet or a window not yet filled outputs NaN. Outputs: one probability per label
      (``output_names``); the predicted label is their argmax.
    * Scanning texture models (metadata ``context``: input ``speed_mm_s``): the window is
      ``[T - window, T)`` as for force, and the caller passes the scanning speed (mm/s) with each
      :meth:`push`: one number for every taxel or one per taxel, the speed over the windows of the
      steps that push completes. Rows whose speed is missing, not finite or not > 0 (no scanning)
      output NaN; so does every row of a push without ``speed_mm_s``.

    ``start_us``: the first step is the first grid point at or after it; None = at or after the
    completeness time of the first :meth:`push` (earlier steps would lack their history).
    Spikes of taxels not in ``taxels`` and of classes the model does not read are ignored.
    """

    def __init__(self, model: DecoderModel, taxels: Sequence[int], threads: int = 1, start_us: int | None = None,
                 session=None):
        self.model = model
        self.binner = StreamBinner.from_metadata(model.meta, taxels, start_us)
        self.taxels = self.binner.taxels
        #: the model's onnxruntime session: ``session`` if given (one kept across decoders of the same model)
        self._session = session if session is not None else model.session(threads)
        self._state = model.initial_state(self.taxels.size)

    @property
    def output_names(self) -> list[str]:
        """Names of the output columns: ``["force_N"]`` or the texture labels (probabilities)."""
        return list(self.model.meta["output_names"])

    def push(
        self, t_us: np.ndarray, taxel: np.ndarray, cls: np.ndarray, final_us: dict[str, int],
        speed_mm_s: float | np.ndarray | None = None,
    ) -> list[tuple[int, np.ndarray]]:
        """Add the spike events of one update (sensor clock, us; ``cls`` indexes SA1, RA, PC);
        return ``(T, values (n_taxels, n_outputs) float32)`` for every step it completes, in time
        order, rows in the order of ``taxels``. ``speed_mm_s``: the scanning speed (mm/s) of these
        steps for a model that reads it (scalar or per taxel); other models ignore it."""
        speed, scanning = self._speed(speed_mm_s)
        out = []
        for step, counts, filled in self.binner.push(t_us, taxel, cls, final_us):
            filled = filled & scanning
            values, state = self.model.run(self._session, counts, self._state, speed)  # stateless / no speed: ignored
            if state is not None:
                self._state = state
            values = np.asarray(values, dtype=np.float32).reshape(counts.shape[0], -1)
            values[~filled] = np.nan
            out.append((step, values))
        return out

    def _speed(self, speed_mm_s: float | np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray]:
        """(speed fed to the model or None, rows scanning (n_taxels,) bool). One speed for every row
        goes in as ``(1, 1)``: the graph then computes its phases once, not once per taxel."""
        n = self.taxels.size
        if not self.model.needs_speed:
            return None, np.ones(n, bool)
        v = np.full(n, np.nan) if speed_mm_s is None else np.broadcast_to(np.asarray(speed_mm_s, np.float64).reshape(-1), (n,))
        scanning = np.isfinite(v) & (v > 0)
        rows = np.where(scanning, v, v[scanning][0] if scanning.any() else 1.0).astype(np.float32).reshape(n, 1)
        return (rows[:1] if np.all(rows == rows[0]) else rows), scanning
