"""Settings of a fit (:class:`FitConfig`): classes and their windows, split, objective, optimiser
budget, workers."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..params import HIGHPASS_RANGE_HZ, GateCalibration, default_params
from ..settings import CLASSES
from .objective import ObjectiveConfig


def shipped_windows_ms() -> dict[str, float]:
    """Per class, the causal PVDF window (ms) it runs at in the shipped defaults (SA1 and RA on the
    16 ms fast path, PC on 128 ms): the windows a fit uses unless told otherwise."""
    p = default_params()
    return {c: p.window_ms(c) for c in CLASSES if c in p.classes}


#: classes refined by default, each with the count weight of its refinement: RA, whose count is the
#: target other sensor builds miss first, and PC, refined on the VR-normalised distance (docs/fitting.md)
DEFAULT_REFINE = {"RA": 3.0, "PC": 5.0}

#: the gate factor (x the noise) and the refinements' sine count weights of a build whose PVDF contact
#: SNR is below ``weak_signal_snr``: its gate at 3 x the noise removes PC's weak ramp transients, and
#: PC's refinement then trades its ramp counts for the 10 Hz sine (docs/fitting.md)
WEAK_SIGNAL_GATE_FACTOR = 2.0
WEAK_SIGNAL_SINE_COUNT_WEIGHTS = {"PC": 10.0}
#: the search of a build whose SingleTact is noisy (sample noise above ``noisy_st_noise_n``): SA1 also
#: runs from a saturated start (:data:`SATURATED_STARTS`) and restarts once, as its optimum
#: depends on the run there (docs/fitting.md, "Across sensor builds"); on a quiet SingleTact neither
#: run won, and together they cost about 3 min of fit time
NOISY_ST_RESTARTS = {"SA1": 1}
NOISY_ST_SATURATED_CLASSES = ("SA1",)
#: input saturations (log i_sat) a class's search also starts from where the fit asks for it
#: (``saturated_classes``), each with a CMA-ES run of its own beside the runs from the starts' own
#: saturation: SA1's count grows with the force (about depth^1.5) faster than TouchSim's with depth,
#: a strongly saturated SA1 follows TouchSim's, and from the mildly saturated starts CMA-ES seldom
#: reaches it (docs/fitting.md)
SATURATED_STARTS = {"SA1": (-2.0,)}
MAX_RESTARTS = 8  #: IPOP restarts a class may have (each doubles the population)
DEFAULT_GATE_FACTOR: float = GateCalibration.model_fields["factor"].default  #: the gate factor of every other build (3)

#: the settings of PC on a build whose contact SNR is below ``film_limited_snr`` (a weak film on a
#: noisy amplifier), where the weak-signal ones still missed PC's targets (docs/fitting.md, "A film-limited
#: build"): PC's input high-pass (cutoff Hz) removes the amplifier's slow baseline wander, which the
#: gate keeps and which shifts the film's level against PC's threshold from trial to trial; PC's
#: refinement leaves a count error up to the margin free (counted as the report does, every condition
#: alike), so its distance decides within it
FILM_LIMITED_HIGHPASS_HZ = {"PC": 5.0}
FILM_LIMITED_COUNT_MARGINS = {"PC": 0.22}
FILM_LIMITED_SINE_COUNT_WEIGHTS = {"PC": 1.0}

REFINE_SUFFIX = ":refine"  #: a refinement's key beside its class's in a fit's state (``"PC:refine"``)


def stage_key(cls: str, refinement: bool) -> str:
    """The state key of class ``cls``'s search (the class) or of its refinement (``"PC:refine"``)."""
    return cls + REFINE_SUFFIX if refinement else cls


def parse_stage_key(key: str) -> tuple[str, bool]:
    """(class, whether the key is its refinement's) of a state key."""
    return (key[: -len(REFINE_SUFFIX)], True) if key.endswith(REFINE_SUFFIX) else (key, False)


@dataclass
class FitConfig:
    """What to fit and how (``touchreal fit``'s options); validated on construction."""

    classes: tuple[str, ...] = CLASSES
    window_ms: float = 128.0  #: preprocessing window (ms): every class without its own entry in class_window_ms
    #: a class's own causal PVDF window (ms); default: the shipped windows (:func:`shipped_windows_ms`)
    class_window_ms: dict[str, float] = field(default_factory=shipped_windows_ms)
    holdout: bool = True  #: False: every trial trains (no held-out half)
    seed: int = 0
    kernel_ms: float = 10.0  #: kernel tau of the objective's D_kernel (eqs. 2-3)
    popsize: int = 12
    max_generations: int = 250  #: generations of the first CMA-ES run
    #: IPOP restarts (population x2, generations /2 each) per class, side by side with its first run
    #: (a class not named: none); an int gives every class that many (None: chosen from the build's
    #: SingleTact noise, :meth:`for_singletact`)
    restarts: dict[str, int] | int | None = None
    #: classes whose search also runs from their saturated start (:data:`SATURATED_STARTS`)
    #: (None: chosen from the build's SingleTact noise, :meth:`for_singletact`)
    saturated_classes: tuple[str, ...] | None = None
    workers: int | None = None  #: None = all cores
    max_ramp_conditions: int | None = None  #: seeded subsample of ramp conditions (None = all)
    max_refs_per_condition: int = 80  #: reference trains kept per condition (whole repeats)
    sine_weight: float = 30.0  #: weight of a sine condition relative to a ramp condition (paper: 1)
    #: the PVDF spectral gate keeps bins above this multiple of the calibrated noise (None: chosen
    #: from the build's contact SNR, :meth:`for_snr`)
    gate_factor: float | None = None
    #: a build whose PVDF contact SNR (:func:`~.calibration.contact_snr`) is below this is fitted with
    #: the weak-signal settings (:data:`WEAK_SIGNAL_GATE_FACTOR`, :data:`WEAK_SIGNAL_SINE_COUNT_WEIGHTS`)
    #: where gate_factor and refine_sine_count_weights are not given; 0: never
    weak_signal_snr: float = 50.0
    #: a build whose SingleTact sample noise (N RMS, :func:`~.calibration.singletact_noise`) is above this
    #: gets :data:`NOISY_ST_RESTARTS` and :data:`NOISY_ST_SATURATED_CLASSES` where not given (measured on the builds of
    #: docs/fitting.md: 3.1-5.0 mN at 0.5-1x the nominal noise, rig-v1 5.0, 8.4 mN at 2x, 11.9 mN at 3x)
    noisy_st_noise_n: float = 0.0065
    count_weight: float = 1.0  #: multiplier of L_rel in the objective of the search (paper: 1)
    segmented_count_classes: tuple[str, ...] = ("PC",)  #: classes whose ramp count loss is taken per turning-point window in the search (paper eq. 7: none)
    #: classes refined after their search (a second CMA-ES run from its best point), each with the
    #: count weight of its refinement's objective (whole-trial counts); empty: the paper's single search
    refine: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_REFINE))
    #: refined classes whose refinement's count term weighs a sine condition this much (1: the plain mean
    #: over conditions the held-out report reads); the others, and every distance, use ``sine_weight``
    #: (None: chosen from the build's contact SNR, :meth:`for_snr`)
    refine_sine_count_weights: dict[str, float] | None = None
    vr_distance_classes: tuple[str, ...] = ("PC",)  #: refined classes whose refinement is scored by the VR-normalised distance, not the kernel distance
    input_stage_classes: tuple[str, ...] = ("RA", "PC")  #: classes whose input stage (low-pass cutoff, negative lead) is fitted
    no_pvdf_classes: tuple[str, ...] = ()  #: classes fitted on the SingleTact channels alone (PVDF weights held at 0)
    #: classes whose film weights (w5, w6: both polarities of PVDF) are held >= 0, so pressing and
    #: releasing both excite the class, as in every TouchSim RA model, whose weights on both polarities
    #: of the skin's velocity are >= 0 (paper: unconstrained)
    excitatory_classes: tuple[str, ...] = ("RA",)
    #: a build whose PVDF contact SNR is below this is film-limited (by default also weak-signal): it
    #: gets :data:`FILM_LIMITED_HIGHPASS_HZ`, :data:`FILM_LIMITED_COUNT_MARGINS` and
    #: :data:`FILM_LIMITED_SINE_COUNT_WEIGHTS` where not given; 0: never
    film_limited_snr: float = 35.0
    #: classes whose input high-pass (1st-order, cutoff Hz) is held at this cutoff (not searched); empty:
    #: none (None: chosen from the build's contact SNR, :meth:`for_snr`)
    highpass_hz: dict[str, float] | None = None
    #: refined classes whose refinement does not charge a count error (L_rel) up to this margin; empty:
    #: none (None: chosen from the build's contact SNR, :meth:`for_snr`)
    refine_count_margins: dict[str, float] | None = None
    progress: bool = True
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)

    def __post_init__(self) -> None:
        if isinstance(self.restarts, int):
            self.restarts = {c: self.restarts for c in CLASSES}
        bad = [c for c in self.classes if c not in CLASSES]
        if bad or not self.classes:
            raise ValueError(f"classes must be a non-empty subset of {list(CLASSES)}, got {list(self.classes)}")
        for name in ("input_stage_classes", "no_pvdf_classes", "excitatory_classes", "segmented_count_classes", "vr_distance_classes", "saturated_classes",
                     "class_window_ms", "refine", "refine_sine_count_weights", "restarts", "highpass_hz", "refine_count_margins"):  # a dict's classes are its keys
            given = getattr(self, name) or ()
            bad = [c for c in given if c not in CLASSES]
            if bad:
                raise ValueError(f"{name} must be a subset of {list(CLASSES)}, got {list(given)}")
        if not all(4.0 <= w <= 512.0 for w in (self.window_ms, *self.class_window_ms.values())):
            raise ValueError("window_ms must be in [4, 512]")
        if not set(self.saturated_classes or ()) <= set(SATURATED_STARTS):
            raise ValueError(f"saturated_classes must be a subset of {list(SATURATED_STARTS)} (the classes with a saturated start)")
        if not all(isinstance(n, int) and 0 <= n <= MAX_RESTARTS for n in (self.restarts or {}).values()):
            raise ValueError(f"restarts must be integers in [0, {MAX_RESTARTS}]")
        if not all(np.isfinite(f) and HIGHPASS_RANGE_HZ[0] <= f <= HIGHPASS_RANGE_HZ[1] for f in (self.highpass_hz or {}).values()):
            raise ValueError(f"highpass_hz cutoffs must be in [{HIGHPASS_RANGE_HZ[0]:g}, {HIGHPASS_RANGE_HZ[1]:g}] Hz")
        if not all(np.isfinite(m) and 0 <= m < 1 for m in (self.refine_count_margins or {}).values()):
            raise ValueError("refine_count_margins must be in [0, 1)")
        if self.popsize < 4 or self.max_generations < 1:
            raise ValueError("popsize must be >= 4 and max_generations >= 1")
        if self.kernel_ms <= 0:
            raise ValueError("kernel_ms must be > 0")
        if not all(np.isfinite(w) and w >= 0 for w in (self.count_weight, *self.refine.values(), *(self.refine_sine_count_weights or {}).values())):
            raise ValueError("count_weight and the weights of refine and refine_sine_count_weights must be >= 0")
        if self.gate_factor is not None and not (np.isfinite(self.gate_factor) and 0 < self.gate_factor <= 100):
            raise ValueError("gate_factor must be in (0, 100]")
        if not all(np.isfinite(v) and v >= 0 for v in (self.weak_signal_snr, self.film_limited_snr)):
            raise ValueError("weak_signal_snr and film_limited_snr must be >= 0")
        if not (np.isfinite(self.noisy_st_noise_n) and self.noisy_st_noise_n > 0):
            raise ValueError("noisy_st_noise_n must be > 0")
        self.objective = ObjectiveConfig(
            **{**self.objective.__dict__, "kernel_tau_s": self.kernel_ms / 1000.0, "count_weight": float(self.count_weight)}
        )

    def weak_signal(self, snr: float | None) -> bool:
        """Whether a build of PVDF contact SNR ``snr`` (None: not measured) gets the weak-signal settings."""
        return snr is not None and snr < self.weak_signal_snr

    def film_limited(self, snr: float | None) -> bool:
        """Whether a build of PVDF contact SNR ``snr`` (None: not measured) gets PC's film-limited settings."""
        return snr is not None and snr < self.film_limited_snr

    def for_snr(self, snr: float | None) -> FitConfig:
        """This configuration with the gate factor, sine count weights, input high-passes and count
        margins that were not given chosen for a build of PVDF contact SNR ``snr``: the weak-signal
        ones below ``weak_signal_snr``, PC's film-limited ones below ``film_limited_snr``."""
        weak, film = self.weak_signal(snr), self.film_limited(snr)

        def chosen(given, film_value: dict, weak_value: dict | None = None) -> dict:
            if given is not None:
                return given
            return dict(film_value) if film else dict(weak_value or {}) if weak else {}

        gate = self.gate_factor if self.gate_factor is not None else WEAK_SIGNAL_GATE_FACTOR if weak else DEFAULT_GATE_FACTOR
        return replace(self, gate_factor=gate,
                       refine_sine_count_weights=chosen(self.refine_sine_count_weights, FILM_LIMITED_SINE_COUNT_WEIGHTS, WEAK_SIGNAL_SINE_COUNT_WEIGHTS),
                       highpass_hz=chosen(self.highpass_hz, FILM_LIMITED_HIGHPASS_HZ),
                       refine_count_margins=chosen(self.refine_count_margins, FILM_LIMITED_COUNT_MARGINS))

    def noisy_singletact(self, noise_n: float | None) -> bool:
        """Whether a build of SingleTact sample noise ``noise_n`` (N RMS; None: not measured) is noisy."""
        return noise_n is not None and noise_n > self.noisy_st_noise_n

    def for_singletact(self, noise_n: float | None) -> FitConfig:
        """This configuration with the restarts and saturated classes that were not given chosen for a
        build of SingleTact sample noise ``noise_n``: :data:`NOISY_ST_RESTARTS` and
        :data:`NOISY_ST_SATURATED_CLASSES` on a noisy one, else none."""
        noisy = self.noisy_singletact(noise_n)
        restarts = self.restarts if self.restarts is not None else dict(NOISY_ST_RESTARTS) if noisy else {}
        saturated = self.saturated_classes if self.saturated_classes is not None else NOISY_ST_SATURATED_CLASSES if noisy else ()
        return replace(self, restarts=restarts, saturated_classes=saturated)

    def restarts_of(self, key: str) -> int:
        """IPOP restarts of a class's search and of its refinement (``key``: a :func:`stage_key`)."""
        return (self.restarts or {}).get(parse_stage_key(key)[0], 0)

    def saturated(self, key: str) -> bool:
        """Whether a search (``key``: a class) also runs from its class's saturated start; never a refinement,
        which starts from the saturation the search chose."""
        cls, refinement = parse_stage_key(key)
        return not refinement and cls in (self.saturated_classes or ())

    def refined(self) -> tuple[str, ...]:
        """The fitted classes that are refined after their search."""
        return tuple(c for c in self.classes if c in self.refine)

    def objective_of(self, key: str) -> ObjectiveConfig:
        """The objective of a class's search (``key`` = the class) or of its refinement
        (``key`` = class + :data:`REFINE_SUFFIX`: the refinement's count weight)."""
        cls, refinement = parse_stage_key(key)
        weight = self.refine[cls] if refinement else self.count_weight
        margin = (self.refine_count_margins or {}).get(cls, 0.0) if refinement else 0.0
        return ObjectiveConfig(**{**self.objective.__dict__, "count_weight": float(weight), "count_margin": float(margin)})

    def window_of(self, cls: str) -> float:
        """Causal PVDF window (ms) class ``cls`` is fitted at."""
        return float(self.class_window_ms.get(cls, self.window_ms))
