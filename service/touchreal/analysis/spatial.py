"""Receptive-field-like spatial measures (paper section 2.5.3, Figs. 10-11).

Inputs are per sampling position: radius ``r`` (mm), angle ``theta`` (degrees, counter-clockwise
from +x) and the mean spike count per trial ``R`` at that position.

* :func:`interpolate_map`: linear interpolation of R over the scanned disc (Fig. 10 A-C);
* :func:`radial_profile`: mean of R over the angles of each radius (Fig. 10 D-F);
* :func:`response_area` / :func:`area_sweep`: area (mm^2) of the interpolated map at or above an
  absolute spike-count threshold (Fig. 10 G-K);
* :func:`anisotropy`: second-order anisotropy index (eq. 12) per ring,
  ``AI_2(r) = |sum_theta R e^{2 i theta}| / sum_theta R``, averaged over valid rings (r > 0 and
  non-zero response); opposite directions map onto the same axis;
* :func:`angular_profile`: per-ring responses normalised to the ring mean, combined over valid
  rings with the ring's mean count as weight (Fig. 11 A-C).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def polar_to_xy(r: np.ndarray, theta_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    th = np.deg2rad(np.asarray(theta_deg, np.float64))
    r = np.asarray(r, np.float64)
    return r * np.cos(th), r * np.sin(th)


@dataclass
class SpatialMap:
    x_mm: np.ndarray  # (nx,)
    y_mm: np.ndarray  # (ny,)
    values: np.ndarray  # (ny, nx), NaN outside the scanned disc

    @property
    def cell_area_mm2(self) -> float:
        return float((self.x_mm[1] - self.x_mm[0]) * (self.y_mm[1] - self.y_mm[0]))


def interpolate_map(r: np.ndarray, theta_deg: np.ndarray, values: np.ndarray, step_mm: float = 0.25) -> SpatialMap:
    """Linear (Delaunay) interpolation of the samples on a square grid; NaN outside the hull."""
    from scipy.interpolate import griddata

    x, y = polar_to_xy(r, theta_deg)
    v = np.asarray(values, np.float64)
    rmax = float(np.max(np.asarray(r, np.float64)))
    if rmax <= 0:
        raise ValueError("need samples off the centre to build a map")
    g = np.arange(-rmax, rmax + step_mm * 0.5, step_mm)
    gx, gy = np.meshgrid(g, g)
    # duplicate positions (e.g. r = 0 at several angles) are averaged first
    key = np.round(np.stack((x, y), axis=1), 6)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    vm = np.bincount(inv, weights=v) / np.bincount(inv)
    grid = griddata(uniq, vm, (gx, gy), method="linear")
    return SpatialMap(g, g, grid)


def response_area(m: SpatialMap, threshold: float) -> float:
    """Area (mm^2) of map cells with value >= threshold (NaN cells never count)."""
    with np.errstate(invalid="ignore"):
        return float(np.sum(m.values >= threshold) * m.cell_area_mm2)


def area_sweep(m: SpatialMap, thresholds: np.ndarray) -> np.ndarray:
    return np.array([response_area(m, t) for t in thresholds])


def radial_profile(r: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(radii, mean, std) of the values grouped by radius."""
    r = np.round(np.asarray(r, np.float64), 6)
    v = np.asarray(values, np.float64)
    radii = np.unique(r)
    mean = np.array([v[r == q].mean() for q in radii])
    std = np.array([v[r == q].std() for q in radii])
    return radii, mean, std


def _rings(r: np.ndarray, theta_deg: np.ndarray, values: np.ndarray):
    r = np.round(np.asarray(r, np.float64), 6)
    th = np.asarray(theta_deg, np.float64)
    v = np.asarray(values, np.float64)
    for q in np.unique(r):
        if q <= 0:
            continue
        sel = r == q
        if sel.sum() < 2:
            continue
        yield q, th[sel], v[sel]


def ai2_ring(theta_deg: np.ndarray, values: np.ndarray) -> float:
    """Eq. (12) on one ring; NaN when the ring has no response."""
    v = np.asarray(values, np.float64)
    s = v.sum()
    if s <= 0:
        return float("nan")
    return float(np.abs(np.sum(v * np.exp(2j * np.deg2rad(np.asarray(theta_deg, np.float64))))) / s)


@dataclass
class Anisotropy:
    ai2: float  # mean over valid rings (NaN if none)
    radii: np.ndarray
    per_ring: np.ndarray  # NaN for rings without response
    axis_deg: float  # dominant axis (degrees, [0, 180)), response-weighted over valid rings


def anisotropy(r: np.ndarray, theta_deg: np.ndarray, values: np.ndarray) -> Anisotropy:
    radii, per, vecs, wts = [], [], [], []
    for q, th, v in _rings(r, theta_deg, values):
        radii.append(q)
        a = ai2_ring(th, v)
        per.append(a)
        if np.isfinite(a):
            vecs.append(np.sum(v * np.exp(2j * np.deg2rad(th))))
            wts.append(v.sum())
    per_a = np.array(per)
    valid = np.isfinite(per_a)
    ai = float(per_a[valid].mean()) if valid.any() else float("nan")
    axis = float(np.rad2deg(np.angle(np.sum(vecs))) / 2.0 % 180.0) if vecs else float("nan")
    return Anisotropy(ai, np.array(radii), per_a, axis)


def angular_profile(r: np.ndarray, theta_deg: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(angles, weighted mean normalised profile, weighted std across rings); 1 = ring mean.

    Every ring must sample the same angles; rings with zero response are skipped.
    """
    angles = None
    profs, w = [], []
    for _, th, v in _rings(r, theta_deg, values):
        order = np.argsort(th)
        th, v = th[order], v[order]
        if angles is None:
            angles = th
        elif th.shape != angles.shape or not np.allclose(th, angles):
            continue
        m = v.mean()
        if m <= 0:
            continue
        profs.append(v / m)
        w.append(m)
    if not profs:
        a = angles if angles is not None else np.zeros(0)
        return a, np.full(a.shape, np.nan), np.full(a.shape, np.nan)
    p = np.array(profs)
    wt = np.array(w) / np.sum(w)
    mean = wt @ p
    std = np.sqrt(wt @ (p - mean) ** 2)
    return angles, mean, std
