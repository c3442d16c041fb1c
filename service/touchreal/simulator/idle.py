"""Noise, mains hum and drift of every taxel of a large skin, cheaply (numba, one pass per sample).

The dense e-skin (:mod:`.eskin`) draws three Gaussian streams per PVDF sample (broadband noise and
two Ornstein-Uhlenbeck drifts, filtered with scipy) and two per SingleTact sample. Here the sum of
white noise and the OU processes of one sensor is generated as the one ARMA process with the same
autocovariance (spectral factorisation: a sum of independent Gaussian processes is the Gaussian
process of the summed autocovariance), driven by a single unit Gaussian per sample, and its state
starts from its stationary distribution. The Gaussians come from a Marsaglia-Tsang ziggurat on a
xorshift128+ generator inside the kernel: exact N(0, 1) draws at a few ns each. The kernel adds the
mains hum (one waveform, a gain per taxel) or the SingleTact offset, the contact signal of the taxels that have one (``idx``:
a column of ``extra`` each), quantises (ADC, SingleTact resolution) and clips, in one pass over
(tick, taxel) in that order, so the samples do not depend on how the ticks are split into calls.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy import linalg

_M1 = 2147483648.0  # 2^31


def _ziggurat_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Marsaglia & Tsang (2000) 128-layer normal ziggurat: (kn, wn, fn)."""
    kn, wn, fn = np.zeros(128, np.int64), np.zeros(128), np.zeros(128)
    dn = tn = 3.442619855899
    vn = 9.91256303526217e-3
    q = vn / math.exp(-0.5 * dn * dn)
    kn[0], kn[1] = int(dn / q * _M1), 0
    wn[0], wn[127] = q / _M1, dn / _M1
    fn[0], fn[127] = 1.0, math.exp(-0.5 * dn * dn)
    for i in range(126, 0, -1):
        dn = math.sqrt(-2.0 * math.log(vn / dn + math.exp(-0.5 * dn * dn)))
        kn[i + 1] = int(dn / tn * _M1)
        tn = dn
        fn[i], wn[i] = math.exp(-0.5 * dn * dn), dn / _M1
    return kn, wn, fn


_KN, _WN, _FN = _ziggurat_tables()
_NONE = np.zeros(0)  # an input a channel's kernel call does not use
_ZIG_R = 3.442620  # start of the tail (the base layer's right edge)


@numba.njit(inline="always")
def _xorshift(s0, s1):  # pragma: no cover - compiled
    """xorshift128+: (new s0, new s1, 64 random bits)."""
    x = s0 ^ (s0 << np.uint64(23))
    x = x ^ s1 ^ (x >> np.uint64(17)) ^ (s1 >> np.uint64(26))
    return s1, x, x + s1


@numba.njit(inline="always")
def _uniform(s0, s1):  # pragma: no cover - compiled
    """(s0, s1, u) with u uniform on (0, 1)."""
    s0, s1, u = _xorshift(s0, s1)
    return s0, s1, (np.float64(u >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@numba.njit(inline="always")
def _normal(s0, s1, kn, wn, fn):  # pragma: no cover - compiled
    """(s0, s1, x) with x ~ N(0, 1): ziggurat, layer and value from independent bits of one draw."""
    while True:
        s0, s1, u = _xorshift(s0, s1)
        hz = np.int64(u >> np.uint64(32)) - 2147483648
        iz = np.int64((u >> np.uint64(4)) & np.uint64(127))
        x = hz * wn[iz]
        if abs(hz) < kn[iz]:
            return s0, s1, x
        if iz == 0:  # the tail beyond R (Marsaglia's exponential method)
            while True:
                s0, s1, a = _uniform(s0, s1)
                s0, s1, b = _uniform(s0, s1)
                t = -math.log(a) / _ZIG_R
                if -2.0 * math.log(b) >= t * t:
                    break
            return s0, s1, (_ZIG_R + t) if hz > 0 else -(_ZIG_R + t)
        s0, s1, a = _uniform(s0, s1)
        if fn[iz] + a * (fn[iz - 1] - fn[iz]) < math.exp(-0.5 * x * x):
            return s0, s1, x


@numba.njit(cache=True, nogil=True)
def standard_normal(state, out):  # pragma: no cover - compiled
    """Fill ``out`` (1-D) with N(0, 1) draws of the xorshift128+ ``state`` (2 uint64, advanced)."""
    s0, s1 = state[0], state[1]
    for k in range(out.size):
        s0, s1, out[k] = _normal(s0, s1, _KN, _WN, _FN)
    state[0], state[1] = s0, s1


@numba.njit(cache=True, nogil=True)
def _arma_row(e, b, a, zi, v):  # pragma: no cover - compiled
    """One tick of the order-2 filter (transposed direct form II) on every taxel: ``v = filter(e)``."""
    b0, b1, b2, a1, a2 = b[0], b[1], b[2], a[1], a[2]
    z0, z1 = zi[0], zi[1]
    for i in range(e.size):
        y = b0 * e[i] + z0[i]
        z0[i] = b1 * e[i] - a1 * y + z1[i]
        z1[i] = b2 * e[i] - a2 * y
        v[i] = y


@numba.njit(inline="always")
def _noise_row(s0, s1, e, b, a, zi, v):  # pragma: no cover - compiled
    """One tick of the noise process on every taxel into ``v`` (``e``: scratch); the advanced generator state."""
    for i in range(e.size):
        s0, s1, e[i] = _normal(s0, s1, _KN, _WN, _FN)
    _arma_row(e, b, a, zi, v)
    return s0, s1


@numba.njit(cache=True, nogil=True)
def _idle_kernel(out, state, b, a, zi, hum, pickup, offset, resid, decay, idx, extra, step, lo, hi):  # pragma: no cover - compiled
    """Per tick: the noise row, then the film's ``hum[k] x pickup`` (when ``hum`` has ticks) or the
    SingleTact's ``offset + resid`` (``resid`` decayed by ``decay`` in place), ``extra`` on the taxels
    ``idx``, quantised to ``step`` and clipped to [``lo``, ``hi``] (the sensor's unit)."""
    n, m = out.shape
    s0, s1 = state[0], state[1]
    e, v = np.empty(m), np.empty(m)
    inv = 1.0 / step
    film = hum.size > 0
    for k in range(n):
        s0, s1 = _noise_row(s0, s1, e, b, a, zi, v)
        if film:
            h = hum[k]
            for i in range(m):
                v[i] += h * pickup[i]
        else:
            for i in range(m):
                v[i] += offset[i] + resid[i]
                resid[i] *= decay
        for j in range(idx.size):
            v[idx[j]] += extra[k, j]
        row = out[k]
        for i in range(m):
            row[i] = np.float32(min(max(np.rint(v[i] * inv) * step, lo), hi) + 0.0)
    state[0], state[1] = s0, s1


def arma_of_sum(white_sd: float, ou: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """(b, a), order 2, of the ARMA process driven by unit white noise whose autocovariance is that of
    white noise of sd ``white_sd`` plus independent AR(1) (OU) processes ``(phi, sd)`` (stationary sd).

    The MA part is the spectral factor of the summed moving-average autocovariance (roots inside the
    unit circle: the invertible factor). At most two OU components.
    """
    if len(ou) > 2:
        raise ValueError("at most two OU components")
    phis = [float(p) for p, _ in ou]
    den = np.poly(phis) if phis else np.ones(1)
    q = den.size - 1
    parts = [white_sd * den]  # each part: the coefficients of its moving average in u = den(B) y
    for j, (phi, sd) in enumerate(ou):
        others = np.poly([p for l, p in enumerate(phis) if l != j]) if q > 1 else np.ones(1)
        parts.append(sd * math.sqrt(1.0 - phi * phi) * np.pad(others, (0, q + 1 - others.size)))
    gamma = np.array([sum(float(np.dot(c[: c.size - t], c[t:])) for c in parts) for t in range(q + 1)])
    b = np.zeros(3)
    if gamma[0] > 0:
        if q == 0:
            theta = np.ones(1)
        else:
            roots = np.roots(np.concatenate([gamma[::-1], gamma[1:]]))
            inside = sorted(roots, key=abs)[:q]  # reciprocal pairs: the q smallest are the invertible ones
            theta = np.real(np.poly(inside))
        b[: q + 1] = math.sqrt(gamma[0] / float(np.dot(theta, theta))) * theta
    a = np.zeros(3)
    a[: q + 1] = den
    return b, a


def stationary_state(b: np.ndarray, a: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(2, n) transposed-direct-form-II states of the order-2 filter (b, a) on unit white noise, drawn
    from their stationary distribution (discrete Lyapunov equation), independent per column."""
    f = np.array([[-a[1], 1.0], [-a[2], 0.0]])
    g = np.array([b[1] - a[1] * b[0], b[2] - a[2] * b[0]])
    cov = linalg.solve_discrete_lyapunov(f, np.outer(g, g))
    w, v = np.linalg.eigh((cov + cov.T) / 2)
    root = v * np.sqrt(np.maximum(w, 0.0))
    return np.ascontiguousarray(root @ rng.standard_normal((2, n)))


class NoiseStream:
    """One sensor's noise of N taxels: ARMA (b, a) on a ziggurat stream, stationary from the start.

    ``seed`` (a SeedSequence) gives the generator's state and the initial filter state.
    """

    def __init__(self, white_sd: float, ou: list[tuple[float, float]], n_taxels: int, seed: np.random.SeedSequence):
        self.b, self.a = arma_of_sum(white_sd, ou)
        gen_ss, init_ss = seed.spawn(2)
        self.state = gen_ss.generate_state(2, np.uint64)
        if not self.state.any():
            self.state[0] = 1
        self.zi = stationary_state(self.b, self.a, n_taxels, np.random.default_rng(init_ss))

    def pvdf(self, out: np.ndarray, hum: np.ndarray, pickup: np.ndarray, idx: np.ndarray, extra: np.ndarray,
             step_v: float, codes: tuple[int, int]) -> None:
        """Fill ``out`` (n ticks at 2 kHz, N) float32 (V): noise + ``hum`` (n,) x ``pickup`` (N,), plus
        ``extra`` (n, len(idx)) on the taxels ``idx``, quantised to ``step_v`` and clipped to the ADC ``codes``."""
        if hum.size != out.shape[0]:
            raise ValueError(f"hum has {hum.size} ticks for {out.shape[0]} rows")
        _idle_kernel(out, self.state, self.b, self.a, self.zi, hum, pickup, _NONE, _NONE, 1.0, idx, extra, step_v,
                     codes[0] * step_v, codes[1] * step_v)

    def singletact(self, out: np.ndarray, offset: np.ndarray, resid: np.ndarray, decay: float, idx: np.ndarray,
                   extra: np.ndarray, step_n: float, max_n: float) -> None:
        """Fill ``out`` (m samples at 100 Hz, N) float32 (N): ``offset`` + noise + ``resid`` (then decayed by
        ``decay`` per sample, in place), plus ``extra`` (m, len(idx)) on the taxels ``idx``, quantised to
        ``step_n`` and clipped to [0, ``max_n``]."""
        _idle_kernel(out, self.state, self.b, self.a, self.zi, _NONE, _NONE, offset, resid, decay, idx, extra, step_n,
                     0.0, max_n)
