"""Skin mechanics of one flat round probe: Sneddon's punch solution and TouchSim's surface wave.

Units: lengths in mm, time in s, rates in Hz, Young's modulus in MPa (= N/mm^2), so a load
(force) comes out in N and a stress in MPa. The skin is an elastic half-space without boundaries.

For an indentation trace ``S0(t)`` (mm, positive = into the skin) of a flat cylindrical probe of
radius ``a``:

* Sneddon (1946) compliance of the punch: ``D0 = (1 - nu^2) / (2 a E)`` (mm/N).
  Load ``P(t) = S0(t) / D0`` (N). As in TouchSim, a negative indentation keeps its sign (the one-pin
  contact iteration works on |S0| and restores the sign afterwards, which for one pin is the
  identity), so ``P`` is odd in ``S0``.
* Static component, the vertical stress at an afferent at horizontal distance ``r`` and depth
  ``z``: with ``XSI = z/a``, ``RHO = r/a``, ``rr = sqrt(1 + XSI^2)``,
  ``R = sqrt((RHO^2 + XSI^2 - 1)^2 + 4 XSI^2)``, ``theta = arctan(1/XSI)``,
  ``phi = arctan2(2 XSI, RHO^2 + XSI^2 - 1)``, ``J01 = sin(phi/2) / sqrt(R)``,
  ``J02 = rr sin(3 phi / 2 - theta) / R^(3/2)``:  ``s_z = P / (2 pi a^2) * (J01 + XSI J02)`` (MPa).
* Dynamic component: profile velocity ``S1'`` by central differences (end samples copied from
  their neighbours, mm/s), dynamic load ``Pdyn = S1' / D0`` (N/s), propagated to the afferent as a
  surface wave: delayed by ``max(dist - a, 0) / v`` (rounded to whole samples), scaled by the
  Sneddon deflection decay ``arcsin(a / dist) / (pi a)`` (``1 / (2 a)`` under the probe) and by
  ``1 / z^2`` for depth: ``u_dyn = Pdyn(t - delay) * decay / z^2`` (zero before the wave arrives).

These are TouchSim's ``static`` and ``dynamic`` LIF inputs (see docs/reference-model.md).
"""

from __future__ import annotations

import numpy as np

#: TouchSim's skin constants (also in the packaged constants file).
YOUNGS_MODULUS_MPA = 0.05
POISSON_RATIO = 0.4
WAVE_VELOCITY_MM_S = 8000.0


def sneddon_compliance(pin_radius_mm: float, youngs_modulus_mpa: float = YOUNGS_MODULUS_MPA,
                       poisson_ratio: float = POISSON_RATIO) -> float:
    """Compliance ``D0 = (1 - nu^2) / (2 a E)`` of a flat round punch (mm per N)."""
    if not (pin_radius_mm > 0 and youngs_modulus_mpa > 0):
        raise ValueError("pin radius and Young's modulus must be > 0")
    return (1.0 - poisson_ratio**2) / (2.0 * pin_radius_mm * youngs_modulus_mpa)


def probe_load(trace_mm: np.ndarray, compliance: float) -> np.ndarray:
    """Probe load ``P = S0 / D0`` (N) for indentation ``S0`` (mm); negative indentation keeps its sign."""
    return np.asarray(trace_mm, dtype=np.float64) / compliance


def stress_gain(distance_mm: np.ndarray, depth_mm: np.ndarray, pin_radius_mm: float) -> np.ndarray:
    """Vertical stress per unit load (MPa/N) at horizontal ``distance_mm`` and ``depth_mm``.

    Sneddon's stress field under a flat punch; the arguments broadcast against each other.
    """
    a = float(pin_radius_mm)
    z = np.asarray(depth_mm, dtype=np.float64)
    r = np.asarray(distance_mm, dtype=np.float64)
    if np.any(z <= 0):
        raise ValueError("afferent depth must be > 0 mm")
    xsi = z / a
    rho = r / a
    rr = np.sqrt(1.0 + xsi**2)
    q = rho**2 + xsi**2 - 1.0
    big_r = np.sqrt(q**2 + 4.0 * xsi**2)
    theta = np.arctan(1.0 / xsi)
    phi = np.arctan2(2.0 * xsi, q)
    j01 = np.sin(phi / 2.0) / np.sqrt(big_r)
    j02 = rr * np.sin(1.5 * phi - theta) / big_r**1.5
    return (j01 + xsi * j02) / (2.0 * np.pi * a * a)


def profile_velocity(trace_mm: np.ndarray, fs_hz: float) -> np.ndarray:
    """Central-difference time derivative of the skin profile under the probe (mm/s).

    ``v[k] = (S[k+1] - S[k-1]) / 2 * fs``; the first and last samples copy their neighbours.
    A trace of fewer than 3 samples has zero velocity.
    """
    s = np.asarray(trace_mm, dtype=np.float64)
    v = np.zeros_like(s)
    if s.size < 3:
        return v
    v[1:-1] = (s[2:] - s[:-2]) / 2.0 * fs_hz
    v[0] = v[1]
    v[-1] = v[-2]
    return v


def wave_delay_samples(distance_mm: np.ndarray, pin_radius_mm: float, fs_hz: float,
                       velocity_mm_s: float = WAVE_VELOCITY_MM_S) -> np.ndarray:
    """Surface-wave delay ``max(dist - a, 0) / v`` rounded to whole samples (int)."""
    d = np.asarray(distance_mm, dtype=np.float64)
    delay_s = np.maximum(d - pin_radius_mm, 0.0) / velocity_mm_s
    return np.rint(delay_s * fs_hz).astype(np.int64)


def wave_decay(distance_mm: np.ndarray, pin_radius_mm: float) -> np.ndarray:
    """Sneddon deflection decay (1/mm): ``arcsin(a/d) / (pi a)`` for ``d > a``, ``1/(2a)`` under the probe."""
    a = float(pin_radius_mm)
    d = np.asarray(distance_mm, dtype=np.float64)
    outside = d > a
    ratio = np.where(outside, a / np.where(outside, d, 1.0), 1.0)
    return np.where(outside, np.arcsin(ratio) / (np.pi * a), 1.0 / (2.0 * a))


def propagate(
    trace_mm: np.ndarray,
    probe_xy_mm: np.ndarray | tuple[float, float],
    afferent_xy_mm: np.ndarray,
    depth_mm: np.ndarray,
    *,
    pin_radius_mm: float = 0.5,
    fs_hz: float = 5000.0,
    youngs_modulus_mpa: float = YOUNGS_MODULUS_MPA,
    poisson_ratio: float = POISSON_RATIO,
    wave_velocity_mm_s: float = WAVE_VELOCITY_MM_S,
) -> tuple[np.ndarray, np.ndarray]:
    """Static and dynamic components at every afferent location and depth.

    Args:
        trace_mm: (T,) probe indentation (mm), sample k at t = k / fs_hz.
        probe_xy_mm: probe centre (mm).
        afferent_xy_mm: (L, 2) afferent locations (mm).
        depth_mm: (D,) receptor depths (mm), e.g. one per class.

    Returns:
        ``static`` (T, L, D): vertical stress (MPa); ``dynamic`` (T, L, D): propagated dynamic
        load (N s^-1 mm^-3, TouchSim's units), both float64.
    """
    trace = np.asarray(trace_mm, dtype=np.float64)
    if trace.ndim != 1:
        raise ValueError("trace must be 1-D")
    aff = np.atleast_2d(np.asarray(afferent_xy_mm, dtype=np.float64))
    if aff.shape[1] != 2:
        raise ValueError("afferent locations must be (L, 2)")
    depth = np.atleast_1d(np.asarray(depth_mm, dtype=np.float64))
    probe = np.asarray(probe_xy_mm, dtype=np.float64).reshape(2)
    dist = np.hypot(aff[:, 0] - probe[0], aff[:, 1] - probe[1])  # (L,)

    d0 = sneddon_compliance(pin_radius_mm, youngs_modulus_mpa, poisson_ratio)
    load = probe_load(trace, d0)  # (T,)
    gain = stress_gain(dist[:, None], depth[None, :], pin_radius_mm)  # (L, D)
    static = load[:, None, None] * gain[None, :, :]

    pdyn = profile_velocity(trace, fs_hz) / d0  # (T,) N/s
    delays = wave_delay_samples(dist, pin_radius_mm, fs_hz, wave_velocity_mm_s)
    scale = wave_decay(dist, pin_radius_mm)[:, None] / depth[None, :] ** 2  # (L, D)
    shifted = np.zeros((trace.size, dist.size))
    for k in np.unique(delays):
        cols = np.flatnonzero(delays == k)
        if k < trace.size:
            shifted[k:, cols] = pdyn[: trace.size - k, None]
    dynamic = shifted[:, :, None] * scale[None, :, :]
    return static, dynamic
