"""The fit's PVDF calibration finds the build's mains frequency: simulated builds on 50 and 60 Hz
mains (the real simulator, `touchreal simulate --build`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from touchreal.cli import main
from touchreal.fitting.calibration import calibrate_pvdf, contact_snr, mains_residual, noise_rms, singletact_noise
from touchreal.fitting.policy import resolve
from touchreal.fitting.profile import BuildProfile
from touchreal.fitting.trials import baseline_segments
from touchreal.params import PreprocessParams
from touchreal.preprocess.gate import calibrate, filter_segments
from touchreal.recording import Dataset


def _baselines(tmp_path, build: str):
    out = tmp_path / build
    assert main(["simulate", "ramp", "--trials", "ramp=12", "--seed", "3", "--build", build, "--out", str(out), "--quiet"]) == 0
    ds = Dataset.open(out)
    return baseline_segments(ds, list(ds.entries()))


def test_a_60_hz_build_is_notched_at_60_hz(tmp_path):
    seg = _baselines(tmp_path, "weak-film-60hz")
    at_50 = calibrate(seg, PreprocessParams())  # the default mains: the 60 Hz lines stay in the gate's floor
    pre = calibrate_pvdf(seg, PreprocessParams())
    assert pre.mains_hz == 60.0
    assert {1, 2, 3} <= set(pre.notch_harmonics)
    assert mains_residual(pre) < 0.5 < mains_residual(at_50)


@pytest.mark.parametrize("given", [50.0, 60.0])
def test_a_50_hz_build_keeps_the_50_hz_calibration(tmp_path, given):
    seg = _baselines(tmp_path, "nominal")
    pre = calibrate_pvdf(seg, PreprocessParams(mains_hz=given))
    assert pre == calibrate(seg, PreprocessParams(mains_hz=50.0))  # what the fit calibrated before, whatever it was told


def _contact_snr(tmp_path, build: str) -> float:
    out = tmp_path / Path(build).stem
    assert main(["simulate", "ramp", "--trials", "ramp=12", "--seed", "3", "--build", build, "--out", str(out), "--quiet"]) == 0
    ds = Dataset.open(out)
    entries = list(ds.entries())
    pre = calibrate_pvdf(baseline_segments(ds, entries), PreprocessParams())
    trials = [ds.load(e) for e in entries]
    return contact_snr([t.pvdf for t in trials], [int(np.searchsorted(t.pvdf_t, e["onset_s"])) for t, e in zip(trials, entries)], pre)


def test_the_contact_snr_tells_a_noisy_amplifier_from_the_nominal_build(tmp_path, corner_build):
    nominal, noisy = _contact_snr(tmp_path, "nominal"), _contact_snr(tmp_path, "noisy-amplifier")
    assert 2.0 < nominal / noisy < 4.5  # the noisy build has 3x the PVDF noise, the same film
    weakest = _contact_snr(tmp_path, str(corner_build))  # half the coupling on the noisy amplifier
    assert 1.5 < noisy / weakest < 2.5  # half the film's signal over the same noise
    rules = [[r.name for r in resolve(BuildProfile(contact_snr=snr), ("PC",)).rules] for snr in (nominal, noisy, weakest)]
    assert rules == [[], ["weak-signal"], ["film-limited"]]  # PC's film-limited settings on the corner only
    assert contact_snr([np.zeros(4000)], [4000], calibrate_pvdf([np.random.default_rng(0).normal(0, 1e-3, 4000)], PreprocessParams())) is None


def test_the_noise_rms_is_that_of_the_filtered_baseline():
    rng = np.random.default_rng(1)
    seg = [rng.normal(0.0, 2e-3, 20000) for _ in range(4)]
    pre = calibrate_pvdf(seg, PreprocessParams())
    filtered = np.concatenate([y[2000:] for y in filter_segments(seg, pre, 2000.0)])  # past the filters' start
    assert noise_rms(pre) == pytest.approx(float(np.std(filtered)), rel=0.05)


def _singletact_noise(tmp_path, build: str) -> float:
    out = tmp_path / Path(build).stem
    assert main(["simulate", "ramp", "--trials", "ramp=12", "--seed", "3", "--build", build, "--out", str(out), "--quiet"]) == 0
    ds = Dataset.open(out)
    return singletact_noise(baseline_segments(ds, list(ds.entries()), channel="st"))


def test_the_singletact_noise_tells_the_noisy_singletacts_from_the_quiet_ones(tmp_path, corner_build):
    quiet = [_singletact_noise(tmp_path, b) for b in ("nominal", "stiff-film-slow-rig")]  # 1x and 0.5x the noise
    noisy = [_singletact_noise(tmp_path, b) for b in ("noisy-amplifier", str(corner_build))]  # 2x and 3x
    assert 0.002 < quiet[1] < quiet[0] < 0.007 and quiet[0] < noisy[0] < noisy[1] < 0.02
    plans = [resolve(BuildProfile(st_noise_n=n), ("SA1", "RA")).plan.classes for n in quiet + noisy]
    assert [(p["SA1"].restarts, p["SA1"].saturated_starts) for p in plans] == [(0, ()), (0, ()), (1, (-2.0,)), (1, (-2.0,))]
    assert all(p["RA"].restarts == 0 for p in plans)


def test_the_singletact_noise_is_the_sample_noise_whatever_the_drift():
    rng = np.random.default_rng(2)
    drift = np.linspace(0.0, 0.5, 300)  # 0.5 N over 3 s: far slower than the noise
    seg = [drift + rng.normal(0.0, 0.01, 300) for _ in range(8)]
    assert singletact_noise(seg) == pytest.approx(0.01, rel=0.1)
    assert np.std(seg[0]) > 0.1  # the drift alone would dominate a plain RMS
    assert singletact_noise([np.zeros(2)]) is None and singletact_noise([]) is None
