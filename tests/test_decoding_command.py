"""``touchreal decoders train`` / ``evaluate`` end to end on tiny simulated datasets, and their errors."""

from __future__ import annotations

import json
import shutil

import pytest

from touchreal.cli import main
from touchreal.decoding.model import load_model
from touchreal.simulator.simulate import simulate_dataset


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    root = tmp_path_factory.mktemp("decoders")
    train = simulate_dataset(["ramp", "texture"], root / "train", trials={"ramp": 8, "texture": 12}, seed=11, reference=False)
    test = simulate_dataset(["ramp", "texture"], root / "test", trials={"ramp": 3, "texture": 3}, seed=12, reference=False)
    ramp_only = simulate_dataset("ramp", root / "ramp_only", trials=2, seed=13, reference=False)
    return train.root, test.root, ramp_only.root


@pytest.fixture(scope="module")
def trained(datasets, tmp_path_factory):
    models = tmp_path_factory.mktemp("models")
    assert main(["decoders", "train", str(datasets[0]), "--out", str(models), "--no-sweeps", "--quiet"]) == 0
    return models


def test_train_writes_models_with_metadata(trained, datasets):
    names = sorted(p.stem for p in trained.glob("*.onnx"))
    assert names == ["force", "force_fast", "force_ra", "force_sa1", "texture", "texture_both", "texture_rate",
                     "texture_spatial", "texture_spectral"]
    tex = load_model(trained / "texture.onnx").meta
    assert tex["labels"] == ["comb_0.5mm", "comb_2mm", "comb_4mm"]
    assert tex["training"]["split"] == "train" and tex["training"]["heldout_trials"] == 6
    assert tex["metrics"]["n_windows"] > 0 and 0.0 <= tex["metrics"]["acc"] <= 1.0
    assert tex["alignment"]["class"] == "PC" and tex["window_ms"] == 500.0
    force = load_model(trained / "force.onnx").meta
    assert force["classes"] == ["SA1", "RA"] and force["input"]["shape"] == [None, 13, 2]
    fast = load_model(trained / "force_fast.onnx").meta
    assert fast["window_ms"] == fast["step_ms"] == 32.0 and fast["input"]["shape"] == [None, 4, 2]
    assert fast["state"]["size"] == 12 and fast["outputs"] == ["force_N", "state_out"]
    scan = load_model(trained / "texture_spatial.onnx").meta  # the scanning model: speed input, no anchor
    assert scan["alignment"] is None and scan["context"]["input"] == "speed_mm_s" and scan["metrics"]["n_windows"] > 0
    held = json.loads((trained / "metrics.json").read_text())
    assert "texture.temporal.acc_500ms" in held and "texture.spatial.acc_200ms" in held and held["info.split"] == "heldout"


def test_train_only_named_models_and_unknown_names_are_an_error(datasets, tmp_path, capsys):
    out = tmp_path / "only"
    assert main(["decoders", "train", str(datasets[0]), "--tasks", "texture", "--only", "texture_spectral",
                 "--out", str(out), "--no-sweeps", "--quiet"]) == 0
    assert sorted(p.stem for p in out.glob("*.onnx")) == ["texture_spectral"]
    spectral = load_model(out / "texture_spectral.onnx").meta
    assert spectral["classes"] == ["SA1", "RA", "PC"] and spectral["bin_ms"] == 1.0 and spectral["input"]["shape"] == [None, 200, 3]
    rc = main(["decoders", "train", str(datasets[0]), "--tasks", "texture", "--only", "force_fast", "--out", str(tmp_path / "x"), "--quiet"])
    assert rc == 2 and "force_fast" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_evaluate_all_on_a_test_dataset(trained, datasets, tmp_path, capsys):
    out = tmp_path / "METRICS.json"
    assert main(["decoders", "evaluate", str(datasets[1]), "--models", str(trained), "--out", str(out), "--split", "all", "--quiet"]) == 0
    m = json.loads(out.read_text())
    for key in ("force.SA1+RA.r2", "force.SA1.rmse", "force.RA.mae", "force.SA1+RA.oscillation", "force.SA1+RA.pearson_r",
                "force.SA1+RA.trial_rmse", "force.window.128ms.SA1+RA.r2", "force.fast.SA1+RA.r2",
                "force.fast.window.32ms.SA1+RA.rmse", "texture.temporal.acc_500ms",
                "texture.rate.acc_500ms_fold_std", "texture.both.acc_500ms", "texture.spectral.acc_200ms", "texture.chance"):
        assert key in m, key
    assert len(m["force.SA1+RA.trial_rmse"]) == 3 and m["texture.chance"] == pytest.approx(1 / 3)
    assert m["info.runtime"] == "onnxruntime" and m["info.split"] == "all"
    assert "force.SA1+RA.r2" in capsys.readouterr().out


def test_dataset_without_texture_trials_is_a_clear_error(trained, datasets, tmp_path, capsys):
    rc = main(["decoders", "evaluate", str(datasets[2]), "--models", str(trained), "--out", str(tmp_path / "m.json"), "--quiet"])
    assert rc == 2 and "no texture trials" in capsys.readouterr().err
    rc = main(["decoders", "train", str(datasets[2]), "--out", str(tmp_path / "m"), "--quiet"])
    assert rc == 2 and "no texture trials" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()  # nothing written


def test_bad_model_files_are_clear_errors(trained, datasets, tmp_path, capsys):
    folder = tmp_path / "models"
    shutil.copytree(trained, folder)
    (folder / "junk.onnx").write_bytes(b"\x08\x01garbage")
    rc = main(["decoders", "evaluate", str(datasets[1]), "--models", str(folder), "--out", str(tmp_path / "m.json"), "--split", "all"])
    err = capsys.readouterr().err
    assert rc == 2 and "junk.onnx: not an ONNX model" in err
    (folder / "junk.onnx").unlink()
    meta = json.loads((folder / "texture.json").read_text())
    meta["labels"] = meta["output_names"] = ["a", "b", "c"]
    (folder / "texture.json").write_text(json.dumps(meta))
    rc = main(["decoders", "evaluate", str(datasets[1]), "--models", str(folder), "--out", str(tmp_path / "m.json"), "--split", "all"])
    assert rc == 2 and "does not match the one embedded" in capsys.readouterr().err
    assert not (tmp_path / "m.json").exists()


def test_bench_decoders_runs_on_the_installed_models(capsys):
    """Smoke test only (figures are printed by the bench, never asserted)."""
    assert main(["bench", "decoders", "--updates", "3", "--taxels", "1", "4"]) == 0
    out = capsys.readouterr().out
    assert "force" in out and "texture" in out and "run time against accuracy" in out
