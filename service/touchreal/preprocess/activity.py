"""Which taxels a scene touches: a cheap detector on the raw samples (sans-I/O).

A taxel whose raw SingleTact and PVDF samples stay inside its noise band around its baseline
does not need the expensive stages (filters, STFT gate, PCHIP, class input, LIF): the
:class:`~touchreal.stream.StreamEncoder` stops a taxel block all of whose taxels have been quiet for
:attr:`ActivityPlan.hold_s`, and starts it again, rebuilt from the raw history, on the first chunk
in which one of them leaves its band (before that chunk is processed, so the contact's first
samples go through the whole chain).

Per taxel and sensor the detector keeps a *baseline* and a *noise scale*, both learned online:

* a chunk is *out of band* for a taxel when the largest deviation of its samples from the
  baseline exceeds ``k_noise`` times the noise scale plus the sensor's quantisation floor
  (two ADC steps: no build has less noise than its converter);
* on quiet chunks the baseline follows the chunk's mean; the noise scale follows the chunk's
  largest deviation, quickly down and slowly up (a high quantile of the quiet deviations, which a
  contact barely moves), so slow drift and a build's noise (and mains hum) are learned, never
  configured per build;
* on loud chunks the baseline still follows, ``drift_tau_s`` slowly: a taxel left under a
  constant load (or a sensor stuck at a new level) settles and sleeps again.

Non-finite samples (the input policy repairs them downstream) are skipped and counted
(``non_finite``); a taxel whose samples are all identical over a chunk of several samples is
counted ``stuck`` (a real sensor always shows some noise) and stays asleep unless it moves.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..raw import RawChunk
from ..settings import PVDF_RANGE_V, ST_RESOLUTION_N

_PVDF_ADC_STEP_V = (PVDF_RANGE_V[1] - PVDF_RANGE_V[0]) / 4096.0  #: the 12-bit PVDF converter's step
_STUCK_MIN_SAMPLES = 8  #: a chunk needs this many PVDF samples for "all identical" to mean stuck


@dataclass(frozen=True)
class ActivityPlan:
    """How the detector decides (printable, overridable, recorded; times in s)."""

    k_noise: float = 2.5  #: out of band: deviation > k_noise x noise scale + floor
    hold_s: float = 1.0  #: a block sleeps once all its taxels have been in band this long
    baseline_tau_s: float = 0.5  #: the baseline's time constant on quiet chunks
    noise_tau_s: float = 2.0  #: the noise scale's time constant towards smaller deviations (and while learning)
    noise_rise_tau_s: float = 60.0  #: its time constant towards larger deviations once learned
    drift_tau_s: float = 5.0  #: the baseline's time constant on loud chunks (constant load, drift)
    st_floor_n: float = 2 * ST_RESOLUTION_N  #: SingleTact floor: two quantisation steps (N)
    pvdf_floor_v: float = 2 * _PVDF_ADC_STEP_V  #: PVDF floor: two ADC steps (V)

    def describe(self) -> dict[str, float]:
        return asdict(self)


class _Band:
    """Baseline and noise scale of one sensor for every taxel."""

    def __init__(self, n_taxels: int, floor: float):
        self.floor = floor
        self.base = np.zeros(n_taxels)
        self.scale = np.zeros(n_taxels)
        self.known = np.zeros(n_taxels, bool)  #: a taxel's band is learned from its first finite chunk
        self.seen = np.zeros(n_taxels)  #: fraction of the learning time (``noise_tau_s``) seen so far

    def out(self, x: np.ndarray, k_noise: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(out of band (N,), chunk mean (N,), largest deviation (N,)) of samples ``x`` (n, N); NaN ignored."""
        with np.errstate(invalid="ignore"):
            finite = np.isfinite(x)
            has = finite.any(axis=0)
            xs = np.where(finite, x, 0.0)
            mean = xs.sum(axis=0) / np.maximum(finite.sum(axis=0), 1)
            new = has & ~self.known
            self.base[new], self.known[new] = mean[new], True
            dev = np.where(finite, np.abs(x - self.base), 0.0).max(axis=0)
            self.scale[new] = dev[new]  # a first chunk under contact only starts the scale high; quiet chunks lower it
        return has & (dev > k_noise * self.scale + self.floor), mean, dev

    def follow(self, quiet: np.ndarray, mean: np.ndarray, dev: np.ndarray, a_base: float, a_drift: float,
               a_fall: float, a_rise: float) -> None:
        """Quiet taxels' baseline follows the chunk mean, loud ones' drifts slowly; the noise scale falls
        towards a smaller deviation at ``a_fall`` and rises towards a larger one at ``a_rise`` (both fast
        while the taxel is still being learned), so it settles at a high quantile of the quiet deviations
        and a contact barely moves it."""
        self.base += np.where(quiet, a_base, a_drift) * (mean - self.base)
        learning = self.seen < 1.0
        up = dev > self.scale
        self.scale += np.where(learning, a_fall, np.where(up, a_rise, a_fall)) * (dev - self.scale)


class ActivityDetector:
    """Per-taxel activity of N taxels, chunk by chunk: :meth:`push` returns the taxels awake after it."""

    def __init__(self, n_taxels: int, plan: ActivityPlan | None = None):
        self.plan = plan or ActivityPlan()
        self.n_taxels = n_taxels
        self._st = _Band(n_taxels, self.plan.st_floor_n)
        self._pv = _Band(n_taxels, self.plan.pvdf_floor_v)
        self.last_out_s = np.full(n_taxels, -np.inf)  #: sensor time (s) of each taxel's latest loud chunk
        self.counters = {"wakes": 0, "non_finite": 0}  #: taxel wake-ups; non-finite raw samples seen
        self.stuck = 0  #: taxels whose PVDF samples were all identical in the latest chunk

    def push(self, chunk: RawChunk) -> np.ndarray:
        """Learn from the chunk's raw samples; the (N,) mask of taxels awake: loud in this chunk or
        within ``hold_s`` of their latest loud chunk (sensor clock)."""
        p = self.plan
        ends = [a[-1] for a in (chunk.st_t, chunk.pvdf_t) if a.size]
        if not ends:
            return self.last_out_s > -np.inf
        now = float(max(ends))
        loud = np.zeros(self.n_taxels, bool)
        span = chunk.pvdf_t.size / 2000.0 if chunk.pvdf_t.size else chunk.st_t.size / 100.0
        rates = [min(1.0, span / tau) for tau in (p.baseline_tau_s, p.drift_tau_s, p.noise_tau_s, p.noise_rise_tau_s)]
        for band, x in ((self._st, chunk.st), (self._pv, chunk.pvdf)):
            if x.shape[0] == 0:
                continue
            out, mean, dev = band.out(x, p.k_noise)
            band.follow(~out, mean, dev, *rates)
            band.seen += span / p.noise_tau_s
            loud |= out
        bad = ~np.isfinite(chunk.pvdf)
        if bad.any():
            self.counters["non_finite"] += int(bad.sum()) + int((~np.isfinite(chunk.st)).sum())
        if chunk.pvdf.shape[0] >= _STUCK_MIN_SAMPLES:
            self.stuck = int((np.ptp(chunk.pvdf, axis=0) == 0).sum())
        awake_before = self.last_out_s >= now - p.hold_s - span
        self.counters["wakes"] += int((loud & ~awake_before).sum())
        self.last_out_s[loud] = now
        return self.last_out_s >= now - p.hold_s
