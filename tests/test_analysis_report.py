"""``touchreal evaluate`` on a tiny subset of rig-v1: every output is written and consistent."""

from __future__ import annotations

import json

import numpy as np
import pytest

from test_fitting_fit import tiny_rig_subset
from touchreal import splits
from touchreal.analysis import metrics as M
from touchreal.analysis import report as R
from touchreal.analysis import trials as T
from touchreal.params import default_params
from touchreal.settings import CHANNELS, CLASSES

pytestmark = pytest.mark.shared

EXPECTED_FILES = {
    "report.md", "metrics.json", "fig7_time_courses.png", "fig8_vr_distance.png", "fig9_frequency_response.png",
    "fig10_maps.png", "fig10_radial.png", "fig10_area.png", "fig10_threshold_sweep.png", "fig11_anisotropy.png",
    "fig12_window_sweep.png",
}


@pytest.fixture(scope="module")
def tiny(rig, tmp_path_factory):
    return tiny_rig_subset(rig, tmp_path_factory.mktemp("tiny"))


@pytest.mark.slow  # ~18 s: the whole report with its sweep and spatial figures; .ci/run runs it (pytest -m slow)
def test_evaluate_writes_every_file_and_consistent_metrics(tiny, tmp_path):
    out = tmp_path / "report"
    cfg = R.EvalConfig(sweep_windows_ms=(32.0, 128.0), sweep_max_ramp_conditions=1, latency_trials=0)
    m = R.evaluate(tiny.root, default_params(), out, cfg)
    assert EXPECTED_FILES <= {p.name for p in out.iterdir()}
    for name in EXPECTED_FILES - {"report.md", "metrics.json"}:
        assert (out / name).stat().st_size > 1000
    disk = json.loads((out / "metrics.json").read_text())
    assert set(m) == set(disk) and m["targets"].keys() == disk["targets"].keys()  # returned = written
    assert disk["classes"] == list(CLASSES)
    assert "all" in disk["evaluated_on"]  # defaults were not fitted on this dataset: every trial is held out
    for c in CLASSES:
        s = disk["mapping"][c]["all"]
        assert s["n_conditions"] == 2 + 5
        assert s["ratio_inter_intra"] == pytest.approx(s["vr_ts_tr_mean"] / s["vr_ts_ts_mean"])
        assert sum(disk["channel_contribution_pct"][c][ch] for ch in CHANNELS) == pytest.approx(100.0)
    fr = disk["frequency_response"]
    assert fr["freqs_hz"] == [10.0, 100.0, 200.0, 300.0, 400.0]
    for c in ("RA", "PC"):
        assert set(fr[c]["anova"]) >= {"frequency", "source", "interaction"}
        assert fr[c]["n_obs"]["TouchReal"] == 5 * 4
    assert set(disk["spatial"]) == set(CLASSES)
    for c in CLASSES:  # per-class latency beside the fidelity (algorithmic only: latency_trials=0)
        lat = disk["latency"][c]
        assert lat["window_ms"] == (16.0 if c in ("SA1", "RA") else 128.0) and lat["delay_ms"] >= 0.0  # the fast path
        assert (lat["algorithmic_ms"] < 20.0) == (c != "PC")
        assert lat["bound_emission_minus_stamp_ms"] == pytest.approx(lat["algorithmic_ms"] - lat["delay_ms"])
        assert "measured_spikes" not in lat
    assert len(disk["window_sweep"]["vr"]["PC"]) == 2
    per_cond = {}
    for e in tiny.entries("ramp"):
        per_cond[e["condition"]] = per_cond.get(e["condition"], 0) + 1
    for c in CLASSES:  # turning-point windows partition each ramp trial: the spikes add up to the whole-trial counts
        ramp_rows = [r for r in disk["mapping_per_condition"][c] if r["protocol"] == "ramp"]
        tp_rows = disk["turning_points"][c]
        assert sum(r["n_trials"] for r in tp_rows if r["event"] == "onset") == sum(per_cond.values())
        for key in ("tr", "ts"):
            total = sum(r[f"n_{key}"] * per_cond[r["condition"]] for r in ramp_rows)
            assert sum(r[f"{key}_spikes"] * r["n_trials"] for r in tp_rows) == pytest.approx(total)
    assert "turning points" in (out / "report.md").read_text()
    assert set(disk["missing_spike_bound"]) == set(M.BOUND_CLASSES)
    for c in M.BOUND_CLASSES:  # the missing-spike bound: one row per jitter; filling can only add spikes
        fitted = disk["missing_spike_bound"][c]["as_fitted"]
        assert fitted["ratio_inter_intra"] == pytest.approx(disk["mapping"][c]["all"]["ratio_inter_intra"])
        assert fitted["count_error"] == pytest.approx(disk["mapping"][c]["all"]["count_error_mean"])
        for b in disk["missing_spike_bound"][c].values():
            rows = b["filled"]
            assert [r["jitter_ms"] for r in rows] == list(M.BOUND_JITTERS_MS)
            assert len({r["added_per_ramp_trial"] for r in rows}) == 1 and rows[0]["added_per_ramp_trial"] >= 0
            assert len({r["count_error"] for r in rows}) == 1  # jitter moves spikes, not counts
    assert "Missing-spike bound" in (out / "report.md").read_text()
    assert {"vr_ratio_SA1", "count_error_PC", "RA_band_pass_peak_100Hz", "PC_rising", "anova_source_RA"} <= set(disk["targets"])
    md = (out / "report.md").read_text()
    assert "simulated rig recordings" in md and "intra" in md and "Table 2" in md
    for f in EXPECTED_FILES - {"report.md", "metrics.json"}:
        assert f"({f})" in md


def test_mapping_metrics_against_direct_vr_computation(tiny):
    params = default_params()
    entries = [e for e in tiny.entries("sine") if e["params"]["freq_hz"] == 100.0]
    trials = T.run_trials(tiny, entries, params, ["PC"])
    m = M.mapping_metrics(trials, trials, ["PC"], 0.001)
    row = m["PC"]["rows"][0]
    from touchreal.analysis.spiketrains import vr_distance

    ts = [t for tr in trials for t in tr.ts["PC"]]
    tr = [t.tr["PC"] for t in trials]
    d_tstr = np.mean([vr_distance(a, b, 0.001) for a in tr for b in ts])
    d_tsts = np.mean([vr_distance(ts[i], ts[j], 0.001) for i in range(len(ts)) for j in range(i + 1, len(ts))])
    assert row["ts_tr"] == pytest.approx(d_tstr, rel=1e-9)
    assert row["ts_ts"] == pytest.approx(d_tsts, rel=1e-9)
    assert row["n_ts"] == pytest.approx(np.mean([t.size for t in ts]))


def test_held_out_selection_follows_the_fit_provenance(tiny):
    entries = [e for e in tiny.entries() if e["protocol"] in ("ramp", "sine")]
    p = default_params()
    held, all_e, note = T.select_held_out(tiny, p)
    assert len(held) == len(all_e) == len(entries) and "not fitted" in note
    prov = dict(p.provenance, fitted_by="touchreal fit", split_method=splits.SPLIT_METHOD, dataset="rig-v1-tiny", split_seed=7)
    fitted = p.model_copy(update={"provenance": prov})
    held, _, note = T.select_held_out(tiny, fitted)
    _, expected = splits.split_repeats(entries, 7)
    assert [e["id"] for e in held] == [e["id"] for e in expected]
    assert "seed 7" in note
    held_all, _, _ = T.select_held_out(tiny, fitted, "all")
    assert len(held_all) == len(entries)
    train, _, note = T.select_held_out(tiny, fitted, "train")
    assert {e["id"] for e in train} == {e["id"] for e in entries} - {e["id"] for e in expected} and "TRAINING" in note
    with pytest.raises(ValueError, match="split train needs"):
        T.select_held_out(tiny, p, "train")


@pytest.mark.slow
def test_cli_evaluate(tiny, tmp_path):
    from touchreal.cli import main

    out = tmp_path / "cli"
    assert main(["evaluate", str(tiny.root), "--out", str(out), "--no-sweep", "--no-spatial", "--quiet", "--latency-trials", "0"]) == 0
    assert (out / "report.md").is_file() and (out / "metrics.json").is_file()
    assert main(["evaluate", str(tiny.root), "--out", str(out), "--ramp-condition", "nope", "--quiet", "--no-sweep", "--no-spatial"]) == 2


@pytest.mark.slow  # ~20 s: a report, the population variants and one 4 x 4 patch; .ci/run runs it (pytest -m slow)
def test_evaluate_adds_the_population_section_beside_the_report(tiny, tmp_path):
    from touchreal.cli import main

    out = tmp_path / "report"
    assert main(["evaluate", str(tiny.root), "--out", str(out), "--no-sweep", "--no-spatial", "--latency-trials", "0",
                 "--population", "3", "--quiet"]) == 0
    assert "[population/report.md](population/report.md)" in (out / "report.md").read_text()
    pop = json.loads((out / "population" / "metrics.json").read_text())
    assert set(pop["pitches"]["3"]["classes"]) == set(CLASSES)
    assert {len(g) for g in pop["plan"]["variants"].values()} == {4, 9}  # matched per TouchSim model
    assert all((out / "population" / f).stat().st_size > 10_000 for f in pop["figures"]["3"])
