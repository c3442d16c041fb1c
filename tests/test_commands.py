"""The encode and demo commands, run through the real CLI entry point."""

import json

import numpy as np

from touchreal.cli import main
from touchreal.params import default_params
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
    assert main(["encode", str(ds), "--out", str(tmp_path / "out")]) == 0
    for tid, trial in trials.items():
        got = json.loads((tmp_path / "out" / f"{tid}.json").read_text())
        assert set(got) == {"SA1", "RA", "PC"}
        want = encode_trial(trial, default_params())
        for c in got:
            np.testing.assert_allclose(got[c], want[c], atol=1e-6)
    assert "encoded 2 trials" in capsys.readouterr().out


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
