"""The encode and demo commands, run through the real CLI entry point."""

import json

import numpy as np
import pytest

from touchreal.cli import main
from touchreal.encoding.encoder import encode_population
from touchreal.params import ClassParams, EncoderParams, default_params
from touchreal.preprocess.pipeline import preprocess_trial
from touchreal.recording import write_dataset
from touchreal.stream import encode_trial

from helpers import synthetic_trial


def _dataset(tmp_path):
    trials = {"a": synthetic_trial(seed=0), "b": synthetic_trial(seed=1, freq_hz=400.0)}
    entries = [
        {"id": i, "protocol": "ramp", "condition": "c", "repeat": r, "params": {}, "onset_s": 0.3, "stim_end_s": 1.05}
        for r, i in enumerate(trials)
    ]
    write_dataset(tmp_path / "ds", {"name": "t", "trials": entries}, trials)
    return tmp_path / "ds", trials


def test_encode_writes_one_json_per_trial(tmp_path, capsys):
    ds, trials = _dataset(tmp_path)
    p = default_params()
    assert p.alignment.lag_ms > 0
    assert main(["encode", str(ds), "--out", str(tmp_path / "out")]) == 0
    assert main(["encode", str(ds), "--out", str(tmp_path / "raw"), "--clock", "sensor"]) == 0
    for tid, trial in trials.items():
        got = json.loads((tmp_path / "out" / f"{tid}.json").read_text())
        raw = json.loads((tmp_path / "raw" / f"{tid}.json").read_text())
        assert set(got) == {"SA1", "RA", "PC"}
        stamps = encode_trial(trial, p)  # what the online stream emits
        for c in got:
            np.testing.assert_allclose(raw[c], stamps[c], atol=1e-6)
            np.testing.assert_allclose(got[c], stamps[c] - p.alignment.lag_ms / 1000.0, atol=1e-6)
    out = capsys.readouterr().out
    assert "encoded 2 trials" in out and "reference clock" in out and "sensor clock" in out


def test_encode_output_of_an_old_file_is_unchanged(tmp_path):
    """A file of the old representation (negative class delays, no alignment) loads with the lag
    moved into the alignment, and `touchreal encode` writes the same spike times the old encoder
    (delay < 0 added to every stamp) gave: still comparable with the dataset's reference spikes."""
    ds, trials = _dataset(tmp_path)
    new = default_params()
    old = json.loads(new.to_json())
    old["version"] = 2
    del old["alignment"]
    for name, c in old["classes"].items():
        c["delay_ms"] = new.classes[name].delay_ms - new.alignment.lag_ms
        c.pop("window_ms", None)
    assert min(c["delay_ms"] for c in old["classes"].values()) < -50.0
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert EncoderParams.load(tmp_path / "old.json").alignment.lag_ms == pytest.approx(new.alignment.lag_ms, abs=1e-9)
    assert main(["encode", str(ds), "--params", str(tmp_path / "old.json"), "--out", str(tmp_path / "out")]) == 0
    n = 0
    for tid, trial in trials.items():
        got = json.loads((tmp_path / "out" / f"{tid}.json").read_text())
        ch = preprocess_trial(trial, new.preprocess)
        legacy = [ClassParams.model_construct(**c) for c in old["classes"].values()]  # negative delays, unvalidated
        for c, want in zip(old["classes"], encode_population(ch.data[:, 0, :], ch.t0_s, legacy)):
            np.testing.assert_allclose(got[c], want, atol=1e-6)
            n += want.size
    assert n > 100


def test_encode_rejects_bad_params_and_missing_dataset(tmp_path, capsys):
    ds, _ = _dataset(tmp_path)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"classes": {"SA1": {"weights": [1, 2]}}}))
    assert main(["encode", str(ds), "--params", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "invalid parameters" in err and "classes.SA1.weights" in err
    assert main(["encode", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "no manifest.json" in capsys.readouterr().err


def test_demo_runs_without_hardware_or_shared_data(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--seconds", "3", "--out", str(out), "--taxels", "2"]) == 0
    text = capsys.readouterr().out
    assert "SA1" in text and "compute per update" in text
    spikes = json.loads((out / "spikes.json").read_text())
    assert sum(len(v) for v in spikes.values()) > 0
    assert (out / "raster.png").stat().st_size > 10_000
