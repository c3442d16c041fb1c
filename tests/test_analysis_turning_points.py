"""Turning-point table of ramp responses: windows, counts, offsets (synthetic trains, no data needed)."""

from __future__ import annotations

import numpy as np
import pytest

from touchreal.analysis import turning_points as tp
from touchreal.analysis.trials import EvalTrial


def ramp_entry(v_up: float, v_down: float, hold_s: float, depth_mm: float = 1.0, onset_s: float = 0.3) -> dict:
    hold_start = onset_s + depth_mm / v_up
    release = hold_start + hold_s
    return {
        "protocol": "ramp",
        "params": {"v_up_mm_s": v_up, "v_down_mm_s": v_down, "hold_s": hold_s, "depth_mm": depth_mm},
        "onset_s": onset_s,
        "events": {"hold_start_s": hold_start, "release_start_s": release},
        "stim_end_s": release + depth_mm / v_down,
    }


def test_turning_points_with_and_without_hold():
    e = ramp_entry(40.0, 8.0, 0.6)
    names = [n for n, _, _ in tp.turning_points(e)]
    assert names == ["onset", "hold", "release", "end"]
    t = [t for _, t, _ in tp.turning_points(e)]
    assert t == pytest.approx([0.0, 0.025, 0.625, 0.75])
    assert [s for _, _, s in tp.turning_points(e)] == [40.0, 40.0, 8.0, 8.0]
    e0 = ramp_entry(95.0, 65.0, 0.0)
    assert [n for n, _, _ in tp.turning_points(e0)] == ["onset", "peak", "end"]


def test_split_assigns_each_spike_to_the_nearest_turning_point():
    times = [0.0, 0.1, 1.0]
    spikes = np.array([-0.5, 0.01, 0.049, 0.051, 0.2, 0.549, 0.551, 3.0])
    parts = tp.split_at_turning_points(spikes, times)
    assert [p.tolist() for p in parts] == [[-0.5, 0.01, 0.049], [0.051, 0.2, 0.549], [0.551, 3.0]]
    assert sum(p.size for p in parts) == spikes.size


def test_table_counts_errors_and_offsets():
    e = ramp_entry(40.0, 40.0, 1.0)  # turning points at 0, 25, 1025, 1050 ms
    ts = [np.array([0.0002, 0.0262, 1.0252, 1.0512]), np.array([0.0004, 1.0254])]  # hold/end missing in one train
    tr = np.array([-0.001, 0.003, 0.024, 0.030, 1.040])  # 2 at onset, 2 at hold, 0 at release, 1 at end
    table = tp.turning_point_table([EvalTrial(e, 0.3, {"PC": tr}, {"PC": ts})], ["PC"])
    rows = {r["event"]: r for r in table["PC"]}
    assert [r["event"] for r in table["PC"]] == ["onset", "hold", "release", "end"]
    assert rows["onset"]["ts_spikes"] == 1.0 and rows["onset"]["tr_spikes"] == 2.0 and rows["onset"]["count_error"] == 1.0
    assert rows["hold"]["ts_spikes"] == 0.5 and rows["hold"]["count_error"] == 1.5
    assert rows["release"]["tr_spikes"] == 0.0 and rows["release"]["offset_ms_quartiles"] is None
    # end: TR 1040 ms against the only TouchSim first spike at 1051.2 ms
    assert rows["end"]["offset_ms_quartiles"][1] == pytest.approx(-11.2)
    assert rows["onset"]["offset_ms_quartiles"][1] == pytest.approx(-1.3)  # -1 ms against the median 0.3 ms
    assert rows["onset"]["ts_latency_ms"] == pytest.approx(0.3) and rows["hold"]["tr_latency_ms"] == pytest.approx(-1.0)
    # every spike is counted exactly once
    assert sum(r["tr_spikes"] for r in table["PC"]) == tr.size


def test_rows_group_by_speed_and_skip_non_ramp_or_unreferenced_trials():
    a = EvalTrial(ramp_entry(8.0, 95.0, 0.0), 0.3, {"RA": np.array([0.0])}, {"RA": [np.array([0.001])]})
    b = EvalTrial(ramp_entry(95.0, 95.0, 0.0), 0.3, {"RA": np.array([0.0, 0.02])}, {"RA": [np.array([0.0])]})
    sine = EvalTrial({"protocol": "sine"}, 0.3, {"RA": np.array([0.1])}, {"RA": [np.array([0.1])]})
    bare = EvalTrial(ramp_entry(8.0, 8.0, 0.0), 0.3, {"RA": np.array([0.1])})
    rows = tp.turning_point_table([a, b, sine, bare], ["RA"])["RA"]
    assert [(r["event"], r["speed_mm_s"], r["n_trials"]) for r in rows] == [
        ("onset", 8.0, 1), ("onset", 95.0, 1), ("peak", 8.0, 1), ("peak", 95.0, 1), ("end", 95.0, 2)
    ]
    assert rows[0]["tr_spikes"] == 1.0 and rows[1]["tr_spikes"] == 1.0  # b's second spike (20 ms) is nearer its end (21 ms)


def test_fill_missing_spikes_adds_touchsims_median_kth_spike_where_touchreal_has_fewer():
    times = [0.0, 0.1, 1.0]
    ts = [  # window 0: mean 1.75 -> 2 spikes; window 1: 1 spike; window 2: mean 0.75 -> 1 spike
        np.array([0.002, 0.010, 0.101, 1.005]),
        np.array([0.003, 0.102, 1.006]),
        np.array([0.001, 0.012, 0.103, 1.007]),
        np.array([0.002, 0.011, 0.104]),
    ]
    mine = np.array([0.0025, 0.09, 0.11])  # one spike short in window 0, one extra in window 1, none in window 2
    out = tp.fill_missing_spikes(mine, ts, times)
    # second spike of window 0 at the median of TouchSim's second spikes; window 2's at the median of
    # the three first spikes; window 1 (more spikes than TouchSim) untouched
    assert out.tolist() == pytest.approx([0.0025, 0.011, 0.09, 0.11, 1.006])
    assert tp.fill_missing_spikes(out, ts, times).tolist() == out.tolist()  # nothing left to add
    assert tp.fill_missing_spikes(np.zeros(0), [np.zeros(0)] * 3, times).size == 0


def test_fill_missing_spikes_jitter_is_gaussian_with_the_given_sd_and_keeps_existing_spikes():
    rng = np.random.default_rng(1)
    times = list(np.arange(400) * 0.5)
    ts = [np.asarray(times) + 0.004] * 4  # one TouchSim spike 4 ms after every turning point
    mine = np.asarray(times[::2]) + 0.004  # TouchReal has every other one
    out = tp.fill_missing_spikes(mine, ts, times, jitter_s=0.002, rng=rng)
    assert out.size == len(times) and np.isin(mine, out).all()
    added = np.setdiff1d(out, mine)
    dev = added - (np.asarray(times[1::2]) + 0.004)
    assert abs(dev.mean()) < 0.0005 and dev.std() == pytest.approx(0.002, rel=0.15)


def _trial(cond: str, tr: np.ndarray, ts: list[np.ndarray]) -> EvalTrial:
    e = ramp_entry(40.0, 40.0, 0.5)
    e["condition"] = cond
    return EvalTrial(e, e["onset_s"], {"PC": tr}, {"PC": ts})


def test_missing_spike_bound_with_exact_times_removes_the_count_error_and_jitter_costs_vr():
    from touchreal.analysis.metrics import mapping_metrics, missing_spike_bound

    e = ramp_entry(40.0, 40.0, 0.5)
    tps = [t for _, t, _ in tp.turning_points(e)]
    rng = np.random.default_rng(0)
    trials = []
    for c in range(6):  # TouchSim: one spike 3 ms after each turning point (+-0.2 ms); TouchReal misses the last two
        ts = [np.asarray(tps) + 0.003 + rng.normal(0, 0.0002, len(tps)) for _ in range(4)]
        trials.append(_trial(f"c{c}", np.asarray(tps[:2]) + 0.003, ts))
    fitted = mapping_metrics(trials, trials, ["PC"], 0.001)["PC"]["summary"]["all"]
    assert fitted["count_error_mean"] == pytest.approx(0.5)
    bound = missing_spike_bound(trials, ["PC"], 0.001, (0.0, 2.0))["PC"]
    assert bound["as_fitted"]["ratio_inter_intra"] == pytest.approx(fitted["ratio_inter_intra"])
    rows = bound["as_fitted"]["filled"]
    assert [r["jitter_ms"] for r in rows] == [0.0, 2.0]
    assert all(r["added_per_ramp_trial"] == 2.0 and r["count_error"] == pytest.approx(0.0) for r in rows)
    assert rows[0]["ratio_inter_intra"] < fitted["ratio_inter_intra"]  # exact spikes reduce the distance
    assert rows[1]["ratio_inter_intra"] > rows[0]["ratio_inter_intra"] + 0.1  # 2 ms jitter costs most of that back
    assert [t.tr["PC"].size for t in trials] == [2] * 6  # the trials themselves are not modified


def test_missing_spike_bound_unbiased_base_removes_each_turning_points_median_offset():
    from touchreal.analysis.metrics import missing_spike_bound

    e = ramp_entry(40.0, 40.0, 0.5)
    tps = np.asarray([t for _, t, _ in tp.turning_points(e)])
    rng = np.random.default_rng(2)
    late = [0.0, 0.004, -0.002, 0.006]  # TouchReal fires at every turning point, each with its own constant offset
    trials = []
    for c in range(3):
        ts = [tps + 0.003 + rng.normal(0, 0.0003, tps.size) for _ in range(4)]
        trials.append(_trial(f"c{c}", np.median(ts, axis=0) + np.asarray(late), ts))
    bound = missing_spike_bound(trials, ["PC"], 0.001, (0.0,))["PC"]
    assert bound["as_fitted"]["ratio_inter_intra"] > 1.5
    assert bound["unbiased"]["ratio_inter_intra"] < 1.0  # back on TouchSim's median spikes
    assert bound["unbiased"]["filled"][0]["added_per_ramp_trial"] == 0.0


def test_shift_windows_moves_each_windows_spikes_by_its_own_shift():
    times = [0.0, 0.1, 1.0]
    spikes = np.array([0.01, 0.049, 0.2, 0.9])
    out = tp.shift_windows(spikes, times, [0.001, -0.002, 0.5])
    assert out.tolist() == pytest.approx([0.011, 0.05, 0.198, 1.4])
    assert tp.shift_windows(np.zeros(0), times, [1.0, 1.0, 1.0]).size == 0
