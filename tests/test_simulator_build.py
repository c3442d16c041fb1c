"""Sensor builds in the simulator: each physical difference does what it says, measured on the
simulated recordings (same seed, one factor changed), and the nominal build is the rig-v1 build."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from touchreal.cli import main
from touchreal.recording import Dataset
from touchreal.simulator.build import LIMITS, REAL_RANGES, SensorBuild, builds, load_build
from touchreal.simulator.simulate import conditions, simulate_trial

QUIET = {"pvdf_noise": 0.0, "st_noise": 0.0, "mains_level": 0.0}  # isolate one factor from the noise


def _ramp(build: SensorBuild, depth: float = 1.6):
    cond = next(c for c in conditions("ramp") if c.stimulus.depth_mm == depth and c.stimulus.hold_s == 0.6)
    entry, trial = simulate_trial(cond, 0, "t", 7, reference=False, skin=build.skin(), robot=build.robot())
    return entry, trial


def _onset_s(t: np.ndarray, x: np.ndarray, base_s: float, thresh: float) -> float:
    base = x[t < base_s].mean()
    return float(t[np.argmax(np.abs(x - base) > thresh)])


def test_the_nominal_build_is_the_rig_v1_build_bit_for_bit():
    cond = conditions("ramp")[5]
    _, a = simulate_trial(cond, 0, "t", 3, reference=False)
    _, b = simulate_trial(cond, 0, "t", 3, reference=False, skin=SensorBuild().skin(), robot=SensorBuild().robot())
    for k in ("st", "st_t", "pvdf", "pvdf_t"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


def test_film_coupling_and_singletact_gain_scale_the_signals():
    _, nom = _ramp(SensorBuild(**QUIET))
    _, weak = _ramp(SensorBuild(**QUIET, pvdf_coupling=0.5))
    _, st = _ramp(SensorBuild(**QUIET, st_gain=1.2))
    dev = lambda x: np.abs(x - x[:100].mean()).max()  # noqa: E731
    assert dev(weak.pvdf) / dev(nom.pvdf) == pytest.approx(0.5, rel=0.02)  # 12-bit ADC steps
    base = lambda tr: tr.st[:10].mean()  # noqa: E731  (the zero-force baseline is not scaled)
    assert (st.st.max() - base(st)) / (nom.st.max() - base(nom)) == pytest.approx(1.2, rel=0.02)


def test_noise_factors_scale_the_baseline_noise():
    _, nom = _ramp(SensorBuild(mains_level=0.0))
    _, noisy = _ramp(SensorBuild(mains_level=0.0, pvdf_noise=3.0, st_noise=3.0))
    sd = lambda tr: np.std(np.diff(tr.pvdf[:400]))  # noqa: E731  (before the onset, differenced: white part)
    assert sd(noisy) / sd(nom) == pytest.approx(3.0, rel=0.15)
    assert np.std(noisy.st[:15]) > 1.5 * np.std(nom.st[:15])  # ST noise shows through its 0.01 N steps


def test_mains_frequency_and_harmonics():
    def amplitude(trial, f_hz):
        x = trial.pvdf - trial.pvdf.mean()
        spec = np.abs(np.fft.rfft(x * np.hanning(x.size))) / x.size
        freqs = np.fft.rfftfreq(x.size, 1 / 2000.0)
        band = np.abs(freqs - f_hz) <= 1.5
        return spec[band].max()

    quiet = {"pvdf_noise": 0.0, "st_noise": 0.0}
    _, f50 = _ramp(SensorBuild(**quiet))
    _, f60 = _ramp(SensorBuild(**quiet, mains_hz=60, mains_harmonics=9))
    assert amplitude(f60, 60) > 5 * amplitude(f60, 50) and amplitude(f50, 50) > 5 * amplitude(f50, 60)
    assert amplitude(f60, 540) > 5 * amplitude(f50, 540)  # a 9th harmonic only where asked for
    _, rich = _ramp(SensorBuild(**quiet, harmonic_gain=3.0))
    assert amplitude(rich, 150) / amplitude(rich, 50) == pytest.approx(3 * amplitude(f50, 150) / amplitude(f50, 50), rel=0.1)


def test_rig_lag_delays_the_physical_stimulus_behind_its_command():
    e1, nom = _ramp(SensorBuild(**QUIET))
    e2, late = _ramp(SensorBuild(**QUIET, rig_lag_ms=80.0))
    assert e1["onset_s"] == e2["onset_s"]  # the command (and the TouchSim reference) keeps its time
    a = _onset_s(nom.pvdf_t, nom.pvdf, e1["onset_s"], 0.005)
    b = _onset_s(late.pvdf_t, late.pvdf, e2["onset_s"], 0.005)
    assert (b - a) * 1000 == pytest.approx(80.0 - 6.5, abs=1.5)


@pytest.mark.parametrize("bad", [{"pvdf_coupling": 0.0}, {"mains_hz": 55}, {"mains_harmonics": 10},
                                 {"rig_lag_ms": float("nan")}, {"st_gain": True}, {"coupling": 1.0}, {"mains_harmonics": 2.5}])
def test_a_bad_build_is_refused(bad):
    with pytest.raises(ValueError):
        SensorBuild.from_json(bad)


def test_shipped_builds_lie_within_what_real_builds_span():
    shipped = builds()
    assert len(shipped) >= 4 and "nominal" in shipped
    for b in shipped.values():
        for name, (lo, hi) in REAL_RANGES.items():
            assert lo <= getattr(b, name) <= hi, (b.name, name)
            assert LIMITS[name][0] <= lo and hi <= LIMITS[name][1]


def test_simulate_command_writes_the_build_into_the_manifest(tmp_path, capsys):
    spec = tmp_path / "mine.json"
    spec.write_text(json.dumps({"name": "mine", "pvdf_coupling": 0.7, "mains_hz": 60}))
    assert main(["simulate", "ramp", "--out", str(tmp_path / "ds"), "--trials", "1", "--no-reference", "--quiet",
                 "--build", str(spec), "--rig-lag-ms", "40"]) == 0
    b = Dataset.open(tmp_path / "ds").manifest["simulator"]["build"]
    assert b == dataclasses.asdict(dataclasses.replace(load_build(str(spec)), rig_lag_ms=40.0, name="mine+custom"))
    with pytest.raises(ValueError, match="neither a shipped build"):
        load_build(str(tmp_path / "missing.json"))


def test_the_fine_texture_set_has_eight_close_combs_at_three_speeds(tmp_path):
    assert main(["simulate", "texture-fine", "--out", str(tmp_path / "ds"), "--trials", "24", "--quiet"]) == 0
    ds = Dataset.open(tmp_path / "ds")
    entries = ds.entries("texture")
    assert len(entries) == 24 and ds.manifest["counts"] == {"texture_fine": 24}
    assert {e["texture"] for e in entries} == {f"comb_{s:g}mm" for s in (1.0, 1.25, 1.5, 1.75, 2.0, 2.25, 2.5, 2.75)}
    assert {e["params"]["speed_mm_s"] for e in entries} == {25.0, 30.0, 35.0}  # one trial per (comb, speed)
    trial = ds.load(entries[0]["id"])
    assert trial.cmd_x is not None and trial.duration_s == pytest.approx(3.0, abs=0.01)
