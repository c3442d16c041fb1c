"""A large skin: sparse contacts moving over a taxel grid, simulated at the cost of the touched taxels.

:func:`large_scene` places contactors over the grid from the **touched fraction** (the share of taxels
under a contact at a typical moment): round probes, each wandering in a cell of its own along a
Lissajous path (10-40 mm/s), pressing (depth cycles), sliding over a texture (a vibration at
40-250 Hz) or rolling (steady depth); above half the skin, one flat plate sliding over it. The number of probes follows
from the touched taxels (about :data:`TAXELS_PER_PROBE` each), their radius from the fraction of
their cell they cover; every random choice comes from the seed. Contacts land during the first
:data:`LAND_S` and stay on the skin.

:class:`LargeSkinSource` plays it: the e-skin physics of :mod:`.eskin` (silicone hysteresis,
SingleTact force and dynamics, PVDF film, spreading, electronics, extra mains pickup under a
contact) runs only for the taxels within :func:`reach_mm` of a contact, and for
:func:`quiet_s` after one has left, each driven by its nearest contactor. Every taxel's noise,
drift and mains hum comes from :mod:`.idle` with the build's statistics, so an untouched taxel
reads what the dense e-skin gives a taxel no probe touches. A SingleTact's slowest relaxation
(Prony, seconds) outlives the quiet time: it is handed over to a per-taxel decaying residual.
Membership is decided every :data:`BLOCK_TICKS` ticks on the absolute tick grid, and the gains are
interpolated linearly within a block, so reads of any size give identical samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numba
import numpy as np
from scipy import signal
from scipy.spatial import cKDTree

from ..raw import RawChunk
from ..settings import ST_RANGE_N, ST_RESOLUTION_N
from .eskin import (ADC_STEP_V, FS_HZ, ST_DECIMATION, SkinParams, _aniso_distance, _exciter_coupling, _ou, _pv_sos,
                    _st_sos, instance_constants, pv_radial_gain, pv_spread_cutoff_hz, st_radial_gain)
from .idle import NoiseStream
from .reads import TickReads

TAXELS_PER_PROBE = 64  #: touched taxels per round probe (a probe of ~45 mm radius on the 10 mm grid)
PLATE_ABOVE = 0.5  #: touched fractions above this are one plate sliding over the skin
BLOCK_TICKS = ST_DECIMATION  #: ticks per membership block (10 ms: one SingleTact sample each)
LAND_S = 0.3  #: contacts land (depth ramps from 0) over this long after the clock starts (s)
REACH_FRACTION = 0.1  #: a taxel is out of reach where a contact's largest signal there is below this x the noise


# ----------------------------------------------------------------------------------------------
# the scene


@dataclass(frozen=True)
class LargeScene:
    """K contactors (arrays of K rows). A contactor is a rectangle of half-sizes ``half_mm`` (mm)
    rounded by ``radius_mm`` (a round probe: half-sizes 0), its centre on the path
    ``centre + sweep * sin(2 pi path_hz t + path_phase)`` (mm, per axis), pressed to
    ``depth_mm + press_mm * sin(2 pi press_hz t + press_phase)`` (mm) and vibrating
    ``vib_mm * sin(2 pi vib_hz t)`` (mm), all after landing from ``start_s`` (s) over :data:`LAND_S`."""

    centre_mm: np.ndarray
    sweep_mm: np.ndarray
    path_hz: np.ndarray
    path_phase: np.ndarray
    half_mm: np.ndarray
    radius_mm: np.ndarray
    depth_mm: np.ndarray
    press_mm: np.ndarray
    press_hz: np.ndarray
    press_phase: np.ndarray
    vib_mm: np.ndarray
    vib_hz: np.ndarray
    start_s: float = 0.0

    @property
    def n_contactors(self) -> int:
        return int(self.radius_mm.size)

    def centres(self, t_s: np.ndarray) -> np.ndarray:
        """(n, K, 2) contactor centres (mm) at times ``t_s`` (s)."""
        t = np.asarray(t_s, float).reshape(-1, 1, 1)
        return self.centre_mm + self.sweep_mm * np.sin(2 * np.pi * self.path_hz * t + self.path_phase)

    def _landing(self, t: np.ndarray) -> np.ndarray:
        return np.clip((t - self.start_s) / LAND_S, 0.0, 1.0)[:, None]

    def depth(self, t_s: np.ndarray) -> np.ndarray:
        """(n, K) indentation (mm, > 0 into the skin) at times ``t_s`` (s)."""
        t = np.asarray(t_s, float).reshape(-1)
        return self._landing(t) * (self.depth_mm + self.press_mm * np.sin(2 * np.pi * self.press_hz * t[:, None] + self.press_phase))

    def vibration(self, t_s: np.ndarray) -> np.ndarray:
        """(n, K) vibration displacement (mm) at times ``t_s`` (s), before the skin's coupling."""
        t = np.asarray(t_s, float).reshape(-1)
        return self._landing(t) * self.vib_mm * np.sin(2 * np.pi * self.vib_hz * t[:, None])

    def touched(self, taxels_xy_mm: np.ndarray, t_s: float) -> np.ndarray:
        """(N,) bool: the taxel centres under a contactor's footprint at time ``t_s`` (s)."""
        xy = np.asarray(taxels_xy_mm, float)
        if self.n_contactors == 0 or self.depth(t_s)[0].max() <= 0:
            return np.zeros(xy.shape[0], bool)
        d = footprint_distance(self.centres(t_s)[0][None, :, :] - xy[:, None, :], self.half_mm, self.radius_mm)
        return np.any((d <= 0.0) & (self.depth(t_s)[0] > 0), axis=1)


def footprint_distance(rel_mm: np.ndarray, half_mm: np.ndarray, radius_mm: np.ndarray, ratio: float = 1.0) -> np.ndarray:
    """Distance (mm, signed inside the rounding) from a point at ``rel_mm`` (contactor centre minus point,
    (..., 2)) to a rounded rectangle's footprint, in the elliptical metric of axis ratio ``ratio``."""
    ex = np.maximum(np.abs(rel_mm[..., 0]) - half_mm[..., 0], 0.0)
    ey = np.maximum(np.abs(rel_mm[..., 1]) - half_mm[..., 1], 0.0)
    return _aniso_distance(ex, ey, ratio) - radius_mm


def _empty_scene(start_s: float) -> LargeScene:
    z1, z2 = np.zeros(0), np.zeros((0, 2))
    return LargeScene(z2, z2, z2, z2, z2, z1, z1, z1, z1, z1, z1, z1, start_s)


def large_scene(taxels_xy_mm: np.ndarray, touched: float, seed: int | np.random.SeedSequence | None = None,
                start_s: float = 0.0, pitch_mm: float = 10.0) -> LargeScene:
    """Contactors covering about ``touched`` (0-1) of the taxels of a grid of pitch ``pitch_mm`` (mm).

    0: none. Up to :data:`PLATE_ABOVE`: round probes, one per cell of a near-square partition of the
    grid's area, about :data:`TAXELS_PER_PROBE` touched taxels each (at least one probe), of radius
    sqrt(touched x cell area / pi), each wandering inside its cell (so footprints never overlap);
    in turn pressing (depth 0.5-1.2 mm +- 0.3-0.4 mm at 0.3-1.5 Hz), sliding over a texture
    (0.005-0.02 mm at 40-250 Hz) and rolling. Above: a flat plate across the whole width, ``touched``
    of the height, sliding over it (at 1: a plate over everything, sliding by less than half a pitch).
    """
    if not 0.0 <= touched <= 1.0:
        raise ValueError(f"touched must be in [0, 1], got {touched!r}")
    if touched == 0.0:
        return _empty_scene(start_s)
    rng = np.random.default_rng(seed)
    xy = np.asarray(taxels_xy_mm, float)
    lo, hi = xy.min(axis=0) - pitch_mm / 2, xy.max(axis=0) + pitch_mm / 2
    size = hi - lo
    if touched > PLATE_ABOVE:
        half = np.array([[size[0] / 2 + pitch_mm, touched * size[1] / 2]])
        sweep = np.array([[0.9 * pitch_mm, 0.9 * (size[1] / 2 - half[0, 1]) if touched < 1 else 0.4 * pitch_mm]])
        centre, radius = ((lo + hi) / 2)[None, :], np.zeros(1)
    else:
        k_target = max(1, round(touched * xy.shape[0] / TAXELS_PER_PROBE))
        kx = max(1, round(math.sqrt(k_target * size[0] / size[1])))
        ky = max(1, round(k_target / kx))
        cell = size / [kx, ky]
        ij = np.stack(np.meshgrid(np.arange(kx), np.arange(ky), indexing="ij"), -1).reshape(-1, 2)
        centre = lo + (ij + 0.5) * cell
        r = min(math.sqrt(touched * cell[0] * cell[1] / math.pi), 0.5 * float(cell.min()))
        radius = np.full(len(centre), r)
        half = np.zeros_like(centre)
        sweep = np.tile(0.9 * (cell / 2 - r), (len(centre), 1))
    k = len(centre)
    speed = rng.uniform(10.0, 40.0, (k, 2))  # mm/s, peak, per axis
    path_hz = np.where(sweep > 0, np.clip(speed / (2 * np.pi * np.maximum(sweep, 1e-9)), 0.02, 1.0), 0.0)
    kind = np.arange(k) % 3  # 0 pressing, 1 sliding over a texture, 2 rolling
    depth = rng.uniform(0.5, 1.2, k)
    press = np.where(kind == 0, rng.uniform(0.3, 0.4, k), 0.0)
    vib = np.where(kind == 1, rng.uniform(0.005, 0.02, k), 0.0)
    return LargeScene(
        centre_mm=centre, sweep_mm=sweep, path_hz=path_hz, path_phase=rng.uniform(0, 2 * np.pi, (k, 2)),
        half_mm=half, radius_mm=radius, depth_mm=depth, press_mm=press, press_hz=rng.uniform(0.3, 1.5, k),
        press_phase=rng.uniform(0, 2 * np.pi, k), vib_mm=vib, vib_hz=rng.uniform(40.0, 250.0, k), start_s=start_s,
    )


# ----------------------------------------------------------------------------------------------
# reach of a contact


def _thresholds(p: SkinParams) -> tuple[float, float, float, float]:
    """(largest SingleTact force (N), largest PVDF signal (V), their negligible levels (N, V))."""
    st_max = ST_RANGE_N[1] * p.st_gain
    pv_max = p.pv_gain_v_mm * math.exp(4 * p.pv_gain_jitter) * p.pv_saturation_mm \
        + p.mains_contact_gain * p.mains_v * math.exp(4 * p.mains_v_log_sd) * sum(map(abs, p.mains_harmonics))
    st_small = REACH_FRACTION * max(p.st_noise_n, ST_RESOLUTION_N / 2)
    pv_small = REACH_FRACTION * max(p.pv_noise_v, ADC_STEP_V / 2)
    return st_max, pv_max, st_small, pv_small


def reach_mm(p: SkinParams = SkinParams()) -> float:
    """Distance (mm, Euclidean, beyond a footprint's edge) past which a contact moves neither sensor by
    more than :data:`REACH_FRACTION` of its noise (or half its quantisation step): the radial gains
    times the largest force (10 N) and film signal (saturated strain at +4 sd of sensitivity, plus
    the extra mains pickup), solved on a 0.01 mm grid, widened by the sensor centres' offsets and the
    elliptical metric."""
    st_max, pv_max, st_small, pv_small = _thresholds(p)
    r = np.arange(0.0, 200.0, 0.01)
    r_st = r[np.argmax(st_radial_gain(r, p) * st_max < st_small)]
    r_pv = r[np.argmax(pv_radial_gain(r, p) * pv_max < pv_small)]
    st = r_st * math.sqrt(max(p.st_axis_ratio, 1 / p.st_axis_ratio)) + math.hypot(*p.st_center_mm)
    pv = r_pv * math.sqrt(max(p.pv_axis_ratio, 1 / p.pv_axis_ratio)) + math.hypot(*p.pv_center_mm)
    return float(max(st, pv))


def quiet_s(p: SkinParams = SkinParams()) -> float:
    """How long (s) a taxel's physics keeps running after it left every contact's reach: until the
    slowest of the silicone release, the film's electronics, the SingleTact's fast relaxation and
    low-passes has decayed from the largest signal to a negligible one (the slow relaxation is handed
    over to a residual)."""
    st_max, pv_max, st_small, pv_small = _thresholds(p)
    taus = (p.tau_release_s, p.pv_tau_ac_s, p.pv_tau_leak_s, p.prony_tau_s[0], 1 / (2 * np.pi * p.st_lowpass_hz),
            1 / (2 * np.pi * p.pv_antialias_hz))
    return float(max(taus) * math.log(max(pv_max / pv_small, st_max / st_small)))


# ----------------------------------------------------------------------------------------------
# the contact physics of the taxels within reach (eskin.py's signal path, one taxel at a time)


@numba.njit(cache=True, nogil=True, inline="always")
def _biquad(x, sos, s, zi, i):  # pragma: no cover - compiled
    """Section ``s`` of ``sos`` on one sample of taxel ``i`` (transposed direct form II, state ``zi``)."""
    y = sos[s, 0] * x + zi[s, 0, i]
    zi[s, 0, i] = sos[s, 1] * x - sos[s, 4] * y + zi[s, 1, i]
    zi[s, 1, i] = sos[s, 2] * x - sos[s, 5] * y
    return y


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def _contact_kernel(k0, block, st_phase, decimation, idx, owner, g_st, g_pv, a_sp, base, vib2, hum, zero, stiff, pv_gain,
                    pickup, c, z, st_zi, st_sos, ring, f_last, spread, pv_zi, pv_sos, out_pv, out_st):  # pragma: no cover
    # ticks k0.. of one block of ``block`` ticks; c: st_gain, exponent, pv_probe_fraction, pv_saturation_mm,
    # pv_membrane_per_mm, mains_contact_gain, a_press, a_release; g_st, g_pv, a_sp: (2, A) at the block's ends
    n = base.shape[0]
    depth = ring.shape[0]
    kb = k0 % block
    dw = 1.0 / block
    r0 = k0 % depth if depth > 0 else 0
    st0 = (k0 - st_phase) % decimation
    st_gain, expo, alpha, sat, memb, touch, a_press, a_release = c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]
    for j in range(idx.size):
        i, o = idx[j], owner[j]
        zz, sp1, sp2 = z[i], spread[0, i], spread[1, i]
        k_st = stiff[i] * st_gain
        k_pv = pv_gain[i] * sat
        zero_i, pick = zero[i], pickup[i] * touch
        row, r, until_st = 0, r0, st0
        for k in range(n):
            w = (kb + k) * dw
            gs = g_st[0, j] + w * (g_st[1, j] - g_st[0, j])
            gp = g_pv[0, j] + w * (g_pv[1, j] - g_pv[0, j])
            a = a_sp[0, j] + w * (a_sp[1, j] - a_sp[0, j])
            b = base[k, o] + zero_i
            d = max(b, 0.0) - zz
            zz += (a_press if d > 0.0 else a_release) * d
            x = gs * k_st * np.exp(expo * np.log(zz)) if zz > 0.0 and gs > 1e-12 else 0.0
            for s in range(st_sos.shape[0]):
                x = _biquad(x, st_sos, s, st_zi, i)
            f_last[i] = x
            if depth > 0:
                x, ring[r, i] = ring[r, i], x
                r = r + 1 if r + 1 < depth else 0
            if until_st == 0:
                out_st[row, j] = x
                row += 1
            until_st = until_st + 1 if until_st + 1 < decimation else 0
            wv = alpha * (b + memb * vib2[k, o]) + (1.0 - alpha) * zz
            sv = gp * k_pv * (1.0 - np.exp(-wv / sat)) if wv > 0.0 and gp > 0.0 else 0.0
            sp1 = a * sp1 + (1.0 - a) * sv
            sp2 = a * sp2 + (1.0 - a) * sp1
            x = sp2
            for s in range(pv_sos.shape[0]):
                x = _biquad(x, pv_sos, s, pv_zi, i)
            out_pv[k, j] = x + hum[k] * pick * min(max(zz / 0.2, 0.0), 1.0) * gp
        z[i], spread[0, i], spread[1, i] = zz, sp1, sp2


class LargeSkinSource(TickReads):
    """Sans-I/O source of a large skin playing :func:`large_scene` (same reading interface as
    :class:`~touchreal.simulator.scene.SceneSource`: ``advance``, ``read``, ``time_s``, ``requested_s``).

    Args:
        taxels_xy_mm: (N, 2) taxel centres (mm), a grid of pitch ``pitch_mm``.
        touched: the touched fraction (0-1) of :func:`large_scene`.
        seed: reproducibility (same seed -> identical arrays, however reads are chunked).
        skin: physical constants (a build's :meth:`~.build.SensorBuild.skin`).
        t0_s, st_phase_ticks: time of the first PVDF tick (s) and SingleTact phase, as for ``SceneSource``.
    """

    def __init__(self, taxels_xy_mm: Sequence[Sequence[float]] | np.ndarray, touched: float, *,
                 seed: int | np.random.SeedSequence | None = None, skin: SkinParams | None = None,
                 t0_s: float | None = None, st_phase_ticks: int | None = None, pitch_mm: float = 10.0) -> None:
        p = self.skin_params = skin or SkinParams()
        xy = self.taxels_xy_mm = np.atleast_2d(np.asarray(taxels_xy_mm, float))
        n = self.n_taxels = xy.shape[0]
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        clock_ss, scene_ss, inst_ss, pv_ss, st_ss = ss.spawn(5)
        clock = np.random.default_rng(clock_ss)
        self.t0_s = float(clock.uniform(0.0, 1.0 / FS_HZ)) if t0_s is None else float(t0_s)
        self.st_phase = (int(clock.integers(0, ST_DECIMATION)) if st_phase_ticks is None else int(st_phase_ticks)) % ST_DECIMATION
        self.tick = 0
        self._requested_s = self.t0_s - math.fmod(self.t0_s, 1.0 / FS_HZ)
        self.scene = large_scene(xy, touched, scene_ss, self._requested_s, pitch_mm)
        self._reach_mm = reach_mm(p)
        self._quiet_ticks = int(math.ceil(quiet_s(p) * FS_HZ))
        self._tree = cKDTree(xy)

        inst = np.random.default_rng(inst_ss)  # instance constants, drawn as ESkin draws them
        (self._stiff, self._zero, self._st_offset, self._pv_gain, self.mains_hz, self._mains_amp, self._mains_phase,
         self._pickup) = instance_constants(p, n, inst)

        ou = [(_ou(p.pv_wander_tau_s, 1.0, FS_HZ)[2], p.pv_wander_v), (_ou(p.pv_flicker_tau_s, 1.0, FS_HZ)[2], p.pv_flicker_v)]
        self._pv_noise = NoiseStream(p.pv_noise_v, ou, n, pv_ss)
        self._st_noise = NoiseStream(p.st_noise_n, [(_ou(p.st_wander_tau_s, 1.0, FS_HZ / ST_DECIMATION)[2], p.st_wander_n)], n, st_ss)

        self._st_sos, self._pv_sos = (np.ascontiguousarray(s / s[:, 3:4]) for s in (_st_sos(p), _pv_sos(p)))
        self._coupling = _exciter_coupling(p)
        self._slow_pole = math.exp(-1.0 / (FS_HZ * max(p.prony_tau_s)))
        self._consts = np.array([p.st_gain, p.exponent, p.pv_probe_fraction, p.pv_saturation_mm, p.pv_membrane_per_mm,
                                 p.mains_contact_gain, 1.0 - math.exp(-1.0 / (FS_HZ * p.tau_press_s)),
                                 1.0 - math.exp(-1.0 / (FS_HZ * p.tau_release_s))])
        k = self.scene.n_contactors
        self._zi_coupling = np.zeros((len(self._coupling[1]) - 1, k))
        # per-taxel physics state (zero: untouched), the SingleTact residual and the last tick in reach
        self._z = np.zeros(n)
        self._st_zi = np.zeros((self._st_sos.shape[0], 2, n))
        self._ring = np.zeros((int(round(p.st_latency_s * FS_HZ)), n))
        self._f_last = np.zeros(n)
        self._spread = np.zeros((2, n))
        self._pv_zi = np.zeros((self._pv_sos.shape[0], 2, n))
        self._resid = np.zeros(n)
        self._last_in_reach = np.full(n, -(1 << 40), np.int64)
        self.active = np.zeros(0, np.int64)  #: taxels whose contact physics runs in the current block
        self._owner = np.zeros(0, np.int64)
        self._gains = np.zeros((3, 2, 0))

    # -- clock -----------------------------------------------------------------------------------------
    @property
    def clock_t0_s(self) -> float:
        return self.t0_s

    # -- simulation ------------------------------------------------------------------------------------
    def _advance(self, n: int) -> RawChunk:
        k = self.tick + np.arange(n)
        st_rows = (k - self.st_phase) % ST_DECIMATION == 0
        pv = np.empty((n, self.n_taxels), np.float32)
        st = np.empty((int(st_rows.sum()), self.n_taxels), np.float32)
        pos = row = 0
        while pos < n:
            if self.tick % BLOCK_TICKS == 0:
                self._plan(self.tick)
            seg = min(n - pos, BLOCK_TICKS - self.tick % BLOCK_TICKS)
            m = int(st_rows[pos : pos + seg].sum())
            self._segment(seg, pv[pos : pos + seg], st[row : row + m])
            pos, row = pos + seg, row + m
        return RawChunk(st_t=self.t0_s + k[st_rows] / FS_HZ, st=st, pvdf_t=self.t0_s + k / FS_HZ, pvdf=pv)

    def _in_reach(self, k0: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Taxels within reach of a contactor during the block from tick ``k0``, their nearest contactor,
        and the contactor centres (2, K, 2) at the block's start and end (mm)."""
        sc = self.scene
        ends = sc.centres(self.t0_s + np.array([k0, k0 + BLOCK_TICKS]) / FS_HZ)
        if sc.n_contactors == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), ends
        move = np.hypot(*(ends[1] - ends[0]).T)
        limit = self._reach_mm + move
        found = self._tree.query_ball_point(ends.mean(axis=0), np.hypot(*sc.half_mm.T) + sc.radius_mm + limit)
        taxel = np.concatenate([np.asarray(f, np.int64) for f in found])
        contactor = np.repeat(np.arange(sc.n_contactors), [len(f) for f in found])
        d = [footprint_distance(ends[e][contactor] - self.taxels_xy_mm[taxel], sc.half_mm[contactor], sc.radius_mm[contactor])
             for e in (0, 1)]
        keep = np.minimum(d[0], d[1]) <= limit[contactor]
        taxel, contactor, d0 = taxel[keep], contactor[keep], d[0][keep]
        order = np.lexsort((d0, taxel))
        first = np.r_[True, taxel[order][1:] != taxel[order][:-1]]
        return taxel[order][first], contactor[order][first], ends

    def _plan(self, k0: int) -> None:
        """At a block start: retire the taxels out of reach for the quiet time (their SingleTact's slow
        relaxation goes to the residual), take on the taxels come within reach, and their gains."""
        taxel, contactor, ends = self._in_reach(k0)
        self._last_in_reach[taxel] = k0
        act = self.active
        gone = act[k0 - self._last_in_reach[act] >= self._quiet_ticks]
        if gone.size:
            self._retire(gone, k0)
        self.active = np.union1d(np.setdiff1d(act, gone, assume_unique=True), taxel)
        owner = np.full(self.active.size, self.scene.n_contactors, np.int64)  # K: no contactor (in the quiet time)
        owner[np.searchsorted(self.active, taxel)] = contactor
        self._owner = owner
        self._gains = self._block_gains(ends)

    def _retire(self, gone: np.ndarray, k0: int) -> None:
        """Hand the SingleTact's remaining (slow-pole) output of ``gone`` at the next SingleTact sample to
        the residual, and reset their physics to rest."""
        ks = k0 + (self.st_phase - k0) % ST_DECIMATION
        depth = self._ring.shape[0]
        if depth and ks - depth <= k0 - 1:
            due = self._ring[ks % depth, gone]
        else:
            due = self._f_last[gone] * self._slow_pole ** (ks - depth - k0 + 1)
        self._resid[gone] += due
        for state in (self._st_zi, self._ring, self._spread, self._pv_zi):
            state[..., gone] = 0.0
        self._z[gone] = 0.0
        self._f_last[gone] = 0.0

    def _block_gains(self, ends: np.ndarray) -> np.ndarray:
        """(3, 2, A): SingleTact gain, PVDF gain and spreading pole of the active taxels at the block's
        start and end (zero gains where no contactor drives a taxel)."""
        p, sc = self.skin_params, self.scene
        out = np.zeros((3, 2, self.active.size))
        out[2] = np.exp(-2 * np.pi * pv_spread_cutoff_hz(self._reach_mm, p) / FS_HZ)
        own = self._owner < sc.n_contactors
        if not own.any():
            return out
        o, xy = self._owner[own], self.taxels_xy_mm[self.active[own]]
        for e in (0, 1):
            rel = ends[e][o] - xy
            r_st = np.maximum(footprint_distance(rel - np.asarray(p.st_center_mm), sc.half_mm[o], sc.radius_mm[o], p.st_axis_ratio), 0.0)
            r_pv = np.maximum(footprint_distance(rel - np.asarray(p.pv_center_mm), sc.half_mm[o], sc.radius_mm[o], p.pv_axis_ratio), 0.0)
            out[0, e, own] = st_radial_gain(r_st, p)
            out[1, e, own] = pv_radial_gain(r_pv, p)
            out[2, e, own] = np.exp(-2 * np.pi * pv_spread_cutoff_hz(r_pv, p) / FS_HZ)
        return out

    def _mains(self, t: np.ndarray) -> np.ndarray:
        """(n,) the mains hum's waveform (V) at times ``t`` (s), before each taxel's pickup."""
        hum = np.zeros(t.size)
        for h, (amp, ph) in enumerate(zip(self._mains_amp, self._mains_phase), start=1):
            hum += amp * np.sin(2 * np.pi * h * self.mains_hz * t + ph)
        return hum

    def _segment(self, n: int, pv: np.ndarray, st: np.ndarray) -> None:
        """Simulate the next ``n`` ticks (within one block) into ``pv`` (n, N) V and ``st`` (m, N) N."""
        k0 = self.tick
        t = self.t0_s + (k0 + np.arange(n)) / FS_HZ
        hum = self._mains(t)
        sc, a = self.scene, self.active.size
        c_pv, c_st = np.zeros((n, a)), np.zeros((st.shape[0], a))
        if a:
            base, vib2 = np.zeros((n, sc.n_contactors + 1)), np.zeros((n, sc.n_contactors + 1))
            if sc.n_contactors:
                vib, self._zi_coupling = signal.lfilter(*self._coupling, sc.vibration(t), axis=0, zi=self._zi_coupling)
                base[:, :-1], vib2[:, :-1] = sc.depth(t) + vib, vib * vib
            g = self._gains
            _contact_kernel(k0, BLOCK_TICKS, self.st_phase, ST_DECIMATION, self.active, self._owner, g[0], g[1], g[2], base, vib2, hum, self._zero,
                            self._stiff, self._pv_gain, self._pickup, self._consts, self._z, self._st_zi, self._st_sos,
                            self._ring, self._f_last, self._spread, self._pv_zi, self._pv_sos, c_pv, c_st)
        self._pv_noise.pvdf(pv, hum, self._pickup, self.active, c_pv, ADC_STEP_V, (-2048, 2047))
        self._st_noise.singletact(st, self._st_offset, self._resid, self._slow_pole ** ST_DECIMATION, self.active, c_st,
                                  ST_RESOLUTION_N, ST_RANGE_N[1])
        self.tick += n
