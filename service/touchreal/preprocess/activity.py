"""Which taxels a scene touches: a cheap detector on the raw samples (sans-I/O).

A taxel whose raw SingleTact and PVDF samples stay inside its noise band around its baseline
does not need the expensive stages (filters, STFT gate, PCHIP, class input, LIF): the
:class:`~touchreal.stream.StreamEncoder` stops a taxel block all of whose taxels have been quiet for
:attr:`ActivityPlan.hold_s`, and starts it again, rebuilt from the raw history, on the first chunk
in which one of them leaves its band (before that chunk is processed, so the contact's first
samples go through the whole chain).

Per taxel and sensor the detector keeps a *baseline* and a *noise level*, both learned online:

* a chunk is *out of band* for a taxel when the largest deviation of its samples from the
  baseline exceeds ``k_noise`` times the noise level (the rms deviation of quiet samples) plus
  the sensor's quantisation floor (two ADC steps: no build has less noise than its converter).
  At 5 x rms, Gaussian noise leaves the band about once per 1.7 million samples (once per
  15 minutes per taxel at 2 kHz), and mains hum of any amplitude never does (its peak is
  sqrt(2) x its rms);
* a sustained vibration too small for that (the class stages see it through the STFT gate's
  narrow bins) raises the mean square of the PVDF high-passed at 20 Hz (drift and baseline
  removed) over the last ``energy_tau_s``: above ``energy_ratio`` x the noise's, the chunk is out
  of band too;
* a new taxel (the stream's start) is judged once it has learned its noise for a quarter of
  ``noise_tau_s`` (0.5 s): until then it is awake and every chunk teaches its noise level, from
  then on only quiet ones;
* on quiet chunks the baseline follows the chunk's mean and the noise level the chunk's mean
  square deviation (a loud chunk never moves the level, nor a quiet one whose mean square is
  beyond ``teach_ratio`` x the level's: a slow press the baseline lags stays out of it), so slow
  drift and a build's noise and hum are learned, never configured per build;
* on loud chunks the baseline still follows, ``drift_tau_s`` slowly: a taxel left under a
  constant load (or a sensor stuck at a new level) settles and sleeps again. The deviation is
  tested around the baseline and around the *resting level* (which follows only chunks in band
  around it: slow drift, not a load); a chunk must leave both, so a taxel let go, back at its
  resting level, sleeps after ``hold_s`` instead of waiting for the drifted baseline to return.

Non-finite samples (the input policy repairs them downstream) are skipped and counted
(``non_finite``); a taxel whose samples are all identical over a chunk of several samples is
counted ``stuck`` (a real sensor always shows some noise) and stays asleep unless it moves.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numba
import numpy as np
from scipy.signal import butter, sosfilt_zi

from ..raw import RawChunk
from ..settings import PVDF_FS_HZ, PVDF_RANGE_V, ST_FS_HZ, ST_RESOLUTION_N
from .filters import sos_step

_PVDF_ADC_STEP_V = (PVDF_RANGE_V[1] - PVDF_RANGE_V[0]) / 4096.0  #: the 12-bit PVDF converter's step
_JUDGED_AFTER = 0.25  #: a new taxel is judged once it has learned its noise for this fraction of noise_tau_s
_STUCK_MIN_SAMPLES = 8  #: a chunk needs this many PVDF samples for "all identical" to mean stuck
#: the vibration test's high-pass: 2nd-order Butterworth at 20 Hz on the 2 kHz PVDF (drift and baseline out)
_HP_SOS = butter(2, 20.0, "highpass", fs=2000.0, output="sos")
_HP_ZI = sosfilt_zi(_HP_SOS)


@dataclass(frozen=True)
class ActivityPlan:
    """How the detector decides (printable, overridable, recorded; times in s)."""

    k_noise: float = 5.0  #: out of band: a deviation > k_noise x the noise level (rms) + floor
    #: a judged taxel's quiet chunk teaches its noise level only while its mean square deviation is within this x
    #: the level's (3 x the rms: Gaussian noise passes 99.7 % of single samples, a lagged slow press soon does not)
    teach_ratio: float = 9.0
    energy_ratio: float = 1.8  #: out of band: the PVDF's recent high-passed mean square > this x the noise's
    energy_tau_s: float = 0.02  #: "recent": about 40 PVDF samples (the ratio's noise sd ~0.22: 1.8 is 3.6 sd)
    #: a taxel sleeps once it has been in band this long (and spiked no more): at least, as the stream
    #: encoder lengthens it to its chain's memory (:func:`touchreal.stream.chain_memory_s`; 0.33 s for the shipped parameters)
    hold_s: float = 1.0
    baseline_tau_s: float = 0.5  #: the baseline's time constant on quiet chunks
    noise_tau_s: float = 2.0  #: the noise level's time constant (and how long a new taxel learns from every chunk)
    drift_tau_s: float = 5.0  #: the baseline's time constant on loud chunks (constant load, drift)
    st_floor_n: float = 2 * ST_RESOLUTION_N  #: SingleTact floor: two quantisation steps (N)
    pvdf_floor_v: float = 2 * _PVDF_ADC_STEP_V  #: PVDF floor: two ADC steps (V)

    def describe(self) -> dict[str, float]:
        return asdict(self)


@numba.njit(cache=True, nogil=True)
def _band_kernel(x, base, rest, var, known, seen, recent, hp_var, zi, last_x, sos, energy_ratio, a_recent, k_noise, floor,
                 a_base, a_drift, a_noise, learned, teach, stuck_min, out):  # pragma: no cover - compiled
    """One chunk ``x`` (n, N) through a :class:`_Band`'s test and learning, state in place; ``out`` (N,)
    gets the out-of-band verdicts. Returns (non-finite samples, taxels stuck: all ``n`` >= ``stuck_min``
    samples identical; 0 for shorter chunks). Per taxel: the chunk's finite samples give its mean, the mean
    square and peak of their deviation from the baseline, the peak of their deviation from the resting
    level (which follows only chunks in band around it), and (``energy_ratio`` > 0) the mean square
    of their high-pass (a non-finite sample stands in as the previous chunk's newest sample); then
    the baseline and noise levels follow (:meth:`_Band.step`). A taxel without a finite sample
    keeps its state."""
    n, m = x.shape
    finite = True  # the common case: the per-sample tests below fold away (a quarter less CPU, measured)
    for k in range(n):
        for i in range(m):
            finite &= np.isfinite(x[k, i])
    cnt = np.zeros(m)
    total = np.zeros(m)
    moved = np.zeros(m, np.bool_)
    for k in range(n):
        for i in range(m):
            v = x[k, i]
            if finite or np.isfinite(v):
                cnt[i] += 1.0
                total[i] += v
            if v != x[0, i]:  # NaN included: a sensor that reads NaN is not stuck at a value
                moved[i] = True
    stuck = 0
    if n >= stuck_min:
        for i in range(m):
            stuck += not moved[i]
    non_finite = n * m - int(cnt.sum())
    ms = np.zeros(m)
    peak = np.zeros(m)
    peak_rest = np.zeros(m)
    mean = np.zeros(m)
    for i in range(m):
        if cnt[i] > 0.0:
            mean[i] = total[i] / cnt[i]
            if not known[i]:
                base[i], rest[i], known[i] = mean[i], mean[i], True
                seen[i] = -1.0  # marks "new in this chunk" until its noise level is set below
    for k in range(n):
        for i in range(m):
            v = x[k, i]
            if finite or np.isfinite(v):
                d = v - base[i]
                ms[i] += d * d
                peak[i] = max(peak[i], abs(d))
                peak_rest[i] = max(peak_rest[i], abs(v - rest[i]))
    hms = np.zeros(m)
    if energy_ratio > 0.0:
        row = np.empty(m)
        sos1 = sos.reshape((1,) + sos.shape)
        zi1 = zi.reshape((1,) + zi.shape)
        for k in range(n):
            for i in range(m):
                v = x[k, i]
                row[i] = v if finite or np.isfinite(v) else last_x[i]
            sos_step(sos1, 0, row, zi1, 0, m)
            for i in range(m):
                hms[i] += row[i] * row[i]
        for i in range(m):
            v = x[n - 1, i]
            if np.isfinite(v):
                last_x[i] = v
            hms[i] /= n
    for i in range(m):
        if cnt[i] == 0.0:
            out[i] = False
            continue
        ms[i] /= cnt[i]
        if seen[i] < 0.0:  # new: its noise level starts at this chunk's
            seen[i], var[i] = 0.0, ms[i]
        # out of band around the baseline (which drifts under a constant load) and around the resting level
        # (which a release returns to: a taxel let go sleeps after hold_s, not once the baseline has drifted back)
        band = k_noise * np.sqrt(var[i]) + floor
        loud = min(peak[i], peak_rest[i]) > band
        if energy_ratio > 0.0:
            if hp_var[i] == 0.0:
                hp_var[i] = recent[i] = hms[i]
            recent[i] += a_recent * (hms[i] - recent[i])
            loud = loud or recent[i] > energy_ratio * hp_var[i] + floor * floor
        out[i] = loud and seen[i] >= learned
        quiet = not out[i]
        base[i] += (a_base if quiet else a_drift) * (mean[i] - base[i])
        if quiet and peak_rest[i] <= band:  # at rest (a settled load is quiet around the baseline only)
            rest[i] += a_base * (mean[i] - rest[i])
        # until a taxel is judged, its noise level is the running mean of every chunk's (learned in a few
        # chunks); from then on only quiet chunks within ``teach`` x its mean square teach it, so a slow press
        # that the baseline lags (its deviation growing inside the band) is not learned as noise
        if seen[i] < learned:
            rate = min(1.0, a_noise / max(seen[i], a_noise))
        else:
            rate = a_noise if quiet and ms[i] <= teach * var[i] else 0.0
        var[i] += rate * (ms[i] - var[i])
        if energy_ratio > 0.0:
            hp_var[i] += rate * (hms[i] - hp_var[i])
    return non_finite, stuck


class _Band:
    """Baseline and noise level of one sensor for every taxel."""

    def __init__(self, n_taxels: int, floor: float):
        self.floor = floor
        self.base = np.zeros(n_taxels)
        self.rest = np.zeros(n_taxels)  #: the baseline of chunks in band around it (where a released taxel returns)
        self.var = np.zeros(n_taxels)  #: mean square deviation from the baseline of quiet samples
        self.known = np.zeros(n_taxels, bool)  #: a taxel's band is learned from its first finite chunk
        self.seen = np.zeros(n_taxels)  #: fraction of the learning time (``noise_tau_s``) seen so far
        self.recent = np.zeros(n_taxels)  #: mean square of the high-passed samples over about ``energy_tau_s``
        self.hp_var = np.zeros(n_taxels)  #: mean square of the high-passed quiet samples
        self.zi: np.ndarray | None = None  #: the high-pass's state
        self.last_x = np.zeros(n_taxels)  #: each taxel's newest sample if finite (stands in for a non-finite one)
        self.non_finite = 0  #: the latest chunk's non-finite samples
        self.stuck = 0  #: taxels whose samples were all identical in the latest chunk (of :data:`_STUCK_MIN_SAMPLES` or more)

    def step(self, x: np.ndarray, k_noise: float, energy_ratio: float, a_recent: float, a_base: float,
             a_drift: float, a_noise: float, learned_by: float, teach: float) -> np.ndarray:
        """The (N,) out-of-band mask of samples ``x`` (n, N), NaN ignored, then learn from them.

        Out of band: a sample beyond ``k_noise`` x the noise level (+ the floor), or (``energy_ratio`` >
        0) the recent mean square of the high-passed samples (:data:`_HP_SOS`: drift and baseline
        removed, vibration kept) above ``energy_ratio`` x the noise's (a sustained small vibration);
        never before the taxel has learned for ``learned_by`` (a fraction of ``noise_tau_s``).
        Learning: quiet taxels' baseline (rate ``a_base``) and noise levels (``a_noise``) follow the
        chunk; loud ones' baseline drifts slowly (``a_drift``) and their noise levels stay; while a
        taxel is new every chunk teaches it. ``seen`` advances by the chunk's share of ``noise_tau_s``
        elsewhere (:meth:`ActivityDetector.push`)."""
        # float32 samples (the simulated skin's, a device's) are read as they are: every sum and test is in
        # float64, so a copy to float64 first gives the same bits and cost a tenth of a large skin's detector
        x = np.ascontiguousarray(x) if x.dtype in (np.float32, np.float64) else np.asarray(x, np.float64)
        if self.zi is None:
            first = np.where(np.isfinite(x[0]), x[0], 0.0) if x.shape[0] else np.zeros(self.base.size)
            self.zi = np.ascontiguousarray(_HP_ZI[:, :, None] * first[None, None, :])
        out = np.empty(self.base.size, bool)
        self.non_finite, self.stuck = _band_kernel(
            x, self.base, self.rest, self.var, self.known, self.seen, self.recent, self.hp_var, self.zi, self.last_x, _HP_SOS,
            energy_ratio, a_recent, k_noise, self.floor, a_base, a_drift, a_noise, learned_by, teach, _STUCK_MIN_SAMPLES, out)
        return out


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
        self.awake = np.ones(n_taxels, bool)  #: the mask :meth:`push` returned last (every taxel before any)

    def push(self, chunk: RawChunk) -> np.ndarray:
        """Learn from the chunk's raw samples; the (N,) mask of taxels awake: loud in this chunk or
        within ``hold_s`` of their latest loud chunk (sensor clock)."""
        p = self.plan
        ends = [a[-1] for a in (chunk.st_t, chunk.pvdf_t) if a.size]
        if not ends:
            return self.last_out_s > -np.inf
        now = float(max(ends))
        loud = np.zeros(self.n_taxels, bool)
        span = chunk.pvdf_t.size / PVDF_FS_HZ if chunk.pvdf_t.size else chunk.st_t.size / ST_FS_HZ
        # the energy test on the PVDF only: a SingleTact sample every 10 ms is too few for a 20 ms mean square
        for band, x, ratio, fs in ((self._st, chunk.st, 0.0, ST_FS_HZ), (self._pv, chunk.pvdf, p.energy_ratio, PVDF_FS_HZ)):
            if x.shape[0] == 0:
                continue
            covers = x.shape[0] / fs  # each band learns on its own samples' time
            rates = [min(1.0, covers / tau) for tau in (p.baseline_tau_s, p.drift_tau_s, p.noise_tau_s)]
            loud |= band.step(x, p.k_noise, ratio, min(1.0, covers / p.energy_tau_s), *rates, _JUDGED_AFTER, p.teach_ratio)
            band.seen += covers / p.noise_tau_s
            self.counters["non_finite"] += band.non_finite
        if chunk.pvdf.shape[0] >= _STUCK_MIN_SAMPLES:
            self.stuck = self._pv.stuck
        awake_before = self.last_out_s >= now - p.hold_s - span
        self.counters["wakes"] += int((loud & ~awake_before).sum())
        self.last_out_s[loud] = now
        unjudged = (self._pv.seen < _JUDGED_AFTER) | (self._st.seen < _JUDGED_AFTER)  # awake until judged
        self.awake = (self.last_out_s >= now - p.hold_s) | unjudged
        return self.awake
