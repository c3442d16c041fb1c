import json

import numpy as np
import pytest

from touchreal.recording import Dataset, RecordingError, ReferenceTrains, load_trial, save_trial, write_dataset

from helpers import synthetic_trial


def _manifest(ids):
    return {
        "name": "t",
        "trials": [
            {"id": i, "file": f"trials/{i}.npz", "protocol": "ramp", "condition": "c", "repeat": 0, "params": {}, "onset_s": 0.3, "stim_end_s": 1.0}
            for i in ids
        ],
    }


def test_reference_trains_pack_roundtrip():
    trains = [[np.array([0.1, 0.2]), np.array([]), np.array([0.5])], [np.array([0.3]), np.array([0.4, 0.6]), np.array([])]]
    ref = ReferenceTrains.from_trains(trains)
    assert ref.off.shape == (2, 4)
    for r in range(2):
        for m in range(3):
            np.testing.assert_allclose(ref.train(r, m), trains[r][m])


def test_dataset_roundtrip(tmp_path):
    tr = synthetic_trial()
    tr.reference = {"SA1": ReferenceTrains.from_trains([[np.array([0.4, 0.5])]])}
    ds = write_dataset(tmp_path / "d", _manifest(["a", "b"]), {"a": tr, "b": synthetic_trial(seed=1)})
    assert [e["file"] for e in ds.trials] == ["trials/a.npz", "trials/b.npz"]
    back = ds.load("a")
    np.testing.assert_array_equal(back.st, tr.st)
    np.testing.assert_array_equal(back.pvdf_t, tr.pvdf_t)
    np.testing.assert_allclose(back.reference["SA1"].train(0, 0), [0.4, 0.5], rtol=1e-6)
    assert ds.entries("ramp")[1]["n_pvdf"] == tr.pvdf.size


def _broken(tmp_path, **changes):
    d = synthetic_trial().to_npz_dict()
    for k, v in changes.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    path = tmp_path / "x.npz"
    np.savez(path, **d)
    return path


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"st": None}, "missing keys"),
        ({"pvdf_t": np.r_[0.0, 0.0005, 0.0004, np.arange(3, 3000) / 2000.0]}, "not strictly increasing"),
        ({"st_t": np.arange(150) / 50.0, "st": np.zeros(150, np.float32)}, "expected 100 Hz"),
        ({"pvdf": np.zeros(10, np.float32)}, "equal length"),
        ({"ref_RA_t": np.zeros(3, np.float32)}, "must come together"),
        ({"ref_RA_t": np.zeros(3, np.float32), "ref_RA_off": np.array([[0, 5]], np.int32)}, "consistently"),
        ({"st_t": np.r_[np.nan, np.arange(1, 150) / 100.0]}, "non-finite"),
    ],
)
def test_malformed_trials_are_rejected_clearly(tmp_path, changes, message):
    with pytest.raises(RecordingError, match=message):
        load_trial(_broken(tmp_path, **changes))


def test_not_a_trial_file(tmp_path):
    p = tmp_path / "junk.npz"
    p.write_bytes(b"not a zip")
    with pytest.raises(RecordingError, match="not a readable trial"):
        load_trial(p)


def test_save_validates_before_writing(tmp_path):
    tr = synthetic_trial()
    tr.st_t = tr.st_t[::-1].copy()
    with pytest.raises(RecordingError):
        save_trial(tmp_path / "y.npz", tr)
    assert not (tmp_path / "y.npz").exists()


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda m: m["trials"][0].pop("onset_s"), "lacks"),
        (lambda m: m["trials"][0].update(protocol="poke"), "unknown protocol"),
        (lambda m: m["trials"].append(dict(m["trials"][0])), "duplicate"),
        (lambda m: m.pop("trials"), "'trials' list"),
    ],
)
def test_bad_manifest(tmp_path, mutate, message):
    m = _manifest(["a"])
    mutate(m)
    (tmp_path / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(RecordingError, match=message):
        Dataset.open(tmp_path)


def test_missing_manifest(tmp_path):
    with pytest.raises(RecordingError, match="no manifest.json"):
        Dataset.open(tmp_path)


@pytest.mark.shared
@pytest.mark.slow
def test_every_rig_trial_validates(rig):
    counts = {}
    for e in rig.trials:
        tr = rig.load(e)
        counts[e["protocol"]] = counts.get(e["protocol"], 0) + 1
        assert tr.st.size == e["n_st"] and tr.pvdf.size == e["n_pvdf"] and tr.cmd_depth.size == e["n_cmd"]
        if e["reference"]:
            assert tr.reference["RA"].repeats == e["reference"]["repeats"]
            assert tr.reference["RA"].n_models == 9 and tr.reference["SA1"].n_models == 4
    assert counts == rig.manifest["counts"]
