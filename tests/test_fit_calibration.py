"""The fit's PVDF calibration finds the build's mains frequency: simulated builds on 50 and 60 Hz
mains (the real simulator, `touchreal simulate --build`)."""

from __future__ import annotations

import numpy as np
import pytest

from touchreal.cli import main
from touchreal.fitting.calibration import calibrate_pvdf, mains_residual
from touchreal.fitting.trials import baseline_segments
from touchreal.params import PreprocessParams
from touchreal.preprocess.gate import calibrate, gate_thresholds
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


def test_the_gate_factor_scales_only_the_gate_threshold(tmp_path):
    seg = _baselines(tmp_path, "noisy-amplifier")
    kept = calibrate_pvdf(seg, PreprocessParams())  # the product's factor
    fit = calibrate_pvdf(seg, PreprocessParams(), gate_factor=2.0)
    assert kept.gate.factor == 3.0 and fit.gate.factor == 2.0
    assert fit.model_copy(update={"gate": kept.gate}) == kept and fit.gate.noise_asd == kept.gate.noise_asd
    w = np.hanning(256)
    np.testing.assert_allclose(gate_thresholds(fit.gate, w, 2000.0), gate_thresholds(kept.gate, w, 2000.0) * 2.0 / 3.0)
