"""Per-class latency of a parameter set: when a spike leaves the online chain, against its stamp.

Two figures per class (ms):

* ``algorithmic``: the online chain's own bound on the time from a sensor sample to the emission
  of what it caused (:attr:`~touchreal.stream.StreamEncoder.latency_s`: the look-ahead of the
  class's source, its causal PVDF window or the SingleTact interpolation alone). A spike's stamp is
  that sample's time plus the class delay (>= 0), so ``emission - stamp`` is at most
  ``algorithmic - delay``.
* ``measured``: median (and 90th percentile) of ``emission - stamp`` over real spikes, with a
  recording replayed through the :class:`~touchreal.stream.StreamEncoder` in small chunks; a spike's
  emission time is the end of the chunk whose processing returned it (recording clock, compute time
  not included: the chain is sans-I/O).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..params import EncoderParams
from ..recording import Trial
from ..sources.replay import ReplaySource
from ..settings import CLASSES
from ..stream import StreamEncoder

MEASURE_CHUNK_S = 0.001  #: replay chunk of the measured latency (a live sensor's finest update)


def algorithmic_latency_s(params: EncoderParams) -> dict[str, float]:
    """Per class: sample-to-emission latency (s) of the online chain, the
    :attr:`StreamEncoder.latency_s` of the class's source (its window, or the SingleTact alone)."""
    return {c: float(v) for c, v in StreamEncoder(params).latency_s.items()}


def measured_latency_s(params: EncoderParams, trials: Sequence[Trial], chunk_s: float = MEASURE_CHUNK_S) -> dict[str, np.ndarray]:
    """Per class: ``emission - stamp`` (s) of every spike of ``trials`` replayed in ``chunk_s`` chunks."""
    out: dict[str, list[np.ndarray]] = {c: [] for c in params.classes}
    for trial in trials:
        src = ReplaySource(trial)
        se = StreamEncoder(params)
        while not src.done:
            ev = se.process(src.read(chunk_s))
            for c in params.classes:
                t = ev.train(c)
                if t.size:
                    out[c].append(src.now_s - t)
        ev = se.finish()  # the tail is emitted at the end of the stream
        for c in params.classes:
            t = ev.train(c)
            if t.size:
                out[c].append(src.now_s - t)
    return {c: np.concatenate(v) if v else np.zeros(0) for c, v in out.items()}


def latency_table(params: EncoderParams, trials: Sequence[Trial] = (), chunk_s: float = MEASURE_CHUNK_S) -> dict[str, dict[str, float | int | None]]:
    """Per class (ms): window, delay, algorithmic latency, its bound on ``emission - stamp`` and,
    with ``trials``, the measured median / 90th percentile of ``emission - stamp``, the median time
    from the causing sample to the emission (``emission - stamp + delay``) and the spike count."""
    alg = algorithmic_latency_s(params)
    meas = measured_latency_s(params, trials, chunk_s) if trials else {}
    out: dict[str, dict[str, float | int | None]] = {}
    for c in (c for c in CLASSES if c in params.classes):
        d = params.classes[c].delay_ms
        row: dict[str, float | int | None] = {
            "window_ms": float(params.window_ms(c)),
            "delay_ms": float(d),
            "algorithmic_ms": 1000.0 * alg[c],
            "bound_emission_minus_stamp_ms": 1000.0 * alg[c] - d,
        }
        if trials:
            m = meas[c]
            row.update(
                measured_median_ms=float(1000.0 * np.median(m)) if m.size else None,
                measured_median_after_sample_ms=float(1000.0 * np.median(m) + d) if m.size else None,
                measured_p90_ms=float(1000.0 * np.percentile(m, 90)) if m.size else None,
                measured_spikes=int(m.size),
                measured_chunk_ms=1000.0 * chunk_s,
            )
        out[c] = row
    return out
