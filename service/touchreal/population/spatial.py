"""How an afferent's input is built from the taxels around it.

The rule works in two steps: it localises the load each taxel carries, then propagates it to
every afferent with the component of TouchSim's reference model
(:mod:`touchreal.reference.mechanics`) that drives the afferent's class. The localisation is
re-estimated every :data:`HOLD_SAMPLES` samples of the absolute 5 kHz grid (5 ms: twice per sample
of the SingleTact, which reads at 100 Hz) and held in between, so the weights cost 200 evaluations a
second, not 5000; the channels themselves are mixed sample by sample. Causal, and any chunking gives
the same inputs.

**Localisation.** A taxel reports the load on its cell (a square of side ``cell_mm`` around its
centre), not where on the cell it sits; its neighbours (the taxels within 1.5 cells: the 8 around
it on a grid) say more. Each taxel's load is placed at the load-weighted centroid of its
neighbourhood, each load taken above the neighbourhood's smallest (the shared baseline), clipped
to the taxel's cell: a probe on a taxel's centre stays there, one on an edge or a corner shared by
several cells is placed on it. The vibration is localised the same way from the films' envelopes
(``|PVDF|`` smoothed over :data:`HOLD_SAMPLES`, one pole): a taxel is a **vibration contact** when
its envelope is the largest of its neighbourhood (ties: the lower index), placed at the
envelope-weighted centroid. The films localise the vibration (they feel it at once, and where the
SingleTact's sensor does not reach), the SingleTact the load.

**SingleTact channels** (ST, dST: a taxel's load and its rate), every class. Each taxel's load is
propagated from its localised position to the afferent's receptor depth as TouchSim's static
component propagates a probe's: the vertical stress of Sneddon's flat punch of the plan's
``probe_radius_mm``, relative to its value under the probe. Loads of several taxels superpose (the
mechanics is linear in the load). Depth separates the classes: a deep receptor (RA 1.6 mm, PC
2.0 mm) sees a smoother, wider field than a shallow one (SA1 0.3 mm).

**PVDF channels** (PVDF, dPVDF: skin vibration). A film samples the vibration field around it (it
picks up a contact several millimetres away), so films are not superposed, which would count one
vibration once per film. For the classes of ``surface_wave`` (default RA: TouchSim's RA units are
driven by the dynamic component alone, and the fitted RA by the film), the vibration is placed at
the vibration contacts: at each the films are interpolated (bilinear weights of the taxel grid,
what a film centred there would read) and propagated to the afferent as TouchSim's dynamic
component, the surface wave's Sneddon deflection decay ``arcsin(a / d) / (pi a)`` relative to its
value under the probe (1 within the probe's radius ``a``). Contacts superpose. For the other
classes the films are interpolated at the afferent itself.

For one taxel (or an afferent on a taxel's centre with no load nearby) every weight is exactly 1,
so one afferent per class on a lone taxel's centre gets exactly that taxel's channels: the class
parameters keep the meaning they were fitted with (one afferent under the probe, read by one
taxel).

Where it breaks down:

* The localisation sees a contact move only while it loads more than one cell: inside the part of
  a cell that only its own sensor feels, a load stays at the centre, so an afferent under such an
  off-centre contact gets less than TouchSim's would, one near the centre more, by up to the
  sensor's blind margin; the coarser the pitch, the more the maps follow the taxels.
* The films are broad (a film reads a vibration several millimetres away), so their envelopes
  place a vibration less sharply than the loads place a press, and a contact between films is read
  weaker than one on a film. Where nothing vibrates (a static hold) the envelopes are the films'
  noise, whose local maxima become weak contacts.
* Classes outside ``surface_wave`` get the films' own decay with distance, not TouchSim's; the
  wave's delay (at most 1.3 ms over 10 mm) is left out.
* An afferent outside every cell gets only the static field's tail and the films' values within a
  cell of the grid's edge.
* Skin stretch, tangential load and the skin's curvature are not modelled (as in TouchSim's
  single-probe model).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from ..reference.mechanics import stress_gain

_MAX_REACH_MM = 30.0  #: farthest taxel an afferent may take static input from
_TABLE_STEP_MM = 0.002  #: distance step of the static kernels' tables (linear interpolation)
NEIGHBOURHOOD_CELLS = 1.5  #: a taxel's neighbours lie within this many cells (the 8 around it on a grid)


def cell_kernels(offsets_mm: np.ndarray, depth_mm: float, cell_mm: float, probe_radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Static weight (TouchSim's stress field of a probe at the offset's origin, relative to its value
    under the probe) and the film's bilinear interpolation weight, each (N,) and 1 at offset 0, at
    afferents ``offsets_mm`` (N, 2) from the load (static) or the taxel's centre (films), at receptor
    depth ``depth_mm``."""
    off = np.asarray(offsets_mm, np.float64).reshape(-1, 2)
    st = stress_gain(np.hypot(off[:, 0], off[:, 1]), depth_mm, probe_radius_mm) / stress_gain(0.0, depth_mm, probe_radius_mm)
    tent = np.clip(1.0 - np.abs(off) / cell_mm, 0.0, None)
    return st, tent[:, 0] * tent[:, 1]


def wave_weight(distance_mm: np.ndarray, probe_radius_mm: float) -> np.ndarray:
    """TouchSim's surface-wave decay relative to its value under the probe: 1 within the probe's
    radius ``a``, ``(2 / pi) arcsin(a / d)`` beyond."""
    d = np.asarray(distance_mm, np.float64)
    a = float(probe_radius_mm)
    return np.where(d > a, (2.0 / np.pi) * np.arcsin(np.minimum(a / np.where(d > a, d, 1.0), 1.0)), 1.0)


def static_reach_mm(depth_mm: float, probe_radius_mm: float, min_weight: float) -> float:
    """Distance from a load beyond which its static weight stays under ``min_weight``."""
    r = np.linspace(0.0, _MAX_REACH_MM, 3001)
    st = stress_gain(r, depth_mm, probe_radius_mm) / stress_gain(0.0, depth_mm, probe_radius_mm)
    above = np.flatnonzero(np.abs(st) >= min_weight)
    return float(r[above[-1]]) + r[1] if above.size else r[1]


def _csr(rows: list[np.ndarray], cols: list[np.ndarray], vals: list[np.ndarray], shape) -> sparse.csr_matrix:
    r, c, v = (np.concatenate(x) if x else np.zeros(0) for x in (rows, cols, vals))
    m = sparse.csr_matrix((v.astype(np.float64), (r.astype(np.int64), c.astype(np.int64))), shape=shape)
    m.sort_indices()
    return m


@dataclass(frozen=True)
class SpatialRule:
    """The spatial rule resolved for a skin and its afferents (see the module doc).

    ``static_pairs`` (A, X): the taxels whose localised load can reach an afferent (values unused);
    ``films`` (A, X): the bilinear film weights of afferents outside ``surface_wave`` (empty rows
    for the others); ``wave`` (A,): the afferent's films come from the contacts; ``kernel`` (A,):
    the afferent's row of ``tables`` (its receptor depth); ``tables``: static weight over distance
    at ``_TABLE_STEP_MM``; ``neighbours`` (X, X): each taxel's neighbourhood, itself included.
    """

    taxels_xy_mm: np.ndarray
    afferent_xy_mm: np.ndarray
    cell_mm: float
    probe_radius_mm: float
    min_weight: float
    static_pairs: sparse.csr_matrix
    films: sparse.csr_matrix
    wave: np.ndarray
    kernel: np.ndarray
    tables: np.ndarray
    neighbours: sparse.csr_matrix

    @classmethod
    def build(cls, afferent_xy_mm: np.ndarray, depth_mm: np.ndarray, wave: np.ndarray, taxels_xy_mm: np.ndarray, *,
              cell_mm: float, probe_radius_mm: float, min_weight: float) -> SpatialRule:
        aff = np.asarray(afferent_xy_mm, np.float64).reshape(-1, 2)
        depth = np.asarray(depth_mm, np.float64).reshape(-1)
        wave = np.asarray(wave, bool).reshape(-1)
        taxels = np.asarray(taxels_xy_mm, np.float64).reshape(-1, 2)
        tree = cKDTree(taxels)
        depths, kernel = np.unique(depth, return_inverse=True)
        n_tab = int(math.ceil(_MAX_REACH_MM / _TABLE_STEP_MM)) + 2
        r = np.arange(n_tab) * _TABLE_STEP_MM
        tables = np.empty((depths.size, n_tab))
        rows, cols, fr, fc, fw = [], [], [], [], []
        for i, z in enumerate(depths):
            st = stress_gain(r, z, probe_radius_mm) / stress_gain(0.0, z, probe_radius_mm)
            st[0] = 1.0  # exactly: an afferent on the load gets it bit for bit
            tables[i] = np.where(r <= _MAX_REACH_MM, st, 0.0)
            idx = np.flatnonzero(kernel == i)
            # a taxel's load sits within its cell: up to half a cell's diagonal from its centre
            near = tree.query_ball_point(aff[idx], static_reach_mm(z, probe_radius_mm, min_weight) + cell_mm * math.sqrt(0.5))
            rows.append(np.repeat(idx, [len(n) for n in near]))
            cols.append(np.fromiter((t for n in near for t in n), np.int64, count=rows[-1].size))
        for a in np.flatnonzero(~wave):
            near = np.asarray(tree.query_ball_point(aff[a], cell_mm * math.sqrt(2.0)), np.int64)
            _, w = cell_kernels(aff[a] - taxels[near], 1.0, cell_mm, probe_radius_mm)
            keep = w > 0.0
            fr.append(np.full(int(keep.sum()), a)), fc.append(near[keep]), fw.append(w[keep])
        shape = (len(aff), len(taxels))
        pairs = _csr(rows, cols, [np.ones(c.size) for c in cols], shape)
        films = _csr(fr, fc, fw, shape)
        nb = tree.query_ball_point(taxels, NEIGHBOURHOOD_CELLS * cell_mm)
        nrow = np.repeat(np.arange(len(taxels)), [len(n) for n in nb])
        ncol = np.fromiter((t for n in nb for t in n), np.int64, count=nrow.size)
        neighbours = _csr([nrow], [ncol], [np.ones(nrow.size)], (len(taxels), len(taxels)))
        return cls(taxels, aff, float(cell_mm), float(probe_radius_mm), float(min_weight), pairs, films, wave,
                   kernel.astype(np.int64), tables, neighbours)

    def localise(self, channels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T, X, 4) channels -> each taxel's localised load position (T, X, 2) and the flags of the
        taxels whose load is the largest of their neighbourhood (T, X), sample by sample (a
        diagnostic: :meth:`mix` localises every :data:`HOLD_SAMPLES` samples)."""
        x = np.ascontiguousarray(channels, np.float64)
        n_t, n_x = x.shape[:2]
        pos = np.empty((n_t, n_x, 2))
        contact = np.empty((n_t, n_x), np.bool_)
        ptr, idx = self.neighbours.indptr.astype(np.int64), self.neighbours.indices.astype(np.int64)
        for k in range(n_t):
            _localise_sample(x[k], self.taxels_xy_mm, ptr, idx, self.cell_mm, pos[k], contact[k])
        return pos, contact

    def rows(self, afferents: np.ndarray) -> RuleRows:
        """The rule's arrays for the given afferents, in that order (what an encoder's columns read)."""
        a = np.asarray(afferents, np.int64)
        sp, fl = self.static_pairs[a], self.films[a]
        return RuleRows(np.ascontiguousarray(self.afferent_xy_mm[a]), sp.indptr.astype(np.int64), sp.indices.astype(np.int64),
                        fl.indptr.astype(np.int64), fl.indices.astype(np.int64), fl.data.astype(np.float64),
                        np.ascontiguousarray(self.wave[a]), np.ascontiguousarray(self.kernel[a]))

    def mix(self, channels: np.ndarray, rows: RuleRows, k0: int = 0, state: RuleState | None = None) -> np.ndarray:
        """(T, X, 4) taxel channels (ST, dST, PVDF, dPVDF) from absolute grid index ``k0`` -> (T, R, 4)
        inputs of the afferents of ``rows`` (float64). The localisation is re-estimated at every
        :data:`HOLD_SAMPLES`-th sample of the absolute grid (and at the first sample of a fresh
        ``state``) and held in between; ``state`` carries it over blocks (a fresh one when None)."""
        x = np.ascontiguousarray(channels, np.float64)
        out = np.empty((x.shape[0], rows.xy.shape[0], 4))
        if x.shape[0] == 0:
            return out
        state = state if state is not None else RuleState(len(self.taxels_xy_mm))
        if state.rows is not rows:  # other afferents: their weights follow from the held localisation
            state.rows, state.fresh_weights = rows, False
            state.w_static = np.zeros(rows.st_idx.size)
        nb = self.neighbours
        flags = np.array([state.valid, state.fresh_weights])
        _mix(x, int(k0), HOLD_SAMPLES, self.taxels_xy_mm, nb.indptr.astype(np.int64), nb.indices.astype(np.int64), self.cell_mm,
             rows.xy, rows.st_ptr, rows.st_idx, rows.fl_ptr, rows.fl_idx, rows.fl_w, rows.wave, rows.kernel, self.tables,
             1.0 / _TABLE_STEP_MM, self.min_weight, self.probe_radius_mm, state.pos, state.contact, flags, state.w_static,
             state.env, state.vpos, state.vcontact, out)
        state.valid, state.fresh_weights = bool(flags[0]), bool(flags[1])
        return out


HOLD_SAMPLES = 25  #: the localisation is re-estimated every this many 5 kHz samples (5 ms: twice per SingleTact sample)


@dataclass(frozen=True)
class RuleRows:
    """The rule's arrays for an encoder's afferents (:meth:`SpatialRule.rows`)."""

    xy: np.ndarray
    st_ptr: np.ndarray
    st_idx: np.ndarray
    fl_ptr: np.ndarray
    fl_idx: np.ndarray
    fl_w: np.ndarray
    wave: np.ndarray
    kernel: np.ndarray


class RuleState:
    """The held localisation of a stream (per taxel: load position and flag, film envelope, vibration
    position and contact flag) and the static weights of the afferents it was last applied to."""

    def __init__(self, n_taxels: int):
        self.pos = np.zeros((n_taxels, 2))
        self.contact = np.zeros(n_taxels, np.bool_)
        self.env = np.zeros(n_taxels)
        self.vpos = np.zeros((n_taxels, 2))
        self.vcontact = np.zeros(n_taxels, np.bool_)
        self.valid = False  # no localisation yet: the next sample makes one
        self.rows: RuleRows | None = None
        self.fresh_weights = False
        self.w_static = np.zeros(0)


@numba.njit(cache=True, nogil=True)
def _localise_sample(x, taxels, nb_ptr, nb_idx, cell, pos, contact):  # pragma: no cover - compiled
    """One sample's (X, 4) channels -> each taxel's load position (X, 2) and contact flag (X,)."""
    half = 0.5 * cell
    for j in range(x.shape[0]):
        lo = x[j, 0]
        for p in range(nb_ptr[j], nb_ptr[j + 1]):
            lo = min(lo, x[nb_idx[p], 0])
        sw = 0.0
        sx = 0.0
        sy = 0.0
        top = True
        for p in range(nb_ptr[j], nb_ptr[j + 1]):
            n = nb_idx[p]
            w = x[n, 0] - lo
            sw += w
            sx += w * (taxels[n, 0] - taxels[j, 0])
            sy += w * (taxels[n, 1] - taxels[j, 1])
            if n != j and (x[n, 0] > x[j, 0] or (x[n, 0] == x[j, 0] and n < j)):
                top = False
        ox = 0.0
        oy = 0.0
        if sw > 0.0:
            ox = min(max(sx / sw, -half), half)
            oy = min(max(sy / sw, -half), half)
        pos[j, 0] = taxels[j, 0] + ox
        pos[j, 1] = taxels[j, 1] + oy
        contact[j] = top


@numba.njit(cache=True, nogil=True)
def _mix(x, k0, hold, taxels, nb_ptr, nb_idx, cell, xy, st_ptr, st_idx, fl_ptr, fl_idx, fl_w, wave, kernel, tables, inv_step,
         min_weight, a, pos, contact, flags, w_static, env, vpos, vcontact, out):  # pragma: no cover - compiled
    """The rule over a block, localisation held between every ``hold``-th absolute sample; ``flags``:
    [localisation valid, ``w_static`` fresh for these rows], updated in place with the loads' ``pos``,
    ``contact``, the films' envelope ``env`` (one pole of ``hold`` samples, every sample) and the
    vibration's ``vpos``, ``vcontact``."""
    n_t, n_x = x.shape[0], x.shape[1]
    n_r = xy.shape[0]
    n_tab = tables.shape[1]
    two_over_pi = 2.0 / np.pi
    contacts = np.empty(n_x, np.int64)
    n_c = 0
    max_nb = 0
    for j in range(n_x):
        max_nb = max(max_nb, nb_ptr[j + 1] - nb_ptr[j])
    tent_n = np.zeros((n_x, max_nb), np.int64)
    tent_w = np.zeros((n_x, max_nb))
    w_wave = np.zeros((n_r, 1))
    waves = False  # wave weights computed for the held contacts
    seg_film = np.zeros((hold, n_x, 2))
    ex = np.zeros((n_x, 4))
    alpha = 1.0 - math.exp(-1.0 / hold)
    k = 0
    while k < n_t:
        if not flags[0]:
            for j in range(n_x):
                env[j] = abs(x[k, j, 2])
        else:
            for j in range(n_x):
                env[j] += alpha * (abs(x[k, j, 2]) - env[j])
        if (k0 + k) % hold == 0 or not flags[0]:
            _localise_sample(x[k], taxels, nb_ptr, nb_idx, cell, pos, contact)
            for j in range(n_x):
                ex[j, 0] = env[j]
            _localise_sample(ex, taxels, nb_ptr, nb_idx, cell, vpos, vcontact)
            flags[0] = True
            flags[1] = False
        if not flags[1]:  # static weights of every (afferent, taxel) pair from the held positions
            for r in range(n_r):
                ax = xy[r, 0]
                ay = xy[r, 1]
                tab = kernel[r]
                for p in range(st_ptr[r], st_ptr[r + 1]):
                    j = st_idx[p]
                    dx = ax - pos[j, 0]
                    dy = ay - pos[j, 1]
                    f = math.sqrt(dx * dx + dy * dy) * inv_step
                    i = int(f)
                    w = 0.0
                    if i < n_tab - 1:
                        t0 = tables[tab, i]
                        w = t0 + (f - i) * (tables[tab, i + 1] - t0)
                        if abs(w) < min_weight:
                            w = 0.0
                    w_static[p] = w
            flags[1] = True
            waves = False
        if not waves:  # the held contacts, their films' interpolation weights and the wave's decay
            n_c = 0
            for j in range(n_x):
                if vcontact[j]:
                    n_c += 1
            w_wave = np.zeros((n_r, max(n_c, 1)))
            n_c = 0
            for j in range(n_x):
                if vcontact[j]:
                    contacts[n_c] = j
                    m = 0
                    for q in range(nb_ptr[j], nb_ptr[j + 1]):
                        n = nb_idx[q]
                        tx = 1.0 - abs(vpos[j, 0] - taxels[n, 0]) / cell
                        ty = 1.0 - abs(vpos[j, 1] - taxels[n, 1]) / cell
                        tent_n[n_c, m] = n
                        tent_w[n_c, m] = tx * ty if tx > 0.0 and ty > 0.0 else 0.0
                        m += 1
                    for q in range(m, max_nb):
                        tent_n[n_c, q] = j
                        tent_w[n_c, q] = 0.0
                    for r in range(n_r):
                        if wave[r]:
                            dx = xy[r, 0] - vpos[j, 0]
                            dy = xy[r, 1] - vpos[j, 1]
                            d = math.sqrt(dx * dx + dy * dy)
                            w_wave[r, n_c] = 1.0 if d <= a else two_over_pi * math.asin(a / d)
                    n_c += 1
            waves = True
        e = k + 1  # the samples up to the next re-estimate share these weights
        while e < n_t and (k0 + e) % hold != 0:
            e += 1
        for kk in range(k + 1, e):
            for j in range(n_x):
                env[j] += alpha * (abs(x[kk, j, 2]) - env[j])
        for c in range(n_c):  # the films at each contact
            for kk in range(k, e):
                f0 = 0.0
                f1 = 0.0
                for q in range(max_nb):
                    tw = tent_w[c, q]
                    if tw != 0.0:
                        f0 += tw * x[kk, tent_n[c, q], 2]
                        f1 += tw * x[kk, tent_n[c, q], 3]
                seg_film[kk - k, c, 0] = f0
                seg_film[kk - k, c, 1] = f1
        for r in range(n_r):
            for kk in range(k, e):
                out[kk, r, 0] = 0.0
                out[kk, r, 1] = 0.0
                out[kk, r, 2] = 0.0
                out[kk, r, 3] = 0.0
            for p in range(st_ptr[r], st_ptr[r + 1]):
                w = w_static[p]
                if w != 0.0:  # adding 0 w x would change no bit
                    j = st_idx[p]
                    for kk in range(k, e):
                        out[kk, r, 0] += w * x[kk, j, 0]
                        out[kk, r, 1] += w * x[kk, j, 1]
            if wave[r]:
                for c in range(n_c):
                    w = w_wave[r, c]
                    for kk in range(k, e):
                        out[kk, r, 2] += w * seg_film[kk - k, c, 0]
                        out[kk, r, 3] += w * seg_film[kk - k, c, 1]
            else:
                for p in range(fl_ptr[r], fl_ptr[r + 1]):
                    j = fl_idx[p]
                    w = fl_w[p]
                    for kk in range(k, e):
                        out[kk, r, 2] += w * x[kk, j, 2]
                        out[kk, r, 3] += w * x[kk, j, 3]
        k = e
