"""The TouchReal parameter file: a validated, versioned JSON schema (pydantic).

One file holds everything that turns raw sensor samples into spikes: the preprocessing
configuration (with the PVDF gate calibration and the mains harmonics to notch) and one
:class:`ClassParams` per afferent class. See docs/parameters.md for every field.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .settings import CLASSES, DEFAULT_UPDATE_MS, DEFAULT_WINDOW_MS, PACKAGE_DATA, PVDF_FS_HZ

SCHEMA_NAME = "touchreal.params"
#: Written version. Version 1 files (no ``ClassParams.lowpass_hz`` / ``negative_lead_ms``) are still
#: read, as no class low-pass and no lead; version 2 files (no ``ClassParams.window_ms``) as every
#: class on ``preprocess.window_ms``. Files without ``alignment`` (every version 1-2 file, and version
#: 3 files written before it existed) may hold negative class delays: they are read as the same
#: encoder with that lead moved into the alignment (:func:`legacy_alignment`); version 3 files (no
#: ``ClassParams.highpass_hz``) as no class high-pass.
SCHEMA_VERSION = 4

# Bounds (low, high; inclusive) of fields below that other modules search within or check too (the fit's
# search space and plan, the server's config patch).
TAU_RANGE_MS = (0.2, 2000.0)  #: membrane time constants (ms) a class may have
DELAY_RANGE_MS = (0.0, 500.0)  #: physiological output delays (ms) a class may have (>= 0)
LEAD_RANGE_MS = (0.0, 100.0)  #: leads (ms) of a class's negative-part inputs over its positive parts
WINDOW_RANGE_MS = (4.0, 512.0)  #: causal PVDF STFT windows (ms) the preprocessing and a class may run at
HIGHPASS_RANGE_HZ = (0.1, 100.0)  #: cutoffs (Hz) a class's input high-pass may have

#: Order of the eight input weights: (positive, negative) part of ST, dST, PVDF, dPVDF.
WEIGHT_NAMES = ("ST+", "ST-", "dST+", "dST-", "PVDF+", "PVDF-", "dPVDF+", "dPVDF-")


class ParamsError(ValueError):
    """An invalid parameter file or upload; the message lists every problem."""


#: A number: an int or a float, never a bool or a numeric string (strict).
Num = Annotated[float, Field(strict=True)]
#: A whole number (strict: no bool, no float, no string).
Int = Annotated[int, Field(strict=True)]

PROVENANCE_MAX_BYTES = 65536  #: the provenance's compact JSON, at most
PROVENANCE_MAX_DEPTH = 8  #: nesting levels of lists and objects in the provenance
PROVENANCE_MAX_INT = 10**18  #: magnitude of an integer in the provenance


def _provenance_depth(v: object) -> int:
    """Nesting depth of lists/dicts (iterative: a deep value cannot exhaust the stack)."""
    deepest, todo = 0, [(v, 0)]
    while todo:
        x, d = todo.pop()
        if isinstance(x, (list, dict)):
            deepest = max(deepest, d + 1)
            if deepest > PROVENANCE_MAX_DEPTH:
                return deepest
            todo.extend((y, d + 1) for y in (x.values() if isinstance(x, dict) else x))
        elif isinstance(x, float) and not math.isfinite(x):
            raise ValueError("numbers must be finite")
        elif isinstance(x, int) and not isinstance(x, bool) and abs(x) > PROVENANCE_MAX_INT:
            raise ValueError(f"integers above {PROVENANCE_MAX_INT:.0e} in magnitude are not allowed")
    return deepest


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, validate_assignment=True)


class ClassParams(_Strict):
    """Encoder parameters of one afferent class (TouchSim-style LIF at 5 kHz)."""

    weights: list[Num] = Field(
        min_length=8, max_length=8, description="w1..w8 on (max(x,0), max(-x,0)) of ST [N], dST [N/s], PVDF [V], dPVDF [V/s]"
    )
    i_sat: Num = Field(ge=0.0, le=1e6, description="saturation current; 0 disables saturation")
    tau_ms: Num = Field(ge=TAU_RANGE_MS[0], le=TAU_RANGE_MS[1], description="membrane time constant (ms)")
    ih: list[Num] = Field(min_length=2, max_length=2, description="weights of the two post-spike basis functions")
    delay_ms: Num = Field(
        ge=DELAY_RANGE_MS[0],
        le=DELAY_RANGE_MS[1],
        description="physiological output delay added to spike times (ms, >= 0: a spike's stamp never precedes "
        "the sensor sample that caused it); a rig's lag behind its reference is in EncoderParams.alignment",
    )
    lowpass_hz: Num | None = Field(
        default=None,
        ge=5.0,
        le=2000.0,
        description="cutoff (Hz) of the class's causal 3rd-order Butterworth input low-pass on all four "
        "channels before rectification (TouchSim's per-model input filter); None = no filter",
    )
    highpass_hz: Num | None = Field(
        default=None,
        ge=HIGHPASS_RANGE_HZ[0],
        le=HIGHPASS_RANGE_HZ[1],
        description="cutoff (Hz) of the class's causal 1st-order Butterworth input high-pass on all four channels, "
        "after the low-pass and before rectification (removes a slow baseline such as a PVDF amplifier's "
        "wander); None = no filter (version 4)",
    )
    negative_lead_ms: Num = Field(
        default=0.0,
        ge=LEAD_RANGE_MS[0],
        le=LEAD_RANGE_MS[1],
        description="lead (ms) of the negative-part inputs max(-x, 0) over the positive parts: the positive "
        "parts are delayed by it before summation (compensates a sensor whose unloading lags its loading)",
    )

    window_ms: Num | None = Field(
        default=None,
        ge=WINDOW_RANGE_MS[0],
        le=WINDOW_RANGE_MS[1],
        description="the class's own causal PVDF STFT window (ms); None = preprocess.window_ms. Classes with "
        "equal windows share one PVDF branch; a class's latency follows its window",
    )

    @field_validator("weights", "ih")
    @classmethod
    def _bounded(cls, v: list[float]) -> list[float]:
        if any(abs(x) > 1e9 for x in v):
            raise ValueError("magnitudes above 1e9 are not meaningful")
        return v

    @property
    def tau_samples(self) -> float:
        return self.tau_ms * 5.0


class GateCalibration(_Strict):
    """PVDF spectral gate: per-frequency noise floor measured on a contact-free baseline."""

    freqs_hz: list[Annotated[Num, Field(ge=0.0, le=PVDF_FS_HZ / 2)]] = Field(
        min_length=2, max_length=4097, description="frequency grid (Hz, 0..PVDF Nyquist), increasing")
    noise_asd: list[Annotated[Num, Field(ge=0.0, le=1e3)]] = Field(
        min_length=2, max_length=4097, description="noise amplitude spectral density (V/sqrt(Hz), 0..1e3)")
    factor: Num = Field(default=3.0, gt=0.0, le=100.0, description="keep bins above factor x expected noise magnitude")
    attenuation: Num = Field(default=0.05, ge=0.0, le=1.0, description="gain applied to bins below threshold")

    @model_validator(mode="after")
    def _consistent(self) -> "GateCalibration":
        if len(self.freqs_hz) != len(self.noise_asd):
            raise ValueError("freqs_hz and noise_asd must have equal length")
        if np.any(np.diff(self.freqs_hz) <= 0):
            raise ValueError("freqs_hz must be strictly increasing")
        return self


class PreprocessParams(_Strict):
    """Causal preprocessing: raw SingleTact/PVDF -> ST, dST, PVDF, dPVDF at 5 kHz."""

    window_ms: Num = Field(default=DEFAULT_WINDOW_MS, ge=WINDOW_RANGE_MS[0], le=WINDOW_RANGE_MS[1],
                           description="causal PVDF STFT window (ms)")
    update_ms: Num = Field(default=DEFAULT_UPDATE_MS, ge=1.0, le=1000.0, description="online update interval (ms)")
    st_lowpass_hz: Num = Field(default=20.0, ge=0.5, lt=50.0, description="SingleTact Butterworth low-pass cutoff (Hz, "
                               "0.5 .. below the 50 Hz Nyquist)")
    st_alpha: Num = Field(default=0.5, gt=0.0, le=1.0, description="alpha-beta estimator position gain")
    st_beta: Num = Field(default=0.1, gt=0.0, lt=2.0, description="alpha-beta estimator velocity gain "
                         "(stable only with 4 - 2 alpha - beta > 0)")
    pvdf_lowpass_hz: Num = Field(default=800.0, ge=10.0, lt=1000.0, description="PVDF Butterworth low-pass cutoff "
                                 "(Hz, 10 .. below the 1 kHz Nyquist)")
    mains_hz: Num = Field(default=50.0, ge=40.0, le=70.0, description="mains frequency (Hz, 40..70)")
    mains_candidates_hz: list[Annotated[Num, Field(ge=40.0, le=70.0)]] = Field(
        default_factory=lambda: [50.0, 60.0], max_length=4,
        description="mains frequencies a source may run on: each stream's is resolved among them from its first "
                    "0.1 s of PVDF, mains_hz unless another one's hum stands out 10x (empty: always mains_hz)")
    notch_harmonics: list[Annotated[Int, Field(ge=1, le=40)]] = Field(
        default_factory=lambda: [1, 3, 5, 7], max_length=40,
        description="mains harmonics to notch (1..40; those at or above the PVDF Nyquist are skipped)")
    notch_q: Num = Field(default=30.0, gt=0.5, le=1000.0, description="quality factor of each notch")
    gate: GateCalibration | None = Field(default=None, description="spectral gate; None passes all bins")

    @field_validator("notch_harmonics")
    @classmethod
    def _harmonics(cls, v: list[int]) -> list[int]:
        if len(set(v)) != len(v):
            raise ValueError("harmonics must be distinct integers >= 1")
        return sorted(v)

    @model_validator(mode="after")
    def _stable_estimator(self) -> "PreprocessParams":
        if 4.0 - 2.0 * self.st_alpha - self.st_beta <= 0.0:
            raise ValueError("st_alpha, st_beta: the alpha-beta estimator is unstable unless 4 - 2 alpha - beta > 0")
        return self


class ReferenceAlignment(_Strict):
    """How TouchReal's spike stamps line up with a dataset's reference spike trains.

    TouchReal stamps a spike on the sensor clock: the time of the sensor sample that caused it plus
    the class's physiological delay. A dataset's reference trains (TouchSim on the *commanded*
    stimulus) run ahead of the sensor by the rig's lag (actuator and sensor response). Comparable
    times are ``stamp - lag_ms``; fit, evaluate and ``touchreal encode`` apply it for a dataset.
    """

    lag_ms: Num = Field(
        default=0.0,
        ge=0.0,
        le=1000.0,
        description="the rig's lag (ms): reference-clock time = TouchReal stamp - lag_ms",
    )
    dataset: str = Field(default="", max_length=1024, description="name of the dataset the lag belongs to ('' = unknown)")


def legacy_alignment(data: dict) -> dict:
    """A raw parameter object without ``alignment``, with negative class delays moved into one.

    Older files aligned spikes with the reference by negative class delays. The same encoder in the
    current representation: lag = max(0, -min delay), every class delay + lag. Comparable output
    (stamp - lag) is unchanged; the class with the most negative delay gets delay 0."""
    classes = data.get("classes")
    if "alignment" in data or not isinstance(classes, dict):
        return data

    def delay(c: object) -> float | None:  # a finite number, else None (left to the validation)
        d = c.get("delay_ms") if isinstance(c, dict) else None
        return float(d) if isinstance(d, (int, float)) and not isinstance(d, bool) and math.isfinite(d) else None

    lag = max([0.0] + [-d for d in map(delay, classes.values()) if d is not None])
    if lag == 0.0:
        return data
    shifted = {name: c if delay(c) is None else {**c, "delay_ms": delay(c) + lag} for name, c in classes.items()}
    prov = data.get("provenance")
    dataset = prov.get("dataset", "") if isinstance(prov, dict) and isinstance(prov.get("dataset", ""), str) else ""
    return {**data, "classes": shifted, "alignment": {"lag_ms": lag, "dataset": dataset}}


class EncoderParams(_Strict):
    """A complete, versioned TouchReal parameter set."""

    schema_name: Literal["touchreal.params"] = Field(default=SCHEMA_NAME, alias="schema")
    version: Literal[1, 2, 3, 4] = SCHEMA_VERSION
    preprocess: PreprocessParams = Field(default_factory=PreprocessParams)
    classes: dict[str, ClassParams]
    alignment: ReferenceAlignment = Field(default_factory=ReferenceAlignment)
    provenance: dict[str, str | bool | int | float | list | dict | None] = Field(
        default_factory=dict, description=f"free-form record of how the set was made (JSON, at most "
        f"{PROVENANCE_MAX_BYTES} bytes and {PROVENANCE_MAX_DEPTH} levels deep, finite numbers; booleans and nulls stay as they are)")

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, populate_by_name=True)

    @model_validator(mode="before")
    @classmethod
    def _legacy_delays(cls, data: object) -> object:
        return legacy_alignment(data) if isinstance(data, dict) else data

    @field_validator("provenance")
    @classmethod
    def _bounded_provenance(cls, v: dict) -> dict:
        if _provenance_depth(v) > PROVENANCE_MAX_DEPTH:
            raise ValueError(f"nested deeper than {PROVENANCE_MAX_DEPTH} levels")
        if len(json.dumps(v, separators=(",", ":"))) > PROVENANCE_MAX_BYTES:
            raise ValueError(f"larger than {PROVENANCE_MAX_BYTES} bytes")
        return v

    @field_validator("classes")
    @classmethod
    def _classes(cls, v: dict[str, ClassParams]) -> dict[str, ClassParams]:
        unknown = set(v) - set(CLASSES)
        if unknown:
            raise ValueError(f"unknown classes {sorted(unknown)}; expected a subset of {list(CLASSES)}")
        if not v:
            raise ValueError("at least one class is required")
        return {c: v[c] for c in CLASSES if c in v}

    @model_validator(mode="after")
    def _version_features(self) -> "EncoderParams":
        if self.version < 2 and any(c.lowpass_hz is not None or c.negative_lead_ms for c in self.classes.values()):
            raise ValueError("classes.*.lowpass_hz and negative_lead_ms need schema version 2")
        if self.version < 3 and any(c.window_ms is not None for c in self.classes.values()):
            raise ValueError("classes.*.window_ms needs schema version 3")
        if self.version < 4 and any(c.highpass_hz is not None for c in self.classes.values()):
            raise ValueError("classes.*.highpass_hz needs schema version 4")
        return self

    def reference_times(self, stamps_s: np.ndarray) -> np.ndarray:
        """Spike stamps (s, sensor clock) -> times comparable with the aligned dataset's reference
        trains (s): ``stamp - alignment.lag_ms``."""
        return np.asarray(stamps_s, np.float64) - self.alignment.lag_ms / 1000.0

    def windows_ms(self) -> dict[float, list[str]]:
        """Distinct causal PVDF windows (ms) -> the classes on each, in class order."""
        out: dict[float, list[str]] = {}
        for c in self.classes:
            out.setdefault(float(self.window_ms(c)), []).append(c)
        return out

    def window_ms(self, cls: str) -> float:
        """Causal PVDF window (ms) of class ``cls``: its own, else the preprocessing default."""
        own = self.classes[cls].window_ms
        return self.preprocess.window_ms if own is None else own

    def to_json(self) -> str:
        return self.model_dump_json(by_alias=True, indent=1)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_json() + "\n")

    @classmethod
    def parse(cls, data: str | bytes | dict) -> "EncoderParams":
        """Validate a JSON text or object; raise :class:`ParamsError` listing every problem."""
        try:
            if isinstance(data, (str, bytes)):
                data = json.loads(data)
            return cls.model_validate(data)
        except json.JSONDecodeError as exc:
            raise ParamsError(f"not valid JSON: {exc}") from exc
        except ValidationError as exc:
            problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or '<root>'}: {e['msg']}" for e in exc.errors())
            raise ParamsError(f"invalid parameters: {problems}") from exc

    @classmethod
    def load(cls, path: str | Path) -> "EncoderParams":
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise ParamsError(f"{path}: cannot read ({exc})") from exc
        return cls.parse(text)


DEFAULT_PARAMS_PATH = PACKAGE_DATA / "default_params.json"


def default_params() -> EncoderParams:
    """The parameter set shipped with the package."""
    return EncoderParams.load(DEFAULT_PARAMS_PATH)
