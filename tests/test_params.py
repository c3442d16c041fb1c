import json

import numpy as np
import pytest

from touchreal.params import DEFAULT_PARAMS_PATH, EncoderParams, ParamsError, default_params


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
        (lambda d: d.update(version=5), "version"),
        (lambda d: d["classes"]["RA"].update(lowpass_hz=1.0), "classes.RA.lowpass_hz"),
        (lambda d: d.update(version=1) or d["classes"]["RA"].update(lowpass_hz=100.0), "need schema version 2"),
        (lambda d: d["preprocess"].update(window_ms=1000), "preprocess.window_ms"),
        (lambda d: d.update(version=2) or d["classes"]["SA1"].update(window_ms=16.0), "needs schema version 3"),
        (lambda d: d["classes"]["SA1"].update(window_ms=2.0), "classes.SA1.window_ms"),
        (lambda d: d["classes"]["PC"].update(highpass_hz=0.0), "classes.PC.highpass_hz"),
        (lambda d: d["classes"]["PC"].update(highpass_hz=200.0), "classes.PC.highpass_hz"),
        (lambda d: d.update(version=3) or d["classes"]["PC"].update(highpass_hz=5.0), "needs schema version 4"),
        (lambda d: d["classes"]["RA"].update(delay_ms=-5.0), "classes.RA.delay_ms"),  # with an alignment: >= 0
        (lambda d: d["alignment"].update(lag_ms=-1.0), "alignment.lag_ms"),
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
        c.pop("window_ms", None)
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



def _legacy(version: int, delays: dict[str, float]) -> dict:
    d = _raw()
    d["version"] = version
    del d["alignment"]
    for c, v in delays.items():
        d["classes"][c]["delay_ms"] = v
        d["classes"][c].pop("window_ms", None)  # older files have no class windows
    return d


@pytest.mark.parametrize("version", [1, 2, 3])
def test_files_without_alignment_move_negative_delays_into_it(version):
    d = _legacy(version, {"SA1": -63.0, "RA": -27.5, "PC": 4.0})
    if version == 1:
        for c in d["classes"].values():
            c.pop("lowpass_hz", None)
            c.pop("negative_lead_ms", None)
    d["provenance"]["dataset"] = "rig-v1"
    p = EncoderParams.parse(d)
    assert p.alignment.lag_ms == 63.0 and p.alignment.dataset == "rig-v1"
    assert {c: v.delay_ms for c, v in p.classes.items()} == {"SA1": 0.0, "RA": 35.5, "PC": 67.0}
    # the stamps move by the lag, the reference-clock times do not
    stamps = np.array([1.0, 2.5])
    for c, old in (("SA1", -63.0), ("RA", -27.5), ("PC", 4.0)):
        np.testing.assert_allclose(p.reference_times(stamps + p.classes[c].delay_ms / 1000), stamps + old / 1000, atol=1e-12)
    # written back, it is a file of the current representation
    again = EncoderParams.parse(p.to_json())
    assert again == p and json.loads(p.to_json())["alignment"]["lag_ms"] == 63.0


def test_files_without_negative_delays_need_no_alignment():
    p = EncoderParams.parse(_legacy(2, {"SA1": 0.0, "RA": 3.0, "PC": 1.0}))
    assert p.alignment.lag_ms == 0.0 and p.classes["RA"].delay_ms == 3.0
    np.testing.assert_array_equal(p.reference_times(np.array([0.5])), [0.5])


def test_shipped_defaults_follow_the_current_rules():
    raw = json.loads(DEFAULT_PARAMS_PATH.read_text())
    assert raw["version"] == 3 and raw["alignment"]["lag_ms"] > 0
    assert all(c["delay_ms"] >= 0 for c in raw["classes"].values())
    p = default_params()  # the fast path: SA1 and RA do not wait for PC's window
    assert (p.window_ms("SA1"), p.window_ms("RA"), p.window_ms("PC")) == (16.0, 16.0, 128.0)


def test_windows_group_classes():
    d = _raw()
    d["classes"]["SA1"]["window_ms"] = 16.0
    d["classes"]["RA"]["window_ms"] = 16.0
    assert EncoderParams.parse(d).windows_ms() == {16.0: ["SA1", "RA"], d["preprocess"]["window_ms"]: ["PC"]}


def test_the_provenance_keeps_booleans_and_nulls_as_json_wrote_them():
    d = json.loads(default_params().to_json())
    d["provenance"] = {"weak_signal": False, "noisy_singletact": True, "contact_snr": None, "n": 3, "x": 0.5}
    p = EncoderParams.parse(d)
    assert p.provenance == d["provenance"] and type(p.provenance["weak_signal"]) is bool  # not 0.0
    assert json.loads(p.to_json())["provenance"] == d["provenance"]
