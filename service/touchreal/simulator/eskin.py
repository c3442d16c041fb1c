"""Physics of the simulated e-skin: SingleTact + PVDF taxels under silicone, on a 2 kHz tick clock.

Pure computation (numpy/scipy/numba, no I/O). :class:`ESkin` turns the contact delivered by the
stimulator (probe or comb indentation after the robot dynamics, exciter displacement, contact
position, comb position) into raw sensor streams of N taxels, chunk by chunk, keeping every state,
so that any chunking of the same input gives bit-identical output.

Signal path, per 2 kHz tick (``FS_HZ``) and taxel:

1. exciter displacement (mm) -> frequency-dependent mechanical coupling (resonant low-pass);
   contact depth ``p = robot depth + coupled vibration`` (mm).
2. silicone compliance with hysteresis: the skin under the probe follows ``max(p, 0)`` with a fast
   compression and a slow recovery time constant (``z``, mm): delay, smoothing, slower release.
   A sliding comb adds its tooth relief (a square profile smoothed by the silicone above each
   sensor, :func:`tooth_relief`) after this lag: sliding moves the pattern, it does not compress.
3. SingleTact: ``F = g_st(r) * k * z**n`` (N), quasi-linear viscoelastic relaxation (Prony series),
   sensor low-pass and latency, sampled at 100 Hz (every 20th tick), baseline offset, wander and
   noise added, quantised to 0.01 N and clipped to [0, 10] N.
4. PVDF: film strain ``w = alpha * p + (1 - alpha) * z`` (mm) plus a quadratic (membrane) term of
   the vibration and the comb relief, saturating as the film bottoms out,
   scaled by the low-frequency radial gain, low-passed by a distance-dependent spreading filter
   (higher frequencies decay faster with distance), two electrical high-pass stages (piezo leakage
   and AC coupling), anti-alias low-pass, then mains hum (50 Hz, strong odd harmonics), broadband
   noise and baseline wander, and a 12-bit ADC over +-1.65 V (V).

Radial attenuation uses an anisotropic distance (shifted centre, elliptical metric): steep for the
8 mm SingleTact (logistic edge near its rim), gradual for the PVDF film. Every constant lives in
:class:`SkinParams` with its unit and where its value comes from (fitted to rig-v1 statistics,
taken from the paper, or assumed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numba
import numpy as np
from scipy import signal

from ..preprocess.filters import SosFilter
from ..settings import PVDF_FS_HZ, PVDF_RANGE_V, ST_FS_HZ, ST_RANGE_N, ST_RESOLUTION_N
from ..raw import RawChunk

FS_HZ = PVDF_FS_HZ  #: internal tick rate (Hz) = PVDF sample rate
ST_DECIMATION = int(round(FS_HZ / ST_FS_HZ))  #: ticks per SingleTact sample (20)
ADC_STEP_V = (PVDF_RANGE_V[1] - PVDF_RANGE_V[0]) / 4096.0  #: PVDF 12-bit ADC step (V)


@dataclass(frozen=True)
class SkinParams:
    """Physical constants of the e-skin (units in the names; provenance in the comments).

    "fit" = fitted to statistics of the simulated rig recordings rig-v1 (see docs/simulator.md),
    "paper" = from the TouchReal paper, "assumed" = plausible value not identifiable from rig-v1.
    """

    # --- silicone / contact mechanics ---
    stiffness_n_mm: float = 2.05  #: k in F = k z^n (N / mm^n) for the 1 mm probe (fit: hold force vs depth)
    exponent: float = 1.78  #: n, contact stiffening exponent (fit)
    comb_stiffness_factor: float = 2.6  #: comb contact is stiffer than the probe (fit: texture hold force)
    tau_press_s: float = 0.0115  #: skin compression time constant (s) (fit: ramp force onsets)
    tau_release_s: float = 0.064  #: skin recovery time constant (s), slower: hysteresis (fit: release tails)
    prony_g: tuple[float, float] = (0.30, 0.08)  #: relaxation fractions of the Prony series (fit)
    prony_tau_s: tuple[float, float] = (0.020, 5.3)  #: relaxation time constants (s) (fit: overshoot, hold decay)
    zero_jitter_mm: float = 0.01  #: sd of the skin-surface position error per instance (mm) (assumed)
    stiffness_jitter: float = 0.02  #: sd of the per-taxel relative stiffness (fit: hold force spread)
    # --- SingleTact sensor ---
    st_lowpass_hz: float = 36.0  #: sensor 2nd-order low-pass cutoff (Hz) (fit)
    st_latency_s: float = 0.007  #: sensor output latency (s) (fit: ST onset vs PVDF onset)
    st_offset_n: float = 0.037  #: mean zero-force baseline (N) (fit: pre-contact baseline)
    st_offset_sd_n: float = 0.012  #: sd of the baseline between instances (N) (fit)
    st_gain: float = 1.0  #: sensitivity: reading per N of contact force (1 for the rig-v1 build; see simulator/build.py)
    st_noise_n: float = 0.004  #: white noise sd before quantisation (N) (fit: baseline sd 0.005 N)
    st_wander_n: float = 0.004  #: baseline wander sd (N) (assumed)
    st_wander_tau_s: float = 2.0  #: baseline wander time constant (s) (assumed)
    # --- spatial response (distances in mm from the contact centre) ---
    st_edge_mm: float = 3.4  #: SingleTact radial gain: logistic edge radius (mm) (fit: spatial scan)
    st_edge_width_mm: float = 0.7  #: width of that edge (mm) (fit)
    st_center_mm: tuple[float, float] = (0.0, 0.15)  #: effective SingleTact centre (mm) (fit: anisotropy)
    st_axis_ratio: float = 1.05  #: elliptical metric x/y for the SingleTact (assumed, mild)
    pv_decay_mm: float = 6.8  #: PVDF low-frequency radial decay length (mm) (fit: 90 Hz scan)
    pv_edge_mm: float = 10.7  #: PVDF film edge (mm) (fit)
    pv_edge_width_mm: float = 0.8  #: width of the film edge (mm) (fit)
    pv_center_mm: tuple[float, float] = (-0.4, -0.2)  #: effective PVDF centre (mm) (fit: wire-side asymmetry)
    pv_axis_ratio: float = 1.12  #: elliptical metric x/y for the film (assumed: rectangular film, mild)
    pv_spread_hz: float = 1500.0  #: spreading low-pass cutoff at the centre (Hz) (fit: 265 vs 90 Hz scan)
    pv_spread_decay_mm: float = 4.2  #: cutoff falls as exp(-r / this) (mm) (fit)
    comb_radius_mm: float = 6.0  #: half-size of the comb footprint (mm) (assumed: covers the sensor)
    # --- PVDF film and electronics ---
    pv_gain_v_mm: float = 7.2  #: film strain -> voltage gain before the high-pass stages (V/mm) (fit: ramp peaks)
    pv_saturation_mm: float = 2.45  #: strain saturation depth (mm) (fit)
    pv_probe_fraction: float = 0.92  #: alpha: share of strain following the probe rather than the skin (fit)
    pv_membrane_per_mm: float = 0.6  #: quadratic (membrane) film strain per mm of vibration (1/mm) (fit: sine 2nd harmonic)
    pv_tau_leak_s: float = 0.0015  #: piezo leakage high-pass time constant (s) (fit)
    pv_tau_ac_s: float = 0.105  #: AC-coupling high-pass time constant (s) (fit)
    pv_antialias_hz: float = 700.0  #: conditioning 2nd-order low-pass cutoff (Hz) (assumed)
    pv_gain_jitter: float = 0.05  #: sd of the per-taxel relative film sensitivity (assumed)
    pv_noise_v: float = 0.0019  #: broadband noise sd (V) (fit: ASD floor 6e-5 V/sqrt(Hz))
    pv_wander_v: float = 0.0045  #: slow baseline wander sd (V) (fit: pre-stimulus means)
    pv_wander_tau_s: float = 1.0  #: its time constant (s) (fit: 10 Hz excess)
    pv_flicker_v: float = 0.0006  #: faster wander sd (V) (fit: 20-30 Hz excess)
    pv_flicker_tau_s: float = 0.008  #: its time constant (s) (fit)
    # --- mains pickup ---
    mains_hz: float = 50.0  #: nominal mains frequency (Hz)
    mains_hz_sd: float = 0.03  #: sd of the mains frequency between instances (Hz) (fit)
    mains_v: float = 0.0095  #: median 50 Hz amplitude (V) (fit)
    mains_v_log_sd: float = 0.25  #: log-sd of that amplitude between instances (fit)
    mains_harmonics: tuple[float, ...] = (1.0, 0.12, 0.50, 0.044, 0.245, 0.024, 0.123, 0.017)  #: h1..h8 / h1 (fit)
    mains_contact_gain: float = 0.17  #: extra pickup while the grounded probe touches the skin (fit)
    mains_taxel_log_sd: float = 0.15  #: log-sd of the per-taxel pickup (assumed)
    # --- exciter coupling and drive calibration ---
    exciter_resonance_hz: float = 150.0  #: exciter-probe-skin resonance (Hz) (assumed; paper: resonance, HF loss)
    exciter_damping: float = 0.3  #: damping ratio of that resonance (assumed)
    sine_target_v: float = 0.145  #: PVDF amplitude the drive is calibrated to (V) (fit: sine trials)
    drive_calibration_sd: float = 0.08  #: relative error of the per-frequency calibration (fit: spread)
    drive_calibration_seed: int = 2024  #: fixes the calibration errors of this simulated rig
    # --- textures (comb tooth relief, square profile smoothed through the silicone) ---
    tooth_relief_st_mm: float = 0.065  #: effective tooth relief seen by the SingleTact (mm) (fit: ST modulation)
    tooth_depth_st_mm: float = 0.63  #: depth at which the SingleTact senses it (mm) (fit: 2 vs 4 mm combs)
    tooth_relief_pv_mm: float = 0.085  #: effective tooth relief seen by the film (mm) (fit: PVDF rms)
    tooth_depth_pv_mm: float = 0.12  #: depth of the film's (shear) sensitivity (mm) (fit: PVDF rms vs spacing)


@dataclass
class ContactInput:
    """What the stimulator delivers to the skin, one row per 2 kHz tick.

    ``depth_mm`` (n,) contactor indentation after the robot dynamics (mm, > 0 into the skin);
    ``vib_mm`` (n,) exciter displacement (mm) before the skin coupling; ``xy_mm`` (n, 2) contact
    centre (mm); ``comb`` (n,) True where the contactor is the comb; ``tex_x_mm`` (n,) lateral comb
    position (mm); ``tex_spacing_mm`` (n,) tooth spacing (mm), 0 where there is no texture.
    """

    depth_mm: np.ndarray
    vib_mm: np.ndarray
    xy_mm: np.ndarray
    comb: np.ndarray
    tex_x_mm: np.ndarray
    tex_spacing_mm: np.ndarray

    @classmethod
    def still(cls, n: int, depth_mm: float = 0.0, xy_mm=(0.0, 0.0)) -> "ContactInput":
        """A constant probe contact of ``n`` ticks (no vibration, no texture)."""
        return cls(
            depth_mm=np.full(n, float(depth_mm)),
            vib_mm=np.zeros(n),
            xy_mm=np.tile(np.asarray(xy_mm, float), (n, 1)),
            comb=np.zeros(n, bool),
            tex_x_mm=np.zeros(n),
            tex_spacing_mm=np.zeros(n),
        )

    def __len__(self) -> int:
        return int(self.depth_mm.shape[0])


# ----------------------------------------------------------------------------------------------
# compiled kernels (state arrays are updated in place)


@numba.njit(cache=True, nogil=True)
def _hysteretic_lag(p, z, a_press, a_release):  # pragma: no cover - compiled
    n, m = p.shape
    out = np.empty_like(p)
    for k in range(n):
        for i in range(m):
            target = p[k, i] if p[k, i] > 0.0 else 0.0
            d = target - z[i]
            z[i] += (a_press if d > 0.0 else a_release) * d
            out[k, i] = z[i]
    return out


@numba.njit(cache=True, nogil=True)
def _spreading_lowpass(s, a, state):  # pragma: no cover - compiled
    # two cascaded unity-DC one-pole low-passes; a has 1 row (constant) or one row per tick
    n, m = s.shape
    step = 1 if a.shape[0] == n else 0
    out = np.empty_like(s)
    for k in range(n):
        for i in range(m):
            ak = a[k * step, i]
            y1 = ak * state[0, i] + (1.0 - ak) * s[k, i]
            y2 = ak * state[1, i] + (1.0 - ak) * y1
            state[0, i] = y1
            state[1, i] = y2
            out[k, i] = y2
    return out


# ----------------------------------------------------------------------------------------------
# linear building blocks (also used by the drive calibration)


def _one_pole_hp(tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """One-pole high-pass with unity gain at high frequency, (b, a) at FS_HZ."""
    a = np.exp(-1.0 / (FS_HZ * tau_s))
    return np.array([(1 + a) / 2, -(1 + a) / 2]), np.array([1.0, -a])


def _prony_hp(tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Relaxing element of the Prony series: x_i' = F' - x_i / tau, (b, a) at FS_HZ."""
    return np.array([1.0, -1.0]), np.array([1.0, -np.exp(-1.0 / (FS_HZ * tau_s))])


def _st_sos(p: SkinParams) -> np.ndarray:
    """SingleTact dynamics as second-order sections: Prony relaxation (normalised to the long-term
    force) in parallel form merged into one biquad, then the sensor low-pass."""
    g_sum = sum(p.prony_g)
    (b1, a1), (b2, a2) = (_prony_hp(t) for t in p.prony_tau_s)
    c1, c2 = (g / (1.0 - g_sum) for g in p.prony_g)
    den = np.convolve(a1, a2)
    num = den + c1 * np.convolve(b1, a2) + c2 * np.convolve(b2, a1)
    relax = np.concatenate([num, den])[None, :]
    return np.vstack([relax, signal.butter(2, p.st_lowpass_hz, fs=FS_HZ, output="sos")])


def _pv_sos(p: SkinParams) -> np.ndarray:
    """PVDF electronics as second-order sections: leakage and AC-coupling high-passes, anti-alias low-pass."""
    (b1, a1), (b2, a2) = _one_pole_hp(p.pv_tau_leak_s), _one_pole_hp(p.pv_tau_ac_s)
    hp = np.concatenate([np.convolve(b1, b2), np.convolve(a1, a2)])[None, :]
    return np.vstack([hp, signal.butter(2, p.pv_antialias_hz, fs=FS_HZ, output="sos")])


def _exciter_coupling(p: SkinParams) -> tuple[np.ndarray, np.ndarray]:
    """Exciter -> contact displacement: resonant 2nd-order low-pass, unity at DC (bilinear, prewarped)."""
    wp = 2 * FS_HZ * np.tan(np.pi * p.exciter_resonance_hz / FS_HZ)
    return signal.bilinear([wp * wp], [1.0, 2 * p.exciter_damping * wp, wp * wp], fs=FS_HZ)


def _logistic(x: np.ndarray, edge: float, width: float) -> np.ndarray:
    return 0.5 * (1.0 - np.tanh((x - edge) / (2.0 * width)))


def st_radial_gain(r_mm, p: SkinParams = SkinParams()) -> np.ndarray:
    """SingleTact gain (0-1) at an (anisotropy-corrected) distance ``r_mm`` (mm) from its centre."""
    r = np.asarray(r_mm, float)
    return _logistic(r, p.st_edge_mm, p.st_edge_width_mm) / _logistic(0.0, p.st_edge_mm, p.st_edge_width_mm)


def pv_radial_gain(r_mm, p: SkinParams = SkinParams()) -> np.ndarray:
    """PVDF low-frequency gain (0-1) at distance ``r_mm`` (mm): exponential decay times the film edge."""
    r = np.asarray(r_mm, float)
    edge = _logistic(r, p.pv_edge_mm, p.pv_edge_width_mm) / _logistic(0.0, p.pv_edge_mm, p.pv_edge_width_mm)
    return np.exp(-r / p.pv_decay_mm) * edge


def pv_spread_cutoff_hz(r_mm, p: SkinParams = SkinParams()) -> np.ndarray:
    """Cutoff (Hz) of the distance-dependent spreading low-pass: vibration decays faster at high frequency."""
    return p.pv_spread_hz * np.exp(-np.asarray(r_mm, float) / p.pv_spread_decay_mm)


def _aniso_distance(dx: np.ndarray, dy: np.ndarray, ratio: float) -> np.ndarray:
    s = np.sqrt(ratio)
    return np.hypot(dx / s, dy * s)


def tooth_relief(x_mm: np.ndarray, spacing_mm: np.ndarray, depth_mm: float) -> np.ndarray:
    """Square comb relief (+-1) seen through ``depth_mm`` of silicone (Poisson smoothing), exact sum.

    Every odd harmonic k of the square wave is attenuated by exp(-2 pi k depth / spacing); the sum
    is (2/pi) arctan(sin(2 pi x / spacing) / sinh(2 pi depth / spacing)). 0 where spacing <= 0.
    """
    x = np.asarray(x_mm, float)
    lam = np.asarray(spacing_mm, float)
    ok = lam > 0
    safe = np.where(ok, lam, 1.0)
    with np.errstate(over="ignore"):
        m = (2 / np.pi) * np.arctan(np.sin(2 * np.pi * x / safe) / np.sinh(2 * np.pi * depth_mm / safe))
    return np.where(ok, m, 0.0)


def pvdf_small_signal_gain(freq_hz: float, preload_mm: float, p: SkinParams = SkinParams()) -> float:
    """|PVDF volts per mm of exciter displacement| at ``freq_hz`` (Hz) for a probe resting at ``preload_mm``.

    The linearised film path at the sensor centre: exciter coupling, film strain slope at the
    preload, leakage and AC-coupling high-passes, anti-alias low-pass (V/mm).
    """
    f = np.array([float(freq_hz)])
    h = np.abs(signal.freqz(*_exciter_coupling(p), worN=f, fs=FS_HZ)[1])
    h = h * np.abs(signal.sosfreqz(_pv_sos(p), worN=f, fs=FS_HZ)[1])
    slope = p.pv_gain_v_mm * np.exp(-max(preload_mm, 0.0) / p.pv_saturation_mm)
    return float(h[0] * slope * p.pv_probe_fraction)


def vibration_drive_mm(freq_hz: float, preload_mm: float, p: SkinParams = SkinParams()) -> float:
    """Exciter displacement amplitude (mm) giving about ``p.sine_target_v`` of PVDF at ``freq_hz`` (Hz).

    This is the rig's per-frequency drive calibration (paper, section 2.2): computed from the
    small-signal model with a fixed relative error per frequency (``drive_calibration_sd``), as an
    empirical adjustment would leave.
    """
    err = np.random.default_rng([p.drive_calibration_seed, int(round(freq_hz * 1000))]).normal(0.0, p.drive_calibration_sd)
    return float(p.sine_target_v * (1.0 + err) / pvdf_small_signal_gain(freq_hz, preload_mm, p))


def preload_depth_mm(force_n: float, p: SkinParams = SkinParams()) -> float:
    """Probe depth (mm) whose long-term force at the sensor centre is ``force_n`` (N)."""
    return float((max(force_n, 0.0) / p.stiffness_n_mm) ** (1.0 / p.exponent))


# ----------------------------------------------------------------------------------------------


def _ou(tau_s: float, sd: float, fs: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Ornstein-Uhlenbeck process as a filter on unit white noise: (b, a, phi) at ``fs``."""
    phi = float(np.exp(-1.0 / (fs * tau_s)))
    return np.array([sd * np.sqrt(1 - phi * phi)]), np.array([1.0, -phi]), phi


class _BlockStream:
    """Rows of a stateful generator produced in fixed blocks and handed out in any slice sizes.

    Generating in fixed blocks makes the output independent of how reads are chunked, and
    amortises the per-call cost of random draws and filters over many small reads.
    """

    def __init__(self, make_block, block: int, width: int) -> None:
        self._make = make_block
        self._block = block
        self._width = width
        self._buf: np.ndarray | None = None
        self._pos = 0

    def take(self, n: int) -> np.ndarray:
        if n <= 0:
            return np.zeros((0, self._width))
        parts = []
        while n > 0:
            if self._buf is None or self._pos >= self._buf.shape[0]:
                self._buf, self._pos = self._make(self._block), 0
            m = min(n, self._buf.shape[0] - self._pos)
            parts.append(self._buf[self._pos : self._pos + m])
            self._pos += m
            n -= m
        return parts[0] if len(parts) == 1 else np.concatenate(parts)


_NOISE_BLOCK_TICKS = 2000  # 1 s of PVDF noise per block


def instance_constants(p: SkinParams, n: int, inst: np.random.Generator) -> tuple:
    """One skin's build spread, drawn in this order from ``inst``: per taxel stiffness (N/mm), zero
    (mm), SingleTact offset (N) and PVDF gain (V/mm); the mains frequency (Hz), its harmonics'
    amplitudes (V) and phases (rad); per taxel mains pickup (a gain)."""
    stiff = p.stiffness_n_mm * np.exp(inst.normal(0.0, p.stiffness_jitter, n))
    zero = inst.normal(0.0, p.zero_jitter_mm, n)
    st_offset = np.maximum(inst.normal(p.st_offset_n, p.st_offset_sd_n, n), 0.0)
    pv_gain = p.pv_gain_v_mm * np.exp(inst.normal(0.0, p.pv_gain_jitter, n))
    mains_hz = float(inst.normal(p.mains_hz, p.mains_hz_sd))
    h = np.asarray(p.mains_harmonics, float)
    mains_amp = p.mains_v * np.exp(inst.normal(0.0, p.mains_v_log_sd)) * h
    mains_phase = inst.uniform(0.0, 2 * np.pi, h.size)
    pickup = np.exp(inst.normal(0.0, p.mains_taxel_log_sd, n)) if n > 1 else np.ones(1)
    return stiff, zero, st_offset, pv_gain, mains_hz, mains_amp, mains_phase, pickup


class ESkin:
    """Stateful simulated e-skin of N taxels (SingleTact + PVDF each) on the 2 kHz tick clock.

    Args:
        taxels_xy_mm: (N, 2) taxel centres (mm) in the frame of the contact positions.
        params: physical constants.
        seed: seeds every random draw (instance constants and noise streams), so the same seed and
            input give identical arrays, whatever the chunking.
        t0_s: time (s) of tick 0, in [0, 0.5 ms); random if None (first PVDF sample).
        st_phase_ticks: tick (0-19) of the first SingleTact sample; random if None.
        initial_depth_mm, initial_xy_mm: a contact already at rest when the clock starts (the
            exciter probe resting on the skin); states start relaxed at that contact.

    ``process(contact)`` consumes the next ``len(contact)`` ticks and returns a
    :class:`~touchreal.raw.RawChunk` (``st`` (m, N) N, ``pvdf`` (n, N) V, float32).
    """

    def __init__(
        self,
        taxels_xy_mm: Sequence[Sequence[float]] | np.ndarray = ((0.0, 0.0),),
        params: SkinParams | None = None,
        seed: int | np.random.SeedSequence | None = None,
        *,
        t0_s: float | None = None,
        st_phase_ticks: int | None = None,
        initial_depth_mm: float = 0.0,
        initial_xy_mm: Sequence[float] = (0.0, 0.0),
    ) -> None:
        p = self.params = params or SkinParams()
        xy = np.atleast_2d(np.asarray(taxels_xy_mm, dtype=float))
        if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] < 1:
            raise ValueError("taxels_xy_mm must be (N, 2) with N >= 1")
        self.taxels_xy_mm = xy
        n_tax = self.n_taxels = xy.shape[0]
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
        inst, *streams = (np.random.default_rng(s) for s in ss.spawn(6))
        self._rng_st_white, self._rng_st_wander, self._rng_pv_white, self._rng_pv_wander, self._rng_pv_flicker = streams

        # clock
        self.t0_s = float(inst.uniform(0.0, 1.0 / FS_HZ)) if t0_s is None else float(t0_s)
        self.st_phase = int(inst.integers(0, ST_DECIMATION)) if st_phase_ticks is None else int(st_phase_ticks) % ST_DECIMATION
        self.tick = 0
        self._geo_cache: tuple | None = None

        # instance constants (per taxel)
        (self._stiff, self._zero, self._st_offset, self._pv_gain, self.mains_hz, self._mains_amp, self._mains_phase,
         self._mains_taxel) = instance_constants(p, n_tax, inst)

        # filters
        self._coup = _exciter_coupling(p)
        self._st_sos = _st_sos(p)
        self._pv_sos = _pv_sos(p)
        self._a_press = 1.0 - np.exp(-1.0 / (FS_HZ * p.tau_press_s))
        self._a_release = 1.0 - np.exp(-1.0 / (FS_HZ * p.tau_release_s))
        self._st_delay_n = int(round(p.st_latency_s * FS_HZ))
        self._ou_st = _ou(p.st_wander_tau_s, p.st_wander_n, ST_FS_HZ)
        self._ou_pv = _ou(p.pv_wander_tau_s, p.pv_wander_v, FS_HZ)
        self._ou_fl = _ou(p.pv_flicker_tau_s, p.pv_flicker_v, FS_HZ)

        # states: relaxed at the initial contact
        init = ContactInput.still(1, initial_depth_mm, initial_xy_mm)
        g_st, g_pv, a_sp = self._geometry(init)
        z0 = np.maximum(initial_depth_mm + self._zero, 0.0)
        fe0 = (p.st_gain * g_st * self._stiff * z0 ** p.exponent)[0]
        s0 = self._film(initial_depth_mm + self._zero[None, :], z0[None, :], g_pv)[0]
        self._z = z0.copy()
        self._zi_coup = np.zeros(2)
        self._st_filter = SosFilter(self._st_sos, n_tax, initial=fe0)
        self._st_delay = np.tile(fe0, (self._st_delay_n, 1))
        self._spread = np.tile(s0, (2, 1))
        self._pv_filter = SosFilter(self._pv_sos, n_tax, initial=s0)
        self._zi_ou_st = self._ou_st[2] * inst.normal(0.0, p.st_wander_n, (1, n_tax))
        self._zi_ou_pv = self._ou_pv[2] * inst.normal(0.0, p.pv_wander_v, (1, n_tax))
        self._zi_ou_fl = self._ou_fl[2] * inst.normal(0.0, p.pv_flicker_v, (1, n_tax))
        self._st_noise = _BlockStream(self._st_noise_block, _NOISE_BLOCK_TICKS // ST_DECIMATION, n_tax)
        self._pv_noise = _BlockStream(self._pv_noise_block, _NOISE_BLOCK_TICKS, n_tax)

    def _st_noise_block(self, m: int) -> np.ndarray:
        """Baseline wander + white noise of the next ``m`` SingleTact samples (m, N) (N)."""
        n_tax = self.n_taxels
        w, self._zi_ou_st = signal.lfilter(
            self._ou_st[0], self._ou_st[1], self._rng_st_wander.standard_normal((m, n_tax)), axis=0, zi=self._zi_ou_st
        )
        return w + self.params.st_noise_n * self._rng_st_white.standard_normal((m, n_tax))

    def _pv_noise_block(self, n: int) -> np.ndarray:
        """Wander + flicker + broadband noise of the next ``n`` PVDF ticks (n, N) (V)."""
        n_tax = self.n_taxels
        w, self._zi_ou_pv = signal.lfilter(
            self._ou_pv[0], self._ou_pv[1], self._rng_pv_wander.standard_normal((n, n_tax)), axis=0, zi=self._zi_ou_pv
        )
        fl, self._zi_ou_fl = signal.lfilter(
            self._ou_fl[0], self._ou_fl[1], self._rng_pv_flicker.standard_normal((n, n_tax)), axis=0, zi=self._zi_ou_fl
        )
        return w + fl + self.params.pv_noise_v * self._rng_pv_white.standard_normal((n, n_tax))

    # ------------------------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        """Time (s) of the next tick."""
        return self.t0_s + self.tick / FS_HZ

    def _geometry(self, c: ContactInput) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-taxel SingleTact gain, PVDF gain and spreading-filter pole; 1 row if the contact is still."""
        p = self.params
        xy, comb = c.xy_mm, c.comb
        still = bool(np.all(xy == xy[0]) and np.all(comb == comb[0]))
        key = (float(xy[0, 0]), float(xy[0, 1]), bool(comb[0]))
        if still and self._geo_cache is not None and self._geo_cache[0] == key:
            return self._geo_cache[1]
        if still:
            xy, comb = xy[:1], comb[:1]
        rel = xy[:, None, :] - self.taxels_xy_mm[None, :, :]
        cut = np.where(comb, p.comb_radius_mm, 0.0)[:, None]
        d_st = rel - np.asarray(p.st_center_mm)
        d_pv = rel - np.asarray(p.pv_center_mm)
        r_st = np.maximum(_aniso_distance(d_st[..., 0], d_st[..., 1], p.st_axis_ratio) - cut, 0.0)
        r_pv = np.maximum(_aniso_distance(d_pv[..., 0], d_pv[..., 1], p.pv_axis_ratio) - cut, 0.0)
        a_sp = np.exp(-2 * np.pi * pv_spread_cutoff_hz(r_pv, p) / FS_HZ)
        out = (st_radial_gain(r_st, p), pv_radial_gain(r_pv, p), np.ascontiguousarray(a_sp))
        if still:
            self._geo_cache = (key, out)
        return out

    def _film(self, w_probe: np.ndarray, z: np.ndarray, g_pv: np.ndarray) -> np.ndarray:
        """Film strain signal (V before the electrical stages) from probe-following and skin depth (mm)."""
        p = self.params
        w = p.pv_probe_fraction * w_probe + (1.0 - p.pv_probe_fraction) * z
        sat = p.pv_saturation_mm
        return g_pv * self._pv_gain * sat * (1.0 - np.exp(-np.maximum(w, 0.0) / sat))

    def process(self, c: ContactInput) -> RawChunk:
        """Simulate the next ``len(c)`` ticks; return the SingleTact and PVDF samples that fall in them."""
        p = self.params
        n, n_tax = len(c), self.n_taxels
        k = self.tick + np.arange(n)
        if n == 0:
            e = np.zeros(0)
            return RawChunk(e, np.zeros((0, n_tax), np.float32), e, np.zeros((0, n_tax), np.float32))

        # contact: exciter coupling, comb relief, silicone hysteresis
        vib = np.asarray(c.vib_mm, float)
        if vib.any() or self._zi_coup.any():  # idle exciter: exact zeros, skip the filter
            vib, self._zi_coup = signal.lfilter(*self._coup, vib, zi=self._zi_coup)
        base = (np.asarray(c.depth_mm, float) + vib)[:, None] + self._zero[None, :]
        p_pv = base + p.pv_membrane_per_mm * (vib * vib)[:, None]
        z = _hysteretic_lag(np.ascontiguousarray(base), self._z, self._a_press, self._a_release)
        z_st = z
        if np.any(c.tex_spacing_mm > 0):
            # a sliding comb translates its pressure pattern laterally: no extra bulk compression,
            # so the relief is added after the silicone hysteresis
            rel_x = self.taxels_xy_mm[None, :, 0] - np.asarray(c.tex_x_mm, float)[:, None]
            lam = np.asarray(c.tex_spacing_mm, float)[:, None]
            relief = tooth_relief(rel_x, lam, p.tooth_depth_st_mm)
            z_st = np.maximum(z + p.tooth_relief_st_mm * np.where(z > 0, relief, 0.0), 0.0)
            p_pv = p_pv + p.tooth_relief_pv_mm * tooth_relief(rel_x, lam, p.tooth_depth_pv_mm) * (base > 0)
        g_st, g_pv, a_sp = self._geometry(c)

        # SingleTact: contact force, viscoelastic relaxation, sensor low-pass and latency
        stiff = self._stiff[None, :] * np.where(c.comb, p.comb_stiffness_factor, 1.0)[:, None]
        fe = p.st_gain * g_st * stiff * z_st ** p.exponent
        f = self._st_filter.process(fe)
        if self._st_delay_n:
            f = np.concatenate([self._st_delay, f])
            self._st_delay = f[-self._st_delay_n :]
            f = f[:n]
        sel = np.flatnonzero((k - self.st_phase) % ST_DECIMATION == 0)
        st = f[sel] + self._st_offset[None, :] + self._st_noise.take(sel.size)
        st = np.clip(np.round(st / ST_RESOLUTION_N) * ST_RESOLUTION_N, *ST_RANGE_N) + 0.0  # no -0.0

        # PVDF: film strain, spreading, electrical high-passes, anti-alias
        s = self._film(p_pv, z, g_pv)
        s = _spreading_lowpass(np.ascontiguousarray(s), a_sp, self._spread)
        v = self._pv_filter.process(s)

        # mains (common source, per-taxel pickup, more while the grounded probe touches), noise, ADC
        t = self.t0_s + k / FS_HZ
        hum = np.zeros(n)
        for h, (amp, ph) in enumerate(zip(self._mains_amp, self._mains_phase), start=1):
            hum += amp * np.sin(2 * np.pi * h * self.mains_hz * t + ph)
        touch = 1.0 + p.mains_contact_gain * np.clip(z / 0.2, 0.0, 1.0)
        v += hum[:, None] * self._mains_taxel[None, :] * touch
        v += self._pv_noise.take(n)
        code = np.clip(np.round(v / ADC_STEP_V), -2048, 2047)

        self.tick += n
        return RawChunk(
            st_t=self.t0_s + k[sel] / FS_HZ,
            st=st.astype(np.float32),
            pvdf_t=t,
            pvdf=(code * ADC_STEP_V).astype(np.float32),
        )
