"""``touchreal reference DATASET_DIR --out OUT_DIR``: files, keys, geometry, seeding, skips."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from touchreal.cli import main
from touchreal.recording import Dataset, Trial, write_dataset
from touchreal.reference.model import reference_trains


def _trial(cmd: np.ndarray, duration_s: float, cmd_t0: float = 0.0) -> Trial:
    st_t = np.arange(int(duration_s * 100)) / 100.0
    pv_t = np.arange(int(duration_s * 2000)) / 2000.0
    return Trial(st_t=st_t, st=np.zeros(st_t.size, np.float32), pvdf_t=pv_t, pvdf=np.zeros(pv_t.size, np.float32),
                 cmd_depth=cmd.astype(np.float32), cmd_t0=cmd_t0)


def _ramp_cmd(n: int = 3000) -> np.ndarray:
    x = np.zeros(n)
    x[500:700] = np.linspace(0, 1, 200)
    x[700:2000] = 1.0
    x[2000:2200] = np.linspace(1, 0, 200)
    return x


def _entry(tid: str, protocol: str, reference: dict | None, **extra) -> dict:
    e = {"id": tid, "file": "", "protocol": protocol, "condition": tid, "repeat": 0, "params": {},
         "onset_s": 0.1, "stim_end_s": 0.44, "offset_r_mm": 0.0, "offset_theta_deg": 0.0, "reference": reference}
    e.update(extra)
    return e


@pytest.fixture()
def tiny(tmp_path):
    man = {"name": "tiny", "reference": {"repeats": {"ramp": 2, "spatial_ramp": 3, "texture": 0}}, "trials": [
        _entry("r0", "ramp", {"repeats": 2, "probe_xy_mm": [0.0, 0.0], "afferent_xy_mm": [0.0, 0.0]}),
        _entry("s0", "spatial_ramp", {"repeats": 3, "probe_xy_mm": [2.0, 0.0], "afferent_xy_mm": [0.0, 0.0]},
               offset_r_mm=2.0),
        _entry("t0", "texture", None, offset_r_mm=1.0, offset_theta_deg=90.0),
    ]}
    trials = {"r0": _trial(_ramp_cmd(), 0.6), "s0": _trial(_ramp_cmd(), 0.6, cmd_t0=0.25),
              "t0": _trial(_ramp_cmd(), 0.6)}
    write_dataset(tmp_path / "ds", man, trials)
    return tmp_path


def test_writes_one_file_per_referenced_trial_and_skips_unreferenced(tiny, capsys):
    out = tiny / "out"
    assert main(["reference", str(tiny / "ds"), "--out", str(out), "--seed", "3"]) == 0
    printed = capsys.readouterr().out
    assert "skipping 1 trial(s) with reference null" in printed and "t0" in printed
    assert sorted(p.name for p in out.iterdir()) == ["r0.npz", "reference.json", "s0.npz"]
    for tid, repeats in (("r0", 2), ("s0", 3)):
        with np.load(out / f"{tid}.npz") as d:
            assert sorted(d.files) == sorted(f"ref_{c}_{k}" for c in ("SA1", "RA", "PC") for k in ("t", "off"))
            for cls, n_models in (("SA1", 4), ("RA", 9), ("PC", 4)):
                off, t = d[f"ref_{cls}_off"], d[f"ref_{cls}_t"]
                assert off.dtype == np.int32 and t.dtype == np.float32
                assert off.shape == (repeats, n_models + 1) and off[-1, -1] == t.size
    summary = json.loads((out / "reference.json").read_text())
    assert [t["id"] for t in summary["trials"]] == ["r0", "s0"]
    assert summary["skipped"] == [{"id": "t0", "reason": "reference null"}]
    assert summary["trials"][1]["probe_xy_mm"] == [2.0, 0.0]


def test_trains_equal_the_model_on_the_recording_clock(tiny):
    out = tiny / "out"
    main(["reference", str(tiny / "ds"), "--out", str(out), "--noiseless", "--repeats", "1"])
    ds = Dataset.open(tiny / "ds")
    for tid, probe, t0 in (("r0", (0.0, 0.0), 0.0), ("s0", (2.0, 0.0), 0.25)):
        cmd = ds.load(tid).cmd_depth.astype(np.float64)
        expect = reference_trains(cmd, probe_xy_mm=probe, noisy=False)
        with np.load(out / f"{tid}.npz") as d:
            for cls, ref in expect.items():
                np.testing.assert_array_equal(d[f"ref_{cls}_off"], ref.off)
                np.testing.assert_array_equal(d[f"ref_{cls}_t"], (ref.t.astype(np.float64) + t0).astype(np.float32))
        assert sum(ref.t.size for ref in expect.values()) > 0


def test_seeding_is_per_trial_and_reproducible(tiny):
    a, b, c = tiny / "a", tiny / "b", tiny / "c"
    main(["reference", str(tiny / "ds"), "--out", str(a), "--seed", "5"])
    main(["reference", str(tiny / "ds"), "--out", str(b), "--seed", "5", "--protocol", "spatial_ramp"])
    main(["reference", str(tiny / "ds"), "--out", str(c), "--seed", "6"])
    assert not (b / "r0.npz").exists()
    with np.load(a / "s0.npz") as x, np.load(b / "s0.npz") as y, np.load(c / "s0.npz") as z:
        for k in x.files:
            np.testing.assert_array_equal(x[k], y[k])  # independent of which trials run
        assert any(not np.array_equal(x[k], z[k]) for k in x.files)


def test_unreferenced_trials_on_request_use_the_entry_offset(tiny):
    out = tiny / "out"
    main(["reference", str(tiny / "ds"), "--out", str(out), "--include-unreferenced", "--noiseless"])
    summary = json.loads((out / "reference.json").read_text())
    t0 = next(t for t in summary["trials"] if t["id"] == "t0")
    np.testing.assert_allclose(t0["probe_xy_mm"], [0.0, 1.0], atol=1e-12)  # (r cos th, r sin th)
    assert t0["afferent_xy_mm"] == [0.0, 0.0] and t0["repeats"] == 1 and not t0["from_manifest"]
    assert (out / "t0.npz").exists()


def test_refuses_to_write_into_the_dataset(tiny, capsys):
    assert main(["reference", str(tiny / "ds"), "--out", str(tiny / "ds" / "trials")]) == 2
    assert "separate folder" in capsys.readouterr().err
    assert main(["reference", str(tiny / "ds"), "--out", str(tiny / "o"), "--repeats", "0"]) == 2


@pytest.mark.shared
def test_rig_references_are_reproduced_statistically(rig, tmp_path):
    """A few rig-v1 trials: our noisy references vs the stored TouchSim ones (pooled counts within 5 %)."""
    picks = []
    for protocol in ("ramp", "sine", "spatial_sine"):
        entries = rig.entries(protocol)
        picks += [entries[i] for i in np.linspace(0, len(entries) - 1, 3).astype(int)]
    (tmp_path / "ds" / "trials").mkdir(parents=True)
    for e in picks:
        os.symlink(rig.root / e["file"], tmp_path / "ds" / e["file"])
    man = {k: v for k, v in rig.manifest.items() if k != "trials"} | {"trials": picks}
    (tmp_path / "ds" / "manifest.json").write_text(json.dumps(man))
    assert main(["reference", str(tmp_path / "ds"), "--out", str(tmp_path / "out")]) == 0
    ours = np.zeros(3)
    theirs = np.zeros(3)
    for e in picks:
        stored = rig.load(e).reference
        with np.load(tmp_path / "out" / f"{e['id']}.npz") as d:
            for j, cls in enumerate(("SA1", "RA", "PC")):
                off = d[f"ref_{cls}_off"]
                assert off.shape == stored[cls].off.shape
                ours[j] += off[:, -1].astype(float).sum() - off[:, 0].sum()
                theirs[j] += stored[cls].off[:, -1].sum() - stored[cls].off[:, 0].sum()
    assert np.all(theirs > 100), theirs
    np.testing.assert_allclose(ours, theirs, rtol=0.05)
