"""The search space of the fit: a normalised parameter vector <-> :class:`ClassParams`.

Coordinates (13, or 15 when the class's input stage is fitted too), chosen so that one CMA-ES step
size means about the same everywhere:

====  =============  ==========================================================================
 idx  name           mapping
====  =============  ==========================================================================
 0-7  w1..w8         ``w = x / (scale_ch * tau0_samples)``: x = 1 drives the LIF to its threshold
                     (steady state ``V = I tau``) when the channel sits at its typical magnitude
                     ``scale_ch`` (99th percentile of |channel| over the training trials);
                     w5, w6 (the film's two polarities) >= 0 in an excitatory space
   8  log_tau        ``tau_ms = tau0_ms * exp(x)``
 9-10 ih1, ih2       ``ih = x * ih_scale`` (TouchSim's class-median basis weights as the unit)
  11  delay          ``delay_ms = 20 x`` (>= 0; the rig's lag is the parameter file's alignment)
  12  log_isat       ``i_sat = exp(x)`` (LIF units; threshold = 1)
  13  log_lowpass    ``lowpass_hz = lp0_hz * exp(x)``          (input stage only)
  14  lead           ``negative_lead_ms = 10 x``               (input stage only)
====  =============  ==========================================================================

:class:`Coord` names every position; code indexes the vector by those names. A class's input
high-pass (``highpass_hz``), when it has one, is a setting of the fit held at its value, not a coordinate.

``tau0_ms``, ``ih_scale`` and ``lp0_hz`` come from TouchSim's own class parameters
(``data/touchsim_constants.json``: tau column 9 in samples, ih columns 10-11, low-pass factor
column 0 = cutoff / 10 Hz), which also give the starting point of tau, ih and the cutoff.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from enum import IntEnum
from functools import lru_cache

import numpy as np

from ..params import DELAY_RANGE_MS, LEAD_RANGE_MS, TAU_RANGE_MS, ClassParams
from ..settings import CLASSES, OUT_FS_HZ, PACKAGE_DATA


class Coord(IntEnum):
    """Position of each named coordinate in the search vector (the table above)."""

    W1 = 0
    W2 = 1
    W3 = 2
    W4 = 3
    W5 = 4
    W6 = 5
    W7 = 6
    W8 = 7
    LOG_TAU = 8
    IH1 = 9
    IH2 = 10
    DELAY = 11
    LOG_ISAT = 12
    LOG_LOWPASS = 13  #: input stage only
    LEAD = 14  #: input stage only


NAMES = tuple(c.name.lower() for c in Coord)  #: the coordinates' names, in vector order
N_DIM = len(NAMES) - 2  #: without the optional input-stage coordinates
WEIGHTS = slice(Coord.W1, Coord.W8 + 1)  #: the eight input weights w1..w8
IH = slice(Coord.IH1, Coord.IH2 + 1)  #: the two post-spike weights
LOWPASS_RANGE_HZ = (20.0, 2000.0)  #: cutoffs the fit may choose
LEAD_UNIT_MS = 10.0
DELAY_UNIT_MS = 20.0
LOG_ISAT_RANGE = (-8.0, 8.0)  #: bounds of log i_sat (LIF units; threshold = 1)
PVDF_WEIGHTS = (Coord.W5, Coord.W6, Coord.W7, Coord.W8)  #: the PVDF and dPVDF weights
#: the film's weights, its positive and negative part: the PVDF's AC-coupled strain follows the
#: skin's rate of change below its high-pass, so its two polarities are pressing and releasing
FILM_WEIGHTS = (Coord.W5, Coord.W6)
_SAMPLES_PER_MS = OUT_FS_HZ / 1000.0

#: Starting directions of the eight weights per class (normalised units), from the functional roles
#: of the paper's section 2.4: SA1 <- force (+ its rise), RA <- force changes and PVDF transients,
#: PC <- PVDF and its derivative; RA's third start leans on dPVDF, which behind the class low-pass
#: gives a band-pass (TouchSim's RA peaks near 100 Hz). The fitter tries every start.
INITIAL_WEIGHTS = {
    "SA1": ((1.0, 0.0, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.3, 0.0, 0.2, 0.2, 0.0, 0.0)),
    "RA": ((0.0, 0.0, 0.6, 0.6, 0.0, 0.0, 0.3, 0.3), (0.0, 0.0, 0.6, 0.6, 0.5, 0.5, 0.0, 0.0), (0.0, 0.0, 0.2, 0.2, 0.0, 0.0, 1.0, 1.0)),
    "PC": ((0.0, 0.0, 0.1, 0.1, 0.3, 0.3, 0.5, 0.5), (0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0)),
}


@lru_cache(maxsize=1)
def touchsim_class_defaults() -> dict[str, dict[str, float]]:
    """Median TouchSim tau (ms), ih weights, delay (ms) and input low-pass cutoff (Hz) per class."""
    d = json.loads((PACKAGE_DATA / "touchsim_constants.json").read_text())
    cols = d["columns"]
    i_tau, i_h1, i_h2, i_del = cols.index("tau"), cols.index("ih_weight_1"), cols.index("ih_weight_2"), cols.index("delay_ms")
    i_lp = cols.index("lowpass_cutoff_factor")
    out = {}
    for cls in CLASSES:
        m = np.asarray(d["models"][cls], dtype=np.float64)
        out[cls] = {
            "tau_ms": float(np.median(m[:, i_tau])) / _SAMPLES_PER_MS,
            "ih1": float(np.median(m[:, i_h1])),
            "ih2": float(np.median(m[:, i_h2])),
            "delay_ms": float(np.median(m[:, i_del])),
            "lowpass_hz": 10.0 * float(np.median(m[:, i_lp])),
        }
    return out


@dataclass(frozen=True)
class ParamSpace:
    """Mapping between the normalised vector and :class:`ClassParams` for one class."""

    cls: str
    channel_scale: tuple[float, float, float, float]  # typical |ST|, |dST|, |PVDF|, |dPVDF|
    tau0_ms: float
    ih_scale: tuple[float, float]
    lp0_hz: float | None = None  #: None: the input stage (low-pass, lead) is not fitted (13 coordinates)
    pvdf: bool = True  #: False: the PVDF and dPVDF weights (w5..w8) are held at 0 (a class on the SingleTact alone)
    #: True: the film's weights (w5, w6) are bounded below at 0, so pressing and releasing both excite
    #: (a class whose on and off responses are both excitatory, as TouchSim's RA)
    excitatory: bool = False
    hp_hz: float | None = None  #: the class's input high-pass cutoff (Hz), held fixed (not searched); None: no high-pass

    @classmethod
    def for_class(cls, name: str, channel_scale, input_stage: bool = False, pvdf: bool = True, excitatory: bool = False,
                  highpass_hz: float | None = None) -> "ParamSpace":
        if name not in CLASSES:
            raise ValueError(f"unknown class {name!r}")
        sc = np.asarray(channel_scale, np.float64)
        if sc.shape != (4,) or not np.all(np.isfinite(sc)) or np.any(sc <= 0):
            raise ValueError("channel_scale must be four positive numbers")
        ts = touchsim_class_defaults()[name]
        ih_scale = (max(abs(ts["ih1"]), 0.05), max(abs(ts["ih2"]), 0.005))
        return cls(name, tuple(float(v) for v in sc), ts["tau_ms"], ih_scale, ts["lowpass_hz"] if input_stage else None, pvdf, excitatory,
                   highpass_hz)

    @property
    def n_dim(self) -> int:
        return N_DIM + 2 * (self.lp0_hz is not None)

    # -- bounds -------------------------------------------------------------------------------

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.full(self.n_dim, -30.0)
        hi = np.full(self.n_dim, 30.0)
        lo[Coord.LOG_TAU], hi[Coord.LOG_TAU] = np.log(TAU_RANGE_MS[0] / self.tau0_ms), np.log(TAU_RANGE_MS[1] / self.tau0_ms)
        lo[IH], hi[IH] = -20.0, 2.0
        lo[Coord.DELAY], hi[Coord.DELAY] = DELAY_RANGE_MS[0] / DELAY_UNIT_MS, DELAY_RANGE_MS[1] / DELAY_UNIT_MS
        lo[Coord.LOG_ISAT], hi[Coord.LOG_ISAT] = LOG_ISAT_RANGE
        if self.excitatory:
            lo[list(FILM_WEIGHTS)] = 0.0
        if self.lp0_hz is not None:
            lo[Coord.LOG_LOWPASS], hi[Coord.LOG_LOWPASS] = (np.log(f / self.lp0_hz) for f in LOWPASS_RANGE_HZ)
            lo[Coord.LEAD], hi[Coord.LEAD] = LEAD_RANGE_MS[0] / LEAD_UNIT_MS, LEAD_RANGE_MS[1] / LEAD_UNIT_MS
        return lo, hi

    def fixed(self) -> dict[int, float]:
        """Coordinates held at a value (not searched): w5..w8 = 0 without PVDF."""
        return {} if self.pvdf else {int(i): 0.0 for i in PVDF_WEIGHTS}

    def stds(self) -> np.ndarray:
        """Per-coordinate initial CMA-ES standard deviations (relative to sigma0 = 1)."""
        s = np.full(self.n_dim, 0.5)
        s[Coord.LOG_ISAT] = 1.0
        return s

    def clip(self, x: np.ndarray) -> np.ndarray:
        lo, hi = self.bounds()
        y = np.clip(np.asarray(x, np.float64), lo, hi)
        for i, v in self.fixed().items():
            y[..., i] = v
        return y

    # -- mapping ------------------------------------------------------------------------------

    def _wscale(self) -> np.ndarray:
        tau0_samples = self.tau0_ms * _SAMPLES_PER_MS
        return 1.0 / (np.repeat(np.asarray(self.channel_scale), 2) * tau0_samples)

    def decode(self, x: np.ndarray) -> ClassParams:
        x = self.clip(x)
        return ClassParams(
            weights=[float(v) for v in x[WEIGHTS] * self._wscale()],
            tau_ms=float(np.clip(self.tau0_ms * np.exp(x[Coord.LOG_TAU]), *TAU_RANGE_MS)),
            ih=[float(x[Coord.IH1] * self.ih_scale[0]), float(x[Coord.IH2] * self.ih_scale[1])],
            delay_ms=float(np.clip(x[Coord.DELAY] * DELAY_UNIT_MS, *DELAY_RANGE_MS)),
            i_sat=float(np.clip(np.exp(x[Coord.LOG_ISAT]), 0.0, 1e6)),
            lowpass_hz=None if self.lp0_hz is None else float(np.clip(self.lp0_hz * np.exp(x[Coord.LOG_LOWPASS]), *LOWPASS_RANGE_HZ)),
            negative_lead_ms=0.0 if self.lp0_hz is None else float(np.clip(x[Coord.LEAD] * LEAD_UNIT_MS, *LEAD_RANGE_MS)),
            highpass_hz=self.hp_hz,
        )

    def encode(self, p: ClassParams) -> np.ndarray:
        x = np.empty(self.n_dim)
        x[WEIGHTS] = np.asarray(p.weights) / self._wscale()
        x[Coord.LOG_TAU] = np.log(p.tau_ms / self.tau0_ms)
        x[Coord.IH1] = p.ih[0] / self.ih_scale[0]
        x[Coord.IH2] = p.ih[1] / self.ih_scale[1]
        x[Coord.DELAY] = p.delay_ms / DELAY_UNIT_MS
        x[Coord.LOG_ISAT] = np.log(p.i_sat) if p.i_sat > 0 else LOG_ISAT_RANGE[1]  # 0 (no saturation) ~ the largest i_sat
        if self.lp0_hz is not None:  # no filter ~ the highest cutoff
            x[Coord.LOG_LOWPASS] = np.log((p.lowpass_hz if p.lowpass_hz is not None else LOWPASS_RANGE_HZ[1]) / self.lp0_hz)
            x[Coord.LEAD] = p.negative_lead_ms / LEAD_UNIT_MS
        return x

    def initial(self, delay_ms: float = 0.0, variant: int = 0) -> np.ndarray:
        """Start: a weight direction of the class, TouchSim's tau, ih and cutoff, mild saturation."""
        x = np.zeros(self.n_dim)
        x[WEIGHTS] = INITIAL_WEIGHTS[self.cls][variant]
        x[Coord.LOG_TAU] = 0.0
        ts = touchsim_class_defaults()[self.cls]
        x[Coord.IH1] = ts["ih1"] / self.ih_scale[0]
        x[Coord.IH2] = ts["ih2"] / self.ih_scale[1]
        x[Coord.DELAY] = delay_ms / DELAY_UNIT_MS
        x[Coord.LOG_ISAT] = 3.0
        return self.clip(x)

    def with_gain(self, x: np.ndarray, gain: float) -> np.ndarray:
        """Scale the eight weights by ``gain`` (used by the initial gain search)."""
        y = np.array(x, np.float64)
        y[WEIGHTS] *= gain
        return self.clip(y)
