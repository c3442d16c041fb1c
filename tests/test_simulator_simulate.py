"""Offline simulated datasets: recording format, manifest fields, trial picking, CLI, reference spikes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_path

from touchreal.cli import main as cli_main
from touchreal.recording import Dataset
from touchreal.simulator.simulate import REFERENCE_REPEATS, conditions, pick_trials, simulate_dataset, simulate_trial

REPO = Path(__file__).resolve().parents[1]
ENTRY_FIELDS = {
    "id", "protocol", "condition", "repeat", "params", "offset_r_mm", "offset_theta_deg", "texture",
    "onset_s", "stim_end_s", "events", "duration_s", "reference",
}


def rig_v1() -> Path:
    """rig-v1 under TOUCHREAL_SHARED (default ../shared next to the repository), or skip."""
    shared = shared_path()
    root = shared / "datasets" / "rig-v1"
    if not (root / "manifest.json").is_file():
        pytest.skip(f"rig-v1 recordings not found under {shared} (set TOUCHREAL_SHARED to the shared data folder)")
    return root


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory) -> Dataset:
    out = tmp_path_factory.mktemp("sim") / "ds"
    return simulate_dataset(["ramp", "sine", "texture", "spatial"], out, trials=2, seed=3)


def test_dataset_opens_and_every_trial_validates(small_dataset):
    ds = Dataset.open(small_dataset.root)
    assert ds.manifest["counts"] == {"ramp": 2, "sine": 2, "texture": 2, "spatial_ramp": 2, "spatial_sine": 2}
    for e, tr in ds:  # load() validates rates, clocks and reference layout
        assert ENTRY_FIELDS <= set(e)
        assert e["n_st"] == tr.st.size == round(e["duration_s"] * 100)
        assert e["n_pvdf"] == tr.pvdf.size == round(e["duration_s"] * 2000)
        assert e["n_cmd"] == tr.cmd_depth.size == round(e["duration_s"] * 5000)
        assert 0.2 <= e["onset_s"] <= 0.5
        assert e["events"]["onset_s"] == e["onset_s"] and e["events"]["end_s"] == e["stim_end_s"]
        assert tr.st.dtype == np.float32 and tr.pvdf.dtype == np.float32
        # the command starts at the onset
        first = np.flatnonzero(tr.cmd_depth != 0)[0] / 5000.0
        assert e["onset_s"] <= first < e["onset_s"] + 0.001
        if e["protocol"] == "texture":
            assert e["duration_s"] == 3.0 and tr.cmd_x is not None and tr.cmd_x.max() == pytest.approx(60.0)
            assert e["texture"] == f"comb_{e['params']['spacing_mm']:g}mm" and e["reference"] is None
            assert not tr.reference
        else:
            assert tr.cmd_x is None
            assert 0.3 <= e["duration_s"] - e["stim_end_s"] <= 0.61
            reps = REFERENCE_REPEATS[e["protocol"]]
            assert e["reference"]["repeats"] == reps
            assert set(tr.reference) == {"SA1", "RA", "PC"}
            assert all(r.repeats == reps for r in tr.reference.values())
        if e["protocol"].startswith("spatial"):
            th = np.radians(e["offset_theta_deg"])
            assert e["reference"]["probe_xy_mm"] == pytest.approx([e["offset_r_mm"] * np.cos(th), e["offset_r_mm"] * np.sin(th)], abs=1e-6)
            assert e["reference"]["afferent_xy_mm"] == [0.0, 0.0]


def test_reference_spikes_come_from_the_reference_model():
    try:
        from touchreal.reference.model import reference_trains
    except ImportError:
        pytest.skip("touchreal.reference.model not available yet")
    cond = next(c for c in conditions("ramp") if c.condition == "ramp_d1.4_vu40_vd40_h0.6")
    entry, trial = simulate_trial(cond, 0, "ramp_0000", seed=5)
    sa1 = trial.reference["SA1"]
    assert sa1.repeats == 6 and sa1.n_models == 4
    spikes = np.concatenate(sa1.trains())
    assert spikes.size > 20
    # spikes on the recording clock: during contact, not before the onset
    assert spikes.min() > entry["onset_s"] and spikes.max() < entry["duration_s"]
    # the same call simulate_trial makes (its third child seed drives the reference): the same trains
    ref_seed = int(np.random.SeedSequence(5).spawn(3)[2].generate_state(1)[0])
    again = reference_trains(
        trial.cmd_depth.astype(np.float64), fs_hz=5000.0, probe_xy_mm=(0.0, 0.0), afferent_xy_mm=(0.0, 0.0),
        repeats=6, noisy=True, delays=False, seed=ref_seed, pin_radius_mm=0.5,
    )
    for c in ("SA1", "RA", "PC"):
        got, want = trial.reference[c].trains(), again[c].trains()
        assert len(got) == len(want) and all(np.array_equal(a, b) for a, b in zip(got, want))
    assert set(again) == {"SA1", "RA", "PC"}


def test_pick_trials_spreads_over_conditions_with_consistent_repeats():
    conds = conditions("sine")
    picked = pick_trials(conds, 12, np.random.default_rng(0))
    per = {}
    for c, r in picked:
        per.setdefault(c.condition, []).append(r)
    assert sorted(len(v) for v in per.values()) == [2, 2, 2, 3, 3]
    assert all(sorted(v) == list(range(len(v))) for v in per.values())
    few = pick_trials(conditions("ramp"), 5, np.random.default_rng(1))
    assert len({c.condition for c, _ in few}) == 5 and all(r == 0 for _, r in few)


def test_single_protocol_name_and_unknown_protocol(tmp_path):
    ds = simulate_dataset("texture", tmp_path / "t", trials=4, seed=0, reference=False)
    assert ds.manifest["counts"] == {"texture": 4}
    assert sorted(e["repeat"] for e in ds.trials) == [0, 0, 0, 1]
    with pytest.raises(ValueError):
        simulate_dataset("poke", tmp_path / "x", trials=1)


def test_design_sizes_match_the_paper():
    assert len(conditions("ramp")) == 448
    assert len(conditions("sine")) == 5 and len(conditions("texture")) == 3
    assert len(conditions("spatial_ramp")) == 6 * (1 + 15 * 12)
    assert len(conditions("spatial_sine")) == 5 * (1 + 15 * 12)


def test_cli_writes_reproducible_datasets(tmp_path):
    args = ["simulate", "spatial", "--trials", "1", "--seed", "9", "--quiet", "--no-reference"]
    assert cli_main(args + ["--out", str(tmp_path / "a")]) == 0
    assert cli_main(args + ["--out", str(tmp_path / "b")]) == 0
    a, b = Dataset.open(tmp_path / "a"), Dataset.open(tmp_path / "b")
    assert [e["protocol"] for e in a.trials] == ["spatial_ramp", "spatial_sine"]
    for (ea, ta), (eb, tb) in zip(a, b):
        assert ea == eb
        assert np.array_equal(ta.st, tb.st) and np.array_equal(ta.pvdf, tb.pvdf)
    assert json.loads((tmp_path / "a" / "manifest.json").read_text())["reference"] is None


@pytest.mark.shared
def test_manifest_entries_have_rig_v1_fields_and_names(small_dataset):
    rig = json.loads((rig_v1() / "manifest.json").read_text())
    rig_fields = set(rig["trials"][0])
    rig_conditions = {e["condition"] for e in rig["trials"]}
    for e in small_dataset.trials:
        assert set(e) == rig_fields
        if e["protocol"] in ("ramp", "sine", "texture"):
            assert e["condition"] in rig_conditions
        same = next(r for r in rig["trials"] if r["protocol"] == e["protocol"])
        assert set(e["params"]) == set(same["params"])
        assert set(e["events"]) == set(same["events"])


def test_cli_trial_counts_per_protocol(tmp_path, capsys):
    args = ["simulate", "ramp", "sine", "--trials", "ramp=3,sine=2", "--seed", "1", "--quiet", "--no-reference"]
    assert cli_main(args + ["--out", str(tmp_path / "d")]) == 0
    assert Dataset.open(tmp_path / "d").manifest["counts"] == {"ramp": 3, "sine": 2}
    assert cli_main(["simulate", "ramp", "--trials", "sine=2", "--out", str(tmp_path / "e")]) == 2
    assert "not being simulated" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(["simulate", "ramp", "--trials", "ramp=0", "--out", str(tmp_path / "f")])


def test_texture_hard_draws_depth_and_build_per_trial_at_the_chosen_speeds(tmp_path, capsys):
    ds = simulate_dataset("texture-hard", tmp_path / "hard", trials=10, seed=2, reference=False, speeds_mm_s=(20.0, 60.0))
    assert ds.manifest["counts"] == {"texture_hard": 10} and ds.manifest["simulator"]["speeds_mm_s"] == [20.0, 60.0]
    design = ds.manifest["protocols"]["texture_hard"]
    depths, couplings, lags = set(), set(), set()
    for e, tr in ds:
        v, var = e["params"]["speed_mm_s"], e["variation"]
        assert e["protocol"] == "texture" and v in (20.0, 60.0) and e["texture"] == f"comb_{e['params']['spacing_mm']:g}mm"
        assert tr.cmd_x.max() == pytest.approx(v * design["slide_s"])  # slid at its speed
        assert tr.cmd_depth.max() == pytest.approx(var["depth_mm"], abs=1e-6)  # pressed to its own depth
        assert 0.4 <= var["depth_mm"] <= 0.6 and 6.5 <= var["build"]["rig_lag_ms"] <= 61.5 and var["build"]["mains_hz"] in (50, 60)
        lo, hi = design["build_ratio"]["pvdf_coupling"]
        assert lo <= var["build"]["pvdf_coupling"] <= hi
        depths.add(var["depth_mm"]), couplings.add(var["build"]["pvdf_coupling"]), lags.add(var["build"]["rig_lag_ms"])
    assert len(depths) == len(couplings) == len(lags) == 10  # independent draws per trial
    assert cli_main(["simulate", "texture", "--speeds", "30", "--out", str(tmp_path / "x"), "--quiet"]) == 2
    assert "apply to texture-hard only" in capsys.readouterr().err
    same = simulate_dataset("texture-hard", tmp_path / "same", trials=3, seed=2, reference=False, vary_build=False)
    assert [e["variation"]["build"] for e in same.entries("texture")] == [same.manifest["simulator"]["build"]] * 3
