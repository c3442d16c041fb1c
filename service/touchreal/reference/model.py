"""TouchSim-compatible reference model: one round probe -> spike trains of the 17 single-unit models.

Pipeline (all at the 5 kHz LIF rate, see docs/reference-model.md):

1. Mechanics (:mod:`touchreal.reference.mechanics`): static vertical stress and propagated dynamic
   load at each afferent location and class depth, (T, L, 3).
2. Input stage, per model p (13 columns, :mod:`touchreal.reference.constants`): 3rd-order
   Butterworth low-pass ``butter(3, p0 * 4 / 1000)`` (``lfilter``) of the static and dynamic inputs;
   second derivative ``dd[k] = d[k+1] - d[k]`` (0 at the last sample);
   ``I = p1 max(s,0) + p2 max(-s,0) + p3 max(d,0) + p4 max(-d,0) + p5 max(dd,0) + p6 max(-dd,0)``;
   noisy runs add ``p8 N(0, 1)`` per sample; then saturation ``p7 I / (p7 + |I|)`` when p7 > 0.
3. LIF (:class:`touchreal.encoding.lif.LifPopulation`): tau = p9 samples, post-spike current
   ``p10 ihbasis[0] + p11 ihbasis[1]``, 5-sample refractory rule. A crossing at sample k is reported
   at ``(k + 1) / 5000`` s, plus ``p12 / 1000`` s when conduction delays are enabled.

Every model at every location and repeat is one column of a single (T, N) LIF population, run in
column blocks to bound memory.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy import signal

from ..encoding.lif import LifPopulation
from ..recording import ReferenceTrains
from ..settings import CLASSES
from .constants import TouchSimConstants, load_constants
from .mechanics import propagate

#: Upper bound on T x columns per LIF block (float64 elements, ~64 MB of current).
MAX_BLOCK_ELEMENTS = 8_000_000


@numba.njit(cache=True, nogil=True)
def _block_current(base, src, noise_sd, i_sat, z, out):  # pragma: no cover - compiled
    """out[k, j] = sat_j(base[k, src[j]] + noise_sd[j] * z[k, j]); z may be empty (noiseless).

    Saturation as :class:`touchreal.encoding.encoder.InputStage`: ``I_sat I / (I_sat + |I|)`` where
    ``I_sat > 0``, non-finite results set to 0.
    """
    n_t, n_c = out.shape
    noisy = z.shape[0] > 0
    for k in range(n_t):
        for j in range(n_c):
            x = base[k, src[j]]
            if noisy:
                x += noise_sd[j] * z[k, j]
            s = i_sat[j]
            if s > 0.0:
                x = s * x / (s + abs(x))
                if not np.isfinite(x):
                    x = 0.0
            out[k, j] = x


@dataclass
class SpikeResponse:
    """Spike trains of all models at all locations and repeats.

    ``train(r, l, m) = t[off[r, l, m]:off[r, l, m + 1]]`` (s from trace sample 0), the layout of the
    conformance files' ``spikes_t`` / ``spikes_off``. Models are in TouchSim order (SA1 0-3, RA 0-8,
    PC 0-3), see ``model_class`` / ``model_index``.
    """

    t: np.ndarray  # (S,) float64 spike times (s)
    off: np.ndarray  # (R, L, M + 1) int64
    model_class: np.ndarray  # (M,) str
    model_index: np.ndarray  # (M,) int

    @property
    def repeats(self) -> int:
        return self.off.shape[0]

    @property
    def n_locations(self) -> int:
        return self.off.shape[1]

    @property
    def n_models(self) -> int:
        return self.off.shape[2] - 1

    def train(self, repeat: int, location: int, model: int) -> np.ndarray:
        return self.t[self.off[repeat, location, model] : self.off[repeat, location, model + 1]]

    def counts(self) -> np.ndarray:
        """(R, L, M) spike counts."""
        return np.diff(self.off, axis=2)

    def class_trains(self, location: int = 0) -> dict[str, ReferenceTrains]:
        """Trains at one location as ``{class: ReferenceTrains}`` (repeats x models of the class)."""
        out: dict[str, ReferenceTrains] = {}
        for cls in CLASSES:
            models = np.flatnonzero(self.model_class == cls)
            trains = [[self.train(r, location, int(m)) for m in models] for r in range(self.repeats)]
            out[cls] = ReferenceTrains.from_trains(trains)
        return out


class ReferenceModel:
    """TouchSim's single round-probe model with its 17 single-unit afferent models.

    Args:
        pin_radius_mm: probe radius a (mm).
        constants: model constants; default the packaged TouchSim constants.
    """

    def __init__(self, *, pin_radius_mm: float = 0.5, constants: TouchSimConstants | None = None):
        if not pin_radius_mm > 0:
            raise ValueError("pin radius must be > 0 mm")
        self.pin_radius_mm = float(pin_radius_mm)
        self.constants = c = constants if constants is not None else load_constants()
        p = c.params
        self.fs_hz = c.fs_hz
        # One Butterworth per model: normalised cutoff p0 * 4 / 1000 (TouchSim's convention at 5 kHz).
        self._filters = [signal.butter(3, p[m, 0] * 4.0 / 1000.0) for m in range(c.n_models)]
        self._uses_static = (p[:, 1] != 0) | (p[:, 2] != 0)
        self.tau = p[:, 9].copy()
        self.ih = p[:, 10:11] * c.ihbasis[0] + p[:, 11:12] * c.ihbasis[1]  # (M, L_ih)
        self.noise_sd = p[:, 8].copy()
        self.i_sat = p[:, 7].copy()
        self.delay_s = p[:, 12] / 1000.0

    @property
    def n_models(self) -> int:
        return self.constants.n_models

    # -- stages -------------------------------------------------------------------------------

    def mechanics(self, trace_mm: np.ndarray, probe_xy_mm, afferent_xy_mm, *, fs_hz: float = 5000.0
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Static (MPa) and dynamic components (T, L, 3) at the class depths, see :func:`propagate`."""
        c = self.constants
        return propagate(
            trace_mm, probe_xy_mm, afferent_xy_mm, c.depth_mm, pin_radius_mm=self.pin_radius_mm, fs_hz=fs_hz,
            youngs_modulus_mpa=c.youngs_modulus_mpa, poisson_ratio=c.poisson_ratio,
            wave_velocity_mm_s=c.wave_velocity_mm_s,
        )

    def drive(self, static: np.ndarray, dynamic: np.ndarray) -> np.ndarray:
        """Noiseless, unsaturated input current (T, L, M) from the (T, L, 3) mechanical components."""
        static = np.asarray(static, dtype=np.float64)
        dynamic = np.asarray(dynamic, dtype=np.float64)
        if static.shape != dynamic.shape or static.ndim != 3 or static.shape[2] != len(CLASSES):
            raise ValueError(f"static and dynamic must both be (T, L, {len(CLASSES)})")
        n_t, n_loc, _ = static.shape
        p = self.constants.params
        cls = self.constants.class_of_model
        out = np.empty((n_t, n_loc, self.n_models))
        if n_t == 0:
            return out
        for m, (b, a) in enumerate(self._filters):
            d = signal.lfilter(b, a, dynamic[:, :, cls[m]], axis=0)
            dd = np.zeros_like(d)
            dd[:-1] = d[1:] - d[:-1]
            if self._uses_static[m]:
                s = signal.lfilter(b, a, static[:, :, cls[m]], axis=0)
                cur = p[m, 1] * np.maximum(s, 0.0) + p[m, 2] * np.maximum(-s, 0.0)
            else:
                cur = np.zeros_like(d)
            cur += p[m, 3] * np.maximum(d, 0.0) + p[m, 4] * np.maximum(-d, 0.0)
            cur += p[m, 5] * np.maximum(dd, 0.0) + p[m, 6] * np.maximum(-dd, 0.0)
            out[:, :, m] = cur
        return out

    def spikes(
        self,
        current: np.ndarray,
        *,
        repeats: int = 1,
        noisy: bool = False,
        delays: bool = False,
        rng: np.random.Generator | int | None = None,
    ) -> SpikeResponse:
        """Run the LIF stage on a (T, L, M) drive (from :meth:`drive`) for ``repeats`` repeats.

        Noise is drawn from ``rng`` (a Generator, or a seed for ``numpy.random.default_rng``).
        Noiseless repeats are identical, so they are computed once.
        """
        current = np.asarray(current, dtype=np.float64)
        n_t, n_loc, n_mod = current.shape
        if n_mod != self.n_models:
            raise ValueError(f"current has {n_mod} models, expected {self.n_models}")
        if repeats < 1:
            raise ValueError("repeats must be >= 1")
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        n_run = repeats if noisy else 1
        flat = np.ascontiguousarray(current.reshape(n_t, n_loc * n_mod))
        group = n_loc * n_mod  # columns of one repeat
        total = n_run * group
        # Column blocks of whole location groups (M columns) so every block is a set of models.
        per_block = max(n_mod, (MAX_BLOCK_ELEMENTS // max(n_t, 1)) // n_mod * n_mod)
        times: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        for c0 in range(0, total, per_block):
            c1 = min(total, c0 + per_block)
            col = np.arange(c0, c1)
            model = col % n_mod
            z = gen.standard_normal((n_t, c1 - c0)) if noisy else np.zeros((0, 0))
            cur = np.empty((n_t, c1 - c0))
            _block_current(flat, col % group, self.noise_sd[model], self.i_sat[model], z, cur)
            pop = LifPopulation(self.tau[model], self.ih[model])
            k, n = pop.step(cur)
            order = np.argsort(n, kind="stable")  # by neuron, time order kept
            k, n = k[order], n[order]
            # (k + 1) / fs, evaluated as k / fs + delay + 1 / fs like TouchSim (bit-identical times)
            delay = self.delay_s[model[n]] if delays else 0.0
            t = k / self.fs_hz + delay + 1.0 / self.fs_hz
            times.append(t)
            cols.append(n + c0)
        t_all = np.concatenate(times) if times else np.zeros(0)
        col_all = np.concatenate(cols) if cols else np.zeros(0, np.int64)
        counts = np.bincount(col_all, minlength=total).reshape(n_run, n_loc, n_mod)
        if n_run < repeats:  # noiseless: replicate the single run
            counts = np.broadcast_to(counts, (repeats, n_loc, n_mod))
            t_all = np.tile(t_all, repeats)
        cum = np.concatenate([[0], np.cumsum(counts.ravel())]).astype(np.int64)
        off = np.empty((repeats, n_loc, n_mod + 1), dtype=np.int64)
        off[..., :n_mod] = cum[:-1].reshape(repeats, n_loc, n_mod)
        off[..., n_mod] = cum[1:].reshape(repeats, n_loc, n_mod)[..., -1]
        c = self.constants
        return SpikeResponse(t=t_all, off=off, model_class=c.model_class.copy(), model_index=c.model_index.copy())

    # -- whole pipeline -------------------------------------------------------------------------

    def simulate(
        self,
        trace_mm: np.ndarray,
        *,
        fs_hz: float = 5000.0,
        probe_xy_mm=(0.0, 0.0),
        afferent_xy_mm=((0.0, 0.0),),
        repeats: int = 1,
        noisy: bool = True,
        delays: bool = False,
        rng: np.random.Generator | int | None = None,
    ) -> SpikeResponse:
        """Spike trains of all 17 models at every afferent location (L, 2) for one indentation trace.

        ``trace_mm`` (mm, positive into the skin) is sampled at ``fs_hz``; traces at other rates
        than 5 kHz are linearly interpolated onto the 5 kHz grid first (TouchSim conformance is
        only established at 5 kHz). Spike times are in s from trace sample 0.
        """
        trace = _to_lif_rate(np.asarray(trace_mm, dtype=np.float64), fs_hz, self.fs_hz)
        static, dynamic = self.mechanics(trace, probe_xy_mm, afferent_xy_mm, fs_hz=self.fs_hz)
        return self.spikes(self.drive(static, dynamic), repeats=repeats, noisy=noisy, delays=delays, rng=rng)


def _to_lif_rate(trace: np.ndarray, fs_hz: float, lif_fs_hz: float) -> np.ndarray:
    if trace.ndim != 1:
        raise ValueError("trace must be 1-D (mm)")
    if not np.all(np.isfinite(trace)):
        raise ValueError("trace has non-finite samples")
    if not (np.isfinite(fs_hz) and fs_hz > 0):
        raise ValueError("fs_hz must be positive")
    if fs_hz == lif_fs_hz or trace.size < 2:
        return trace
    t_in = np.arange(trace.size) / fs_hz
    n_out = int(np.floor(t_in[-1] * lif_fs_hz + 1e-9)) + 1
    return np.interp(np.arange(n_out) / lif_fs_hz, t_in, trace)


_MODELS: dict[float, ReferenceModel] = {}


def _model(pin_radius_mm: float) -> ReferenceModel:
    key = float(pin_radius_mm)
    if key not in _MODELS:
        _MODELS[key] = ReferenceModel(pin_radius_mm=key)
    return _MODELS[key]


def reference_trains(
    trace_mm: np.ndarray,
    *,
    fs_hz: float = 5000.0,
    probe_xy_mm=(0.0, 0.0),
    afferent_xy_mm=(0.0, 0.0),
    repeats: int = 1,
    noisy: bool = True,
    delays: bool = False,
    seed: int | None = None,
    pin_radius_mm: float = 0.5,
) -> dict[str, ReferenceTrains]:
    """TouchSim reference spike trains of one afferent location for one probe indentation trace.

    Args:
        trace_mm: (T,) probe indentation (mm, positive into the skin) at ``fs_hz``.
        probe_xy_mm, afferent_xy_mm: probe centre and afferent location (mm).
        repeats: independent noisy repeats (noiseless repeats are identical).
        noisy: add TouchSim's per-sample input noise.
        delays: add each model's conduction delay.
        seed: seed of the noise generator (None: fresh entropy).
        pin_radius_mm: probe radius (mm).

    Returns:
        ``{'SA1'|'RA'|'PC': ReferenceTrains}`` with all models of each class; spike times in s from
        trace sample 0.
    """
    aff = np.asarray(afferent_xy_mm, dtype=np.float64).reshape(1, 2)
    resp = _model(pin_radius_mm).simulate(
        trace_mm, fs_hz=fs_hz, probe_xy_mm=probe_xy_mm, afferent_xy_mm=aff, repeats=repeats, noisy=noisy,
        delays=delays, rng=seed,
    )
    return resp.class_trains(0)
