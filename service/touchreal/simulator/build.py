"""Sensor builds: the physical differences between two builds of the sensor and its rig.

A user who builds the paper's sensor gets another SingleTact, another PVDF film glued another way,
another charge amplifier, another mains, another robot. :class:`SensorBuild` states those
differences relative to the nominal build (the simulated rig of rig-v1, :class:`~.eskin.SkinParams`
and :class:`~.stimuli.RobotParams` defaults) and turns them into the simulator's parameters, so
``touchreal simulate --build ...`` writes the recordings such a build would give. Ranges that real
builds span are in :data:`REAL_RANGES` (docs/simulator.md); values outside them are accepted up to
:data:`LIMITS` for stress tests.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..settings import PACKAGE_DATA
from .eskin import SkinParams
from .stimuli import RobotParams

#: Relative amplitude of the 9th mains harmonic (the 8 lower ones are the fitted rig-v1 hum; odd
#: harmonics about halve per step, so the 9th continues 0.50, 0.245, 0.123: assumed).
H9 = 0.06

#: What real builds span (documented; :data:`LIMITS` is what the simulator accepts).
REAL_RANGES: dict[str, tuple[float, float]] = {
    "pvdf_coupling": (0.5, 1.5),
    "st_gain": (0.8, 1.2),
    "st_noise": (0.5, 3.0),
    "pvdf_noise": (0.5, 3.0),
    "mains_level": (0.5, 3.0),
    "mains_harmonics": (1, 9),
    "harmonic_gain": (0.5, 3.0),
    "rig_lag_ms": (6.5, 120.0),
}
LIMITS: dict[str, tuple[float, float]] = {
    "pvdf_coupling": (0.05, 5.0),
    "st_gain": (0.2, 5.0),
    "st_noise": (0.0, 20.0),
    "pvdf_noise": (0.0, 20.0),
    "mains_level": (0.0, 20.0),
    "mains_harmonics": (1, 9),
    "harmonic_gain": (0.0, 10.0),
    "rig_lag_ms": (0.0, 200.0),
}


@dataclass(frozen=True)
class SensorBuild:
    """One build, as ratios to the nominal build where a ratio makes sense."""

    name: str = "nominal"
    pvdf_coupling: float = 1.0  #: film sensitivity (V per mm of strain) x this (coupling of the film to the skin)
    st_gain: float = 1.0  #: SingleTact sensitivity (reading per N) x this
    st_noise: float = 1.0  #: SingleTact white noise and baseline wander x this
    pvdf_noise: float = 1.0  #: PVDF broadband noise, flicker and wander x this (amplifier, cabling)
    mains_hz: float = 50.0  #: mains frequency (Hz): 50 or 60
    mains_level: float = 1.0  #: mains pickup (every harmonic) x this
    mains_harmonics: int = 8  #: highest mains harmonic present (1-9)
    harmonic_gain: float = 1.0  #: harmonics 2 and up x this (a more distorted supply)
    rig_lag_ms: float = 6.5  #: physical stimulus behind its command (ms): the robot's latency; the exciter lags by this - 6.5

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name == "name":
                if not isinstance(self.name, str) or not 0 < len(self.name) <= 64:
                    raise ValueError("build name must be a string of 1-64 characters")
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"build {f.name} must be a finite number, got {v!r}")
            if f.name == "mains_hz":
                if v not in (50, 60):
                    raise ValueError(f"build mains_hz must be 50 or 60, got {v!r}")
                continue
            lo, hi = LIMITS[f.name]
            if not lo <= v <= hi:
                raise ValueError(f"build {f.name} must be in [{lo:g}, {hi:g}], got {v!r}")
        if self.mains_harmonics != int(self.mains_harmonics):
            raise ValueError("build mains_harmonics must be an integer")

    # -- simulator parameters -------------------------------------------------------------------------
    def skin(self, base: SkinParams | None = None) -> SkinParams:
        """The e-skin constants of this build (``base``: the nominal ones)."""
        b = base or SkinParams()
        h = (list(b.mains_harmonics) + [H9])[: int(self.mains_harmonics)]
        h = [h[0]] + [x * self.harmonic_gain for x in h[1:]]
        return dataclasses.replace(
            b,
            pv_gain_v_mm=b.pv_gain_v_mm * self.pvdf_coupling,
            st_gain=b.st_gain * self.st_gain,
            st_noise_n=b.st_noise_n * self.st_noise,
            st_wander_n=b.st_wander_n * self.st_noise,
            pv_noise_v=b.pv_noise_v * self.pvdf_noise,
            pv_wander_v=b.pv_wander_v * self.pvdf_noise,
            pv_flicker_v=b.pv_flicker_v * self.pvdf_noise,
            mains_hz=float(self.mains_hz),
            mains_v=b.mains_v * self.mains_level,
            mains_harmonics=tuple(h),
        )

    def robot(self, base: RobotParams | None = None) -> RobotParams:
        """The rig's robot and exciter timing of this build."""
        b = base or RobotParams()
        nominal = RobotParams().latency_s
        return dataclasses.replace(b, latency_s=self.rig_lag_ms / 1000.0,
                                   exciter_latency_s=max(self.rig_lag_ms / 1000.0 - nominal, 0.0))

    # -- files ------------------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: Any) -> SensorBuild:
        """A build from a JSON object (unknown fields refused; missing ones nominal)."""
        if not isinstance(data, dict):
            raise ValueError("a build is a JSON object")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown build fields {unknown}; expected {sorted(names)}")
        return cls(**data)


def builds() -> dict[str, SensorBuild]:
    """The shipped builds (service/touchreal/data/builds.json), by name."""
    data = json.loads((PACKAGE_DATA / "builds.json").read_text())
    return {b["name"]: SensorBuild.from_json(b) for b in data["builds"]}


def load_build(spec: str) -> SensorBuild:
    """A shipped build's name, or a JSON file with one build object."""
    shipped = builds()
    if spec in shipped:
        return shipped[spec]
    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"build {spec!r} is neither a shipped build ({', '.join(shipped)}) nor a JSON file")
    try:
        return SensorBuild.from_json(json.loads(path.read_text()))
    except json.JSONDecodeError as exc:
        raise ValueError(f"build file {spec}: not valid JSON ({exc})") from exc
