"""Offline simulated datasets: rig protocols -> trials in the recording format (with reference spikes).

Each trial is one stimulus played by :class:`~touchreal.simulator.scene.SceneSource` (robot dynamics
+ e-skin physics, one taxel at the sensor centre), recorded like rig-v1: the stimulus starts 0.2-0.5
s into the recording, a 0.3-0.6 s tail follows (texture recordings are 3.0 s), SingleTact at 100 Hz
(N), PVDF at 2 kHz (V), the commanded indentation at 5 kHz (mm) and TouchSim reference spike trains
from :func:`touchreal.reference.model.reference_trains`. Manifest entries carry the same fields as
rig-v1's. Design of every protocol: :data:`PROTOCOL_DESIGN` (the paper's full design).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..recording import Dataset, Trial, write_dataset
from ..settings import PVDF_FS_HZ, ST_FS_HZ
from .build import LIMITS, SensorBuild
from .eskin import SkinParams
from .scene import Scene, SceneEvent, SceneSource
from .stimuli import RampHold, RobotParams, SineBurst, Stimulus, TextureSlide

CMD_FS_HZ = 5000.0  #: commanded-stimulus rate (Hz)

#: The paper's protocol design (same layout as rig-v1's manifest 'protocols').
PROTOCOL_DESIGN: dict[str, Any] = {
    "ramp": {
        "probe": "rigid round probe, 1 mm diameter, robot arm, sensor centre",
        "factors": {
            "v_up_mm_s": [8, 40, 65, 95],
            "v_down_mm_s": [8, 40, 65, 95],
            "hold_s": [0.0, 0.6, 1.2, 1.8],
            "depth_mm": [0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0],
        },
    },
    "sine": {
        "probe": "1 mm probe on a sound exciter, resting on the skin (preload) for the whole recording, sensor centre",
        "freq_hz": [10, 100, 200, 300, 400],
        "burst_s": 1.0,
        "ramp_s": 0.05,
        "nominal_amplitude_mm": 0.1,
        "note": "exciter drive calibrated per frequency so that the PVDF response amplitude is approximately "
        "equal across frequencies; cmd_depth holds the nominal 0.1 mm reference vibration used for TouchSim",
    },
    "texture": {
        "stimulus": "comb textures pressed onto the sensor and slid laterally",
        "spacing_mm": [0.5, 2.0, 4.0],
        "depth_mm": 0.5,
        "speed_mm_s": 30.0,
        "press_speed_mm_s": 10.0,
        "dwell_s": 0.1,
        "slide_s": 2.0,
        "record_s": 3.0,
        "labels": ["comb_0.5mm", "comb_2mm", "comb_4mm"],
    },
    "texture_fine": {
        "stimulus": "eight comb textures of close spacings, each slid at one of three close speeds (a nuisance the "
        "decoder must see through); recorded as protocol 'texture', label = the comb",
        "spacing_mm": [1.0, 1.25, 1.5, 1.75, 2.0, 2.25, 2.5, 2.75],
        "speed_mm_s": [25.0, 30.0, 35.0],
        "depth_mm": 0.5,
        "press_speed_mm_s": 10.0,
        "dwell_s": 0.1,
        "slide_s": 2.0,
        "record_s": 3.0,
        "labels": ["comb_1mm", "comb_1.25mm", "comb_1.5mm", "comb_1.75mm", "comb_2mm", "comb_2.25mm", "comb_2.5mm",
                   "comb_2.75mm"],
    },
    "texture_hard": {
        "stimulus": "ten comb textures of close spacings slid at five speeds; per trial an independent press depth "
        "and sensor build (ratios drawn around the dataset's build); recorded as protocol 'texture', label = the comb",
        "spacing_mm": [1.0, 1.25, 1.5, 1.75, 2.0, 2.25, 2.5, 2.75, 3.0, 3.25],
        "speed_mm_s": [20.0, 30.0, 40.0, 50.0, 60.0],
        "depth_mm": [0.4, 0.6],
        "build_ratio": {"pvdf_coupling": [0.5, 1.5], "st_gain": [0.85, 1.15], "st_noise": [0.5, 2.0],
                        "pvdf_noise": [0.5, 2.0], "mains_level": [0.5, 2.0], "harmonic_gain": [0.5, 2.0]},
        "mains_hz": [50, 60],
        "mains_harmonics": [5, 9],
        "extra_rig_lag_ms": [0.0, 55.0],
        "press_speed_mm_s": 10.0,
        "dwell_s": 0.1,
        "slide_s": 2.0,
        "record_s": 3.0,
        "labels": ["comb_1mm", "comb_1.25mm", "comb_1.5mm", "comb_1.75mm", "comb_2mm", "comb_2.25mm", "comb_2.5mm",
                   "comb_2.75mm", "comb_3mm", "comb_3.25mm"],
        "note": "uniform draws per trial: depth_mm in its range, each build ratio in its range times the dataset build's "
        "value, mains_hz one of the two, mains_harmonics an integer in its range, rig_lag_ms the build's plus extra_rig_lag_ms; "
        "depth and build are recorded in the trial's 'variation'",
    },
    "spatial_ramp": {
        "probe": "1 mm probe at offset (r, theta) from the sensor centre",
        "v_mm_s": 10.0,
        "hold_s": 1.0,
        "depth_mm": [0.1, 0.3, 0.5, 0.7, 0.9, 1.1],
    },
    "spatial_sine": {"probe": "exciter probe at offset (r, theta), drive as in 'sine'", "freq_hz": [35, 90, 165, 265, 365]},
    "spatial_offsets": {"r_mm": list(range(0, 16)), "theta_deg": list(range(0, 360, 30)), "note": "radius 0 once (theta 0)"},
    "offsets": "r in mm from the sensor centre, theta in degrees counter-clockwise from +x; probe at (r cos theta, r sin theta)",
}

#: Independent noisy TouchSim repeats per trial (as rig-v1).
REFERENCE_REPEATS = {"ramp": 6, "sine": 10, "texture": 0, "texture_fine": 0, "texture_hard": 0, "spatial_ramp": 3,
                     "spatial_sine": 3}

#: CLI protocol names -> recording protocols.
PROTOCOL_GROUPS = {"ramp": ("ramp",), "sine": ("sine",), "texture": ("texture",), "texture-fine": ("texture_fine",),
                   "texture-hard": ("texture_hard",),
                   "spatial": ("spatial_ramp", "spatial_sine")}


@dataclass(frozen=True)
class Condition:
    """One stimulus condition of a protocol, at offset (r mm, theta deg) from the sensor centre."""

    protocol: str
    condition: str
    stimulus: Stimulus
    offset_r_mm: float = 0.0
    offset_theta_deg: float = 0.0

    @property
    def probe_xy_mm(self) -> tuple[float, float]:
        th = math.radians(self.offset_theta_deg)
        return (round(self.offset_r_mm * math.cos(th), 9) + 0.0, round(self.offset_r_mm * math.sin(th), 9) + 0.0)

    @property
    def texture(self) -> str | None:
        return f"comb_{self.stimulus.spacing_mm:g}mm" if self.protocol == "texture" else None


def _offsets() -> list[tuple[float, float]]:
    d = PROTOCOL_DESIGN["spatial_offsets"]
    return [(0.0, 0.0)] + [(float(r), float(th)) for r in d["r_mm"] if r > 0 for th in d["theta_deg"]]


def conditions(protocol: str, skin: SkinParams | None = None, speeds_mm_s: Iterable[float] | None = None) -> list[Condition]:
    """Every condition of ``protocol`` in the design (fixed order); ``speeds_mm_s``: the scanning
    speeds of ``texture_hard`` (default: the design's five)."""
    skin = skin or SkinParams()
    d = PROTOCOL_DESIGN
    if protocol == "ramp":
        f = d["ramp"]["factors"]
        return [
            Condition("ramp", f"ramp_d{dep}_vu{vu}_vd{vd}_h{h}", RampHold(float(dep), float(vu), float(vd), float(h)))
            for dep, vu, vd, h in itertools.product(f["depth_mm"], f["v_up_mm_s"], f["v_down_mm_s"], f["hold_s"])
        ]
    if protocol == "sine":
        return [Condition("sine", f"sine_f{f}", SineBurst.calibrated(f, skin)) for f in d["sine"]["freq_hz"]]
    if protocol == "texture":
        t = d["texture"]
        return [
            Condition("texture", f"texture_s{s}", TextureSlide(float(s), t["speed_mm_s"], t["depth_mm"], t["press_speed_mm_s"], t["dwell_s"], t["slide_s"]))
            for s in t["spacing_mm"]
        ]
    if protocol == "texture_fine":
        t = d["texture_fine"]
        return [
            Condition("texture", f"texture_fine_s{s}_v{v:g}", TextureSlide(float(s), float(v), t["depth_mm"], t["press_speed_mm_s"], t["dwell_s"], t["slide_s"]))
            for s in t["spacing_mm"] for v in t["speed_mm_s"]
        ]
    if protocol == "texture_hard":
        t = d["texture_hard"]
        mid = float(np.mean(t["depth_mm"]))  # the nominal press; each trial draws its own (vary_trial)
        return [
            Condition("texture", f"texture_hard_s{s}_v{v:g}", TextureSlide(float(s), float(v), mid, t["press_speed_mm_s"], t["dwell_s"], t["slide_s"]))
            for s in t["spacing_mm"] for v in (t["speed_mm_s"] if speeds_mm_s is None else speeds_mm_s)
        ]
    if protocol == "spatial_ramp":
        sr = d["spatial_ramp"]
        return [
            Condition("spatial_ramp", f"spatial_ramp_d{dep}_r{r:g}_th{th:g}", RampHold(float(dep), sr["v_mm_s"], sr["v_mm_s"], sr["hold_s"]), r, th)
            for dep in sr["depth_mm"] for r, th in _offsets()
        ]
    if protocol == "spatial_sine":
        sines = {f: SineBurst.calibrated(f, skin) for f in d["spatial_sine"]["freq_hz"]}
        return [
            Condition("spatial_sine", f"spatial_sine_f{f}_r{r:g}_th{th:g}", sines[f], r, th)
            for f in d["spatial_sine"]["freq_hz"] for r, th in _offsets()
        ]
    raise ValueError(f"unknown protocol {protocol!r}")


def vary_trial(cond: Condition, rng: np.random.Generator, build: SensorBuild | None = None,
               vary_build: bool = True) -> tuple[Condition, SensorBuild, dict[str, Any]]:
    """A ``texture_hard`` trial's own press depth (mm) and sensor build: uniform draws in the design's
    ranges (:data:`PROTOCOL_DESIGN` ``texture_hard``): build ratios times ``build``'s values (clipped to
    the simulator's limits), the mains frequency and harmonics, the build's rig lag plus an extra.
    ``vary_build`` False: ``build`` itself (the depth still varies). Returns the condition with that
    depth, the build and the manifest's ``variation`` record."""
    t = PROTOCOL_DESIGN["texture_hard"]
    base = build or SensorBuild()
    depth = round(float(rng.uniform(*t["depth_mm"])), 4)
    ratios = {k: float(rng.uniform(*r)) for k, r in t["build_ratio"].items()}
    fields = {k: round(float(np.clip(getattr(base, k) * r, *LIMITS[k])), 4) for k, r in ratios.items()}
    fields["mains_hz"] = float(rng.choice(t["mains_hz"]))
    fields["mains_harmonics"] = int(rng.integers(t["mains_harmonics"][0], t["mains_harmonics"][1] + 1))
    fields["rig_lag_ms"] = round(float(np.clip(base.rig_lag_ms + rng.uniform(*t["extra_rig_lag_ms"]), *LIMITS["rig_lag_ms"])), 2)
    trial_build = dataclasses.replace(base, name=f"{base.name}~trial", **fields) if vary_build else base
    stim = dataclasses.replace(cond.stimulus, depth_mm=depth)
    return dataclasses.replace(cond, stimulus=stim), trial_build, {"depth_mm": depth, "build": trial_build.to_json()}


def pick_trials(conds: list[Condition], n: int, rng: np.random.Generator) -> list[tuple[Condition, int]]:
    """``n`` trials spread over ``conds``: a random subset of conditions, then further repeats.

    Every condition gets either floor(n / C) or ceil(n / C) repeats, numbered 0, 1, ... in order;
    the trials come back in random order (as a rig session interleaves conditions).
    """
    if n <= 0:
        return []
    base, extra = divmod(n, len(conds))
    order = rng.permutation(len(conds))
    reps = np.full(len(conds), base)
    reps[order[:extra]] += 1
    trials = [(conds[i], r) for i in range(len(conds)) for r in range(reps[i])]
    return [trials[i] for i in rng.permutation(len(trials))]


def simulate_trial(
    cond: Condition,
    repeat: int,
    trial_id: str,
    seed: np.random.SeedSequence | int | None = None,
    *,
    reference: bool = True,
    skin: SkinParams | None = None,
    robot: RobotParams | None = None,
) -> tuple[dict[str, Any], Trial]:
    """Simulate one recording of ``cond``: its manifest entry (without file/sample counts) and trial."""
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    timing_ss, skin_ss, ref_ss = ss.spawn(3)
    rng = np.random.default_rng(timing_ss)
    stim = cond.stimulus
    onset = round(float(rng.uniform(0.2, 0.5)), 4)
    if cond.protocol == "texture":
        duration = float(PROTOCOL_DESIGN["texture"]["record_s"])
    else:
        duration = math.ceil((onset + stim.duration_s + rng.uniform(0.3, 0.6)) * 100.0) / 100.0

    scene = Scene((SceneEvent(onset, stim, cond.probe_xy_mm),))
    src = SceneSource(scene, seed=skin_ss, skin=skin, robot=robot)
    raw = src.advance(int(round(duration * PVDF_FS_HZ))).taxel(0)

    t_cmd = np.arange(int(round(duration * CMD_FS_HZ))) / CMD_FS_HZ - onset
    cmd_depth = stim.nominal(t_cmd).astype(np.float32)
    cmd_x = stim.x(t_cmd).astype(np.float32) if cond.protocol == "texture" else None

    repeats = REFERENCE_REPEATS[cond.protocol] if reference else 0
    ref_meta = None
    ref = {}
    if repeats:
        from touchreal.reference.model import reference_trains

        probe, aff = cond.probe_xy_mm, (0.0, 0.0)
        ref = reference_trains(
            cmd_depth.astype(np.float64), fs_hz=CMD_FS_HZ, probe_xy_mm=probe, afferent_xy_mm=aff,
            repeats=repeats, noisy=True, delays=False, seed=int(ref_ss.generate_state(1)[0]), pin_radius_mm=0.5,
        )
        ref_meta = {"repeats": repeats, "probe_xy_mm": list(probe), "afferent_xy_mm": list(aff)}

    ev = {k: round(v, 6) for k, v in stim.events(onset).items()}
    entry = {
        "id": trial_id,
        "protocol": cond.protocol,
        "condition": cond.condition,
        "repeat": int(repeat),
        "params": stim.params(),
        "offset_r_mm": float(cond.offset_r_mm),
        "offset_theta_deg": float(cond.offset_theta_deg),
        "texture": cond.texture,
        "onset_s": onset,
        "stim_end_s": ev["end_s"],
        "events": ev,
        "duration_s": duration,
        "reference": ref_meta,
    }
    trial = Trial(
        st_t=raw.st_t, st=raw.st, pvdf_t=raw.pvdf_t, pvdf=raw.pvdf,
        cmd_depth=cmd_depth, cmd_t0=0.0, cmd_fs=CMD_FS_HZ, cmd_x=cmd_x, reference=ref,
    )
    return entry, trial


def simulate_dataset(
    protocols: str | Iterable[str],
    out: str | Path,
    trials: int | dict[str, int] = 4,
    seed: int | None = 0,
    *,
    reference: bool = True,
    skin: SkinParams | None = None,
    robot: RobotParams | None = None,
    build: SensorBuild | None = None,
    speeds_mm_s: Iterable[float] | None = None,
    vary_build: bool = True,
    progress=None,
) -> Dataset:
    """Write a dataset of ``trials`` trials per recording protocol to the folder ``out``.

    ``trials`` is one count for every protocol or a count per protocol name (a CLI group name such
    as ``spatial`` applies to its members).

    ``protocols``: one name or several, recording protocols (``ramp``, ``sine``, ``texture``,
    ``spatial_ramp``, ``spatial_sine``) or the CLI group ``spatial`` (both spatial protocols).

    ``build``: a sensor build (:mod:`.build`) applied to ``skin`` and ``robot`` (default: nominal);
    the manifest records it under ``simulator.build``. ``texture_hard`` trials each draw their own
    press depth and a build around it (:func:`vary_trial`; ``vary_build`` False: ``build`` for every trial);
    ``speeds_mm_s`` replaces its scanning speeds.
    """
    base_skin, base_robot = skin, robot
    if build is not None:
        skin, robot = build.skin(skin), build.robot(robot)
    protos: list[str] = []
    for p in [protocols] if isinstance(protocols, str) else protocols:
        for q in PROTOCOL_GROUPS.get(p, (p,)):
            if q not in REFERENCE_REPEATS:
                raise ValueError(f"unknown protocol {p!r}")
            if q not in protos:
                protos.append(q)
    per_protocol = {}
    for p in [protocols] if isinstance(protocols, str) else protocols:
        for q in PROTOCOL_GROUPS.get(p, (p,)):
            per_protocol[q] = trials.get(q, trials.get(p, 0)) if isinstance(trials, dict) else trials
    root = np.random.SeedSequence(seed)
    entries, recorded = [], {}
    for proto, pss in zip(protos, root.spawn(len(protos))):
        pick_ss, trial_ss = pss.spawn(2)
        picked = pick_trials(conditions(proto, skin, speeds_mm_s), per_protocol[proto], np.random.default_rng(pick_ss))
        for (cond, rep), tss in zip(picked, trial_ss.spawn(len(picked))):
            tid = f"{proto}_{len(entries):04d}"
            if proto == "texture_hard":
                vary_ss, tss = tss.spawn(2)
                cond, trial_build, variation = vary_trial(cond, np.random.default_rng(vary_ss), build, vary_build)
                entry, trial = simulate_trial(cond, rep, tid, tss, reference=reference, skin=trial_build.skin(base_skin),
                                              robot=trial_build.robot(base_robot))
                entry["variation"] = variation
            else:
                entry, trial = simulate_trial(cond, rep, tid, tss, reference=reference, skin=skin, robot=robot)
            entries.append(entry)
            recorded[tid] = trial
            if progress is not None:
                progress(tid)
    counts = {p: sum(e["id"].rsplit("_", 1)[0] == p for e in entries) for p in protos}
    manifest = {
        "name": Path(out).name,
        "description": "Simulated e-skin recordings (touchreal.simulator: robot dynamics + SingleTact/PVDF physics), "
        f"trials per protocol {per_protocol}, seed {seed}. Not rig data.",
        "channels": _CHANNELS,
        "clock": "one recording clock for all channels, t = 0 at recording start; st and pvdf sample times are given explicitly",
        "protocols": {k: v for k, v in PROTOCOL_DESIGN.items() if k in protos or k in ("offsets", "spatial_offsets")},
        "reference": _reference_meta(reference),
        "counts": counts,
        "simulator": {"module": "touchreal.simulator", "seed": seed, "trials_per_protocol": trials,
                      "build": (build or SensorBuild()).to_json(),
                      **({"speeds_mm_s": [float(v) for v in speeds_mm_s]} if speeds_mm_s is not None else {}),
                      **({} if vary_build else {"vary_build": False})},
        "trials": entries,
    }
    return write_dataset(out, manifest, recorded)


_CHANNELS = {
    "st": {"key": "st", "time_key": "st_t", "unit": "N", "fs_hz": ST_FS_HZ, "dtype": "float32", "range": [0.0, 10.0], "resolution": 0.01,
           "sensor": "simulated SingleTact capacitive force sensor, 8 mm diameter"},
    "pvdf": {"key": "pvdf", "time_key": "pvdf_t", "unit": "V", "fs_hz": PVDF_FS_HZ, "dtype": "float32",
             "sensor": "simulated PVDF piezo film LDT0-028K", "adc": "12-bit, +-1.65 V around the bias point, bias removed"},
    "cmd_depth": {"key": "cmd_depth", "unit": "mm", "fs_hz": CMD_FS_HZ, "dtype": "float32", "time": "cmd_t = cmd_t0 + arange(n) / cmd_fs",
                  "meaning": "commanded probe indentation (TouchSim reference input)"},
    "cmd_x": {"key": "cmd_x", "unit": "mm", "fs_hz": CMD_FS_HZ, "dtype": "float32", "meaning": "commanded lateral comb position (texture trials only)"},
}


def _reference_meta(enabled: bool) -> dict[str, Any] | None:
    if not enabled:
        return None
    return {
        "model": "touchreal.reference.model.reference_trains (TouchSim reimplementation)",
        "input": "cmd_depth (float32 -> float64) at 5 kHz from t = 0, single round probe of radius 0.5 mm at probe_xy_mm",
        "afferent_location": "probe centre for ramp/sine trials; sensor centre (0, 0) for spatial trials (probe at the offset)",
        "noisy": True,
        "delay": False,
        "fs_hz": CMD_FS_HZ,
        "time": "seconds on the recording clock",
        "repeats": dict(REFERENCE_REPEATS),
    }
