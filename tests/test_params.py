import json

import pytest

from touchreal.params import EncoderParams, ParamsError, default_params


def test_default_params_load_and_roundtrip(tmp_path):
    p = default_params()
    assert list(p.classes) == ["SA1", "RA", "PC"]
    path = tmp_path / "p.json"
    p.save(path)
    assert EncoderParams.load(path) == p
    assert json.loads(path.read_text())["schema"] == "touchreal.params"


def _raw():
    return json.loads(default_params().to_json())


@pytest.mark.parametrize(
    "mutate, fragment",
    [
        (lambda d: d["classes"]["SA1"].update(weights=[1.0] * 7), "classes.SA1.weights"),
        (lambda d: d["classes"]["RA"].update(tau_ms=-1), "classes.RA.tau_ms"),
        (lambda d: d["classes"].update(SA2=d["classes"]["SA1"]), "unknown classes"),
        (lambda d: d["classes"]["PC"].update(colour="red"), "classes.PC.colour"),
        (lambda d: d.update(version=4), "version"),
        (lambda d: d["classes"]["RA"].update(lowpass_hz=1.0), "classes.RA.lowpass_hz"),
        (lambda d: d.update(version=1) or d["classes"]["RA"].update(lowpass_hz=100.0), "need schema version 2"),
        (lambda d: d["preprocess"].update(window_ms=1000), "preprocess.window_ms"),
        (lambda d: d.update(version=2) or d["classes"]["SA1"].update(window_ms=16.0), "needs schema version 3"),
        (lambda d: d["classes"]["SA1"].update(window_ms=2.0), "classes.SA1.window_ms"),
        (lambda d: d["preprocess"].update(notch_harmonics=[0, 1]), "preprocess.notch_harmonics"),
        (lambda d: d.update(classes={}), "at least one class"),
    ],
)
def test_invalid_uploads_name_the_field(mutate, fragment):
    d = _raw()
    mutate(d)
    with pytest.raises(ParamsError, match="invalid parameters") as err:
        EncoderParams.parse(d)
    assert fragment in str(err.value)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_nan_and_inf_rejected(bad):
    d = _raw()
    d["classes"]["SA1"]["delay_ms"] = bad
    text = json.dumps(d)  # Python's json writes NaN / Infinity, as a careless client would
    with pytest.raises(ParamsError, match="delay_ms"):
        EncoderParams.parse(text)


def test_not_json():
    with pytest.raises(ParamsError, match="not valid JSON"):
        EncoderParams.parse("{weights: ")


def test_gate_calibration_must_be_consistent():
    d = _raw()
    d["preprocess"]["gate"] = {"freqs_hz": [0, 10, 5], "noise_asd": [1, 1, 1]}
    with pytest.raises(ParamsError, match="strictly increasing"):
        EncoderParams.parse(d)


def test_version_1_files_still_load_without_the_new_input_stage():
    d = _raw()
    d["version"] = 1
    for c in d["classes"].values():
        c.pop("lowpass_hz", None)
        c.pop("negative_lead_ms", None)
    p = EncoderParams.parse(d)
    assert p.version == 1
    assert all(c.lowpass_hz is None and c.negative_lead_ms == 0.0 for c in p.classes.values())


def test_class_window_defaults_to_the_preprocessing_window():
    d = _raw()
    d["version"] = 3
    d["classes"]["SA1"]["window_ms"] = 16.0
    p = EncoderParams.parse(d)
    assert p.window_ms("SA1") == 16.0
    assert p.window_ms("PC") == p.preprocess.window_ms

