"""How an afferent's input is built from the taxels around it.

**SingleTact channels** (ST, dST: a taxel's load and its rate). A taxel reports the load on its
cell (a square of side ``cell_mm`` around its centre), not where on the cell it sits. The rule
places it at the cell's centre, the position estimate of least expected error when nothing says
otherwise, and propagates it to the afferent as the static component of TouchSim's reference
model does for a probe there (:mod:`touchreal.reference.mechanics`): the vertical stress at the
afferent's receptor depth, Sneddon's flat-punch field of a probe of the plan's
``probe_radius_mm``, relative to its value under the probe. Loads of several taxels superpose
(the mechanics is linear in the load). Depth separates the classes: a deep receptor (RA 1.6 mm,
PC 2.0 mm) sees a smoother, wider field than a shallow one (SA1 0.3 mm).

**PVDF channels** (PVDF, dPVDF: skin vibration). A film does not report a load on its cell but
samples the vibration field around it (a film picks up a contact several millimetres away), so
its readings are not superposed, which would count one vibration once per film. The rule
interpolates them at the afferent (bilinear weights of the taxel grid, a partition of unity
inside the grid that falls to 0 within one cell outside it).

Both weights are 1 for an afferent on a taxel's centre, so such an afferent with no load
elsewhere gets exactly that taxel's channels: the class parameters keep the meaning they were
fitted with (one afferent under the probe, read by one taxel).

Where it breaks down:

* A load off a cell's centre is reported around the centre: an afferent under an off-centre
  contact gets less than TouchSim's would, one near the centre more, by up to half a cell. With a
  pitch coarser than a class's receptive field (SA1's is about a millimetre) the population's maps
  are centred on the taxels rather than on the contacts.
* The vibration an afferent gets is what the films nearby measured, which decays with distance as
  the films' sensitivity does, not as TouchSim's surface wave ``arcsin(a / d) / (pi a)`` from a
  contact the rule cannot place; a class driven by the film (the fitted RA) responds over the
  films' reach. The wave's delay (at most 1.3 ms over 10 mm) is left out.
* An afferent outside every cell gets only the static field's tail and the films' values within a
  cell of the grid's edge.
* Skin stretch, tangential load and the skin's curvature are not modelled (as in TouchSim's
  single-probe model).
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from ..reference.mechanics import stress_gain

_MAX_REACH_MM = 30.0  #: farthest taxel an afferent may take input from


def cell_kernels(offsets_mm: np.ndarray, depth_mm: float, cell_mm: float, probe_radius_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Static weight (TouchSim's stress field of a probe on the taxel's centre, relative to its value
    under the probe) and dynamic weight (the film's bilinear interpolation weight), each (N,) and 1 at
    offset 0, at afferents ``offsets_mm`` (N, 2) from the taxel's centre, at receptor depth ``depth_mm``."""
    off = np.asarray(offsets_mm, np.float64).reshape(-1, 2)
    st = stress_gain(np.hypot(off[:, 0], off[:, 1]), depth_mm, probe_radius_mm) / stress_gain(0.0, depth_mm, probe_radius_mm)
    tent = np.clip(1.0 - np.abs(off) / cell_mm, 0.0, None)
    return st, tent[:, 0] * tent[:, 1]


def reach_mm(depth_mm: float, cell_mm: float, probe_radius_mm: float, min_weight: float) -> float:
    """Distance from a taxel's centre beyond which its static weight stays under ``min_weight`` and
    its dynamic weight is 0."""
    r = np.linspace(0.0, _MAX_REACH_MM, 1201)
    st, dy = cell_kernels(np.stack([r, np.zeros_like(r)], axis=1), depth_mm, cell_mm, probe_radius_mm)
    above = np.flatnonzero((np.abs(st) >= min_weight) | (dy >= min_weight))
    return float(r[above[-1]]) + cell_mm if above.size else cell_mm


def taxel_weights(afferent_xy_mm: np.ndarray, depth_mm: np.ndarray, taxels_xy_mm: np.ndarray, *, cell_mm: float,
                  probe_radius_mm: float, min_weight: float) -> tuple[sparse.csr_matrix, sparse.csr_matrix]:
    """Static and dynamic weight matrices (A afferents x X taxels, CSR) of the spatial rule.

    ``depth_mm`` (A,) is each afferent's receptor depth. Static weights under ``min_weight`` are
    dropped (the interpolation's are compact already: within a cell of the taxel).
    """
    aff = np.asarray(afferent_xy_mm, np.float64).reshape(-1, 2)
    depth = np.asarray(depth_mm, np.float64).reshape(-1)
    taxels = np.asarray(taxels_xy_mm, np.float64).reshape(-1, 2)
    tree = cKDTree(taxels)
    rows, cols, ws, wd = [], [], [], []
    for z in np.unique(depth):
        idx = np.flatnonzero(depth == z)
        near = tree.query_ball_point(aff[idx], reach_mm(float(z), cell_mm, probe_radius_mm, min_weight))
        a = np.repeat(idx, [len(n) for n in near])
        j = np.fromiter((t for n in near for t in n), np.int64, count=a.size)
        st, dy = cell_kernels(aff[a] - taxels[j], float(z), cell_mm, probe_radius_mm)
        st = np.where(np.abs(st) >= min_weight, st, 0.0)
        keep = (st != 0.0) | (dy != 0.0)
        rows.append(a[keep]), cols.append(j[keep]), ws.append(st[keep]), wd.append(dy[keep])
    shape = (len(aff), len(taxels))
    r, c = np.concatenate(rows), np.concatenate(cols)
    return (sparse.csr_matrix((np.concatenate(ws), (r, c)), shape=shape),
            sparse.csr_matrix((np.concatenate(wd), (r, c)), shape=shape))


def mix(channels: np.ndarray, static: sparse.csr_matrix, dynamic: sparse.csr_matrix) -> np.ndarray:
    """(T, X, 4) taxel channels (ST, dST, PVDF, dPVDF) -> (T, A, 4) afferent inputs: the SingleTact
    channels through the static weights, the PVDF channels through the dynamic ones (float64)."""
    x = np.asarray(channels, np.float64)
    n_t = x.shape[0]
    out = np.empty((n_t, static.shape[0], 4))
    for ch, w in ((0, static), (1, static), (2, dynamic), (3, dynamic)):
        out[:, :, ch] = (w @ x[:, :, ch].T).T
    return out
