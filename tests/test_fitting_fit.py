"""Fitting: split, search space, the fast simulation vs the product encoder, a synthetic fit that
must lower the loss substantially, and a tiny end-to-end fit on rig-v1 trials."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from touchreal.analysis.turning_points import turning_points
from touchreal.cli import main
from touchreal.encoding.encoder import encode_population
from touchreal.fitting import fit as F
from touchreal.fitting import search as S
from touchreal.fitting.command import parse_restarts
from touchreal.fitting.config import FitConfig
from touchreal.fitting.executor import FitState, LocalExecutor
from touchreal.fitting.split import split_repeats
from touchreal.fitting.trials import TrialData, TrialSet, build_trial_set, simulate
from touchreal.fitting.objective import evaluate_loss
from touchreal.fitting.space import INITIAL_WEIGHTS, N_DIM, ParamSpace
from touchreal.params import ClassParams, EncoderParams, PreprocessParams
from touchreal.recording import write_dataset
from touchreal.settings import CLASSES


def tiny_rig_subset(rig, root, sine_repeats: int = 4):
    """A small dataset folder (outside the repo) with a few rig-v1 trials of every evaluated protocol."""
    keep = []
    ramp_conds = ["ramp_d1.0_vu40_vd95_h1.8", "ramp_d1.6_vu95_vd8_h0.6"]
    for e in rig.trials:
        p = e["protocol"]
        if p == "ramp" and e["condition"] in ramp_conds:
            keep.append(e)
        elif p == "sine" and e["repeat"] < sine_repeats:
            keep.append(e)
        elif p == "spatial_ramp" and e["params"]["depth_mm"] == 0.7 and e["offset_r_mm"] <= 4 and e["repeat"] == 0:
            keep.append(e)
        elif p == "spatial_sine" and e["params"]["freq_hz"] == 265 and e["offset_r_mm"] <= 4 and e["repeat"] == 0:
            keep.append(e)
    manifest = {k: v for k, v in rig.manifest.items() if k != "trials"}
    manifest["name"] = "rig-v1-tiny"
    manifest["trials"] = [dict(e) for e in keep]
    return write_dataset(root, manifest, {e["id"]: rig.load(e) for e in keep})


# ----------------------------------------------------------------------------------- split


def test_split_by_repeat_is_disjoint_balanced_and_seeded():
    entries = [{"id": f"c{c}_r{r}", "condition": f"c{c}", "repeat": r} for c in range(30) for r in range(4)]
    entries += [{"id": "solo", "condition": "solo", "repeat": 0}]
    tr, te = split_repeats(entries, seed=3)
    ids_tr, ids_te = {e["id"] for e in tr}, {e["id"] for e in te}
    assert not ids_tr & ids_te and len(ids_tr | ids_te) == len(entries)
    for c in range(30):
        assert sum(e["condition"] == f"c{c}" for e in tr) == 2
    assert "solo" in ids_tr  # one-trial conditions only train
    assert split_repeats(entries, seed=3) == (tr, te)
    assert {e["id"] for e in split_repeats(entries, seed=4)[0]} != ids_tr


# ----------------------------------------------------------------------------------- space


@pytest.mark.parametrize("input_stage", [False, True])
@pytest.mark.parametrize("cls", CLASSES)
def test_space_round_trip_and_bounds(cls, input_stage):
    space = ParamSpace.for_class(cls, [8.0, 60.0, 0.2, 200.0], input_stage=input_stage)
    rng = np.random.default_rng(0)
    lo, hi = space.bounds()
    assert lo.shape == hi.shape == (N_DIM + 2 * input_stage,) and np.all(lo < hi)
    for v in range(2):
        x0 = space.initial(60.0, v)
        assert np.all((x0 >= lo) & (x0 <= hi))
        p = space.decode(x0)
        assert p.delay_ms == pytest.approx(60.0)
        if input_stage:  # TouchSim's class median cutoff (10 x column 0), no lead
            assert 80.0 < p.lowpass_hz < 350.0 and p.negative_lead_ms == 0.0
        else:
            assert p.lowpass_hz is None and p.negative_lead_ms == 0.0
    for _ in range(20):
        x = rng.uniform(lo, hi)
        p = space.decode(x)  # always a valid ClassParams
        np.testing.assert_allclose(space.encode(p), x, rtol=1e-9, atol=1e-9)
    extreme = space.decode(hi + 100)
    assert extreme.tau_ms <= 2000 and extreme.delay_ms <= 500
    assert space.decode(lo - 100).delay_ms == 0.0  # physiological delays only: the rig's lag is the alignment


def test_space_without_pvdf_holds_the_pvdf_weights_at_zero():
    space = ParamSpace.for_class("SA1", [8.0, 60.0, 0.2, 200.0], pvdf=False)
    assert space.fixed() == {4: 0.0, 5: 0.0, 6: 0.0, 7: 0.0}
    x = np.random.default_rng(1).uniform(*space.bounds())
    assert space.decode(x).weights[4:] == [0.0] * 4 and space.decode(x).weights[0] != 0.0
    es = S.make_cma(space, space.initial(0.0, 1), 6, 2, 1)  # CMA-ES does not search them
    assert np.all(np.asarray(es.ask())[:, 4:8] == 0.0)


def test_a_class_highpass_is_held_at_its_cutoff_not_searched():
    space = ParamSpace.for_class("PC", [8.0, 60.0, 0.2, 200.0], input_stage=True, highpass_hz=5.0)
    plain = ParamSpace.for_class("PC", [8.0, 60.0, 0.2, 200.0], input_stage=True)
    assert space.n_dim == plain.n_dim and np.array_equal(space.bounds()[0], plain.bounds()[0])
    for x in np.random.default_rng(3).uniform(*space.bounds(), (10, space.n_dim)):
        p, q = space.decode(x), plain.decode(x)
        assert p.highpass_hz == 5.0 and q.highpass_hz is None and p.model_copy(update={"highpass_hz": None}) == q
        np.testing.assert_allclose(space.encode(p), x, rtol=1e-9, atol=1e-9)


def test_an_excitatory_space_bounds_the_film_weights_below_at_zero():
    free = ParamSpace.for_class("RA", [8.0, 60.0, 0.2, 200.0], input_stage=True)
    space = ParamSpace.for_class("RA", [8.0, 60.0, 0.2, 200.0], input_stage=True, excitatory=True)
    (lo, hi), (lo0, hi0) = space.bounds(), free.bounds()
    assert list(lo[4:6]) == [0.0] * 2 and lo0[4] < 0 and np.array_equal(np.delete(lo, [4, 5]), np.delete(lo0, [4, 5]))
    assert np.array_equal(hi, hi0) and space.fixed() == {}
    x = np.random.default_rng(2).uniform(lo0, hi0, (50, space.n_dim))
    w = np.array([space.decode(v).weights for v in x])
    assert np.all(w[:, 4:6] >= 0.0) and np.any(w[:, 4:6] == 0.0) and np.any(w[:, [0, 1, 2, 3, 6, 7]] < 0.0)  # only w5, w6
    bounded, unbounded = (np.asarray(S.make_cma(sp, sp.initial(0.0, 1), 12, 2, 1).ask()) for sp in (space, free))
    assert np.all(bounded[:, 4:6] >= 0.0) and np.any(unbounded[:, 4:6] < 0.0)  # CMA-ES samples inside the bound
    inhibitory = free.decode(np.r_[0.0, 0.0, 2.0, -1.0, 3.0, -2.0, -4.0, 0.0, x[0][8:]])  # e.g. an --init file's class
    assert list(space.clip(space.encode(inhibitory))[2:7]) == pytest.approx([2.0, -1.0, 3.0, 0.0, -4.0])  # its start is brought inside


# ------------------------------------------------------------------- fast simulation == encoder


def _synthetic_channels(seed, n=6000):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 5000.0
    force = 3.0 * np.clip((t - 0.2) / 0.1, 0, 1) * (1 - np.clip((t - 0.8) / 0.1, 0, 1))
    dforce = np.gradient(force, t)
    pv = 0.002 * dforce + 0.05 * np.sin(2 * np.pi * 150 * t) * ((t > 0.4) & (t < 0.6)) + rng.normal(0, 0.003, n)
    dpv = np.gradient(pv, t)
    return np.ascontiguousarray(np.stack([force, dforce, pv, dpv], axis=1))


def _trial(i, channels, onset, refs, k0=50):
    return TrialData(f"t{i}", f"c{i // 2}", "ramp", onset, k0, channels, {"SA1": refs}, {"SA1": 1})


def test_batched_candidates_equal_one_at_a_time():
    params = [
        ClassParams(weights=[0.003, 0, 4e-4, -1e-4, 0.05, 0.05, 1e-5, 1e-5], i_sat=0.0, tau_ms=30, ih=[-0.2, 0], delay_ms=20),
        ClassParams(weights=[0, 0, 0.004, 0.004, 0.3, 0.3, 1e-4, 1e-4], i_sat=0.5, tau_ms=4, ih=[-1.8, -0.07], delay_ms=5),
        ClassParams(weights=[0, 0, 0, 0, 2.0, 2.0, 1e-3, 1e-3], i_sat=20.0, tau_ms=1.2, ih=[-6, -0.5], delay_ms=0),
    ]
    trials = [_trial(i, _synthetic_channels(i), 0.1 * i, []) for i in range(3)]
    batched = simulate(trials, params, lag_s=0.065)  # on the reference clock: stamps minus the rig's lag
    n_spikes = 0
    for j, p in enumerate(params):
        for a, tr in zip(batched[j], trials):
            alone = encode_population(tr.channels, tr.k0 / 5000.0, [p])[0] - 0.065 - tr.onset_s
            np.testing.assert_array_equal(a, alone)
            n_spikes += a.size
    assert n_spikes > 50  # the comparison is not vacuous


# ----------------------------------------------------------------------- synthetic recovery


def test_synthetic_fit_recovers_the_generating_parameters():
    """References from a known SA1-like parameter set, as TouchSim would give them: four 'models'
    (gain x 0.85 .. 1.15) with jittered repeats. CMA-ES from the generic start (delay off by 15 ms,
    wrong gain and tau) must lower the loss substantially and land near the generating parameters."""
    rng = np.random.default_rng(5)
    scale = np.array([3.0, 30.0, 0.06, 40.0])
    space = ParamSpace.for_class("SA1", scale)
    x_true = space.initial(25.0)
    x_true[:8] = [1.6, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0]
    x_true[8] = -0.3
    true = space.decode(x_true)
    models = [space.decode(space.with_gain(x_true, g)) for g in (0.85, 0.95, 1.05, 1.15)]
    trials = []
    for i in range(8):
        ch = _synthetic_channels(10 + i) * np.array([1.0 + 0.2 * i, 1.0 + 0.1 * i, 1.0, 1.0])
        onset = 0.15 + 0.01 * i
        refs = []
        for _ in range(3):  # repeats
            for m in models:
                base = encode_population(ch, 50 / 5000.0, [m])[0] - onset
                refs.append(np.sort(base + rng.normal(0, 0.002, base.size)))
        trials.append(TrialData(f"t{i}", f"c{i}", "ramp", onset, 50, ch, {"SA1": refs}, {"SA1": 4}))
    tset = TrialSet(trials, [f"c{i}" for i in range(8)], np.arange(8))
    cfg = FitConfig(classes=("SA1",), popsize=8, max_generations=40, workers=1, progress=False)
    refs = tset.reference_set("SA1", cfg.objective.kernel_tau_s, 80)
    ev = LocalExecutor(FitState(spaces={"SA1": space}, refs={"SA1": refs}, train={"SA1": tset}, objectives={"SA1": cfg.objective_of("SA1")}, lag_s=0.0), 1)

    def loss(x):
        return ev("SA1", np.array([x]))[0][0]

    l_true = loss(x_true)
    x_start = space.initial(10.0)
    x_start[:8] = [0.5, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0]
    l_start = loss(x_start)
    fit = S.fit_class("SA1", space, ev, cfg, [x_start], 0.0)
    for run in fit.runs:
        assert run.history == sorted(run.history, reverse=True)  # best-so-far never increases
    l_fit = loss(fit.x)
    assert l_fit < 0.4 * l_start
    assert l_fit < l_true + 0.15
    # the run from the generic start lands near the generating delay
    assert space.decode(fit.runs[0].best_x).delay_ms == pytest.approx(true.delay_ms, abs=6.0)
    assert l_fit <= min(r.best_loss for r in fit.runs) + 1e-12
    # identifiable behaviour: spike counts per condition match the references' (tau and the
    # weights trade off against each other, so they are not compared one by one)
    terms = evaluate_loss(simulate(trials, [fit.params])[0], tset.cond_index, refs, cfg.objective)
    assert np.mean(np.abs(terms.n_s - terms.n_t) / terms.n_t) < 0.15


# ------------------------------------------------------------------------ rig-v1, end to end


@pytest.mark.shared
def test_tiny_fit_on_rig_trials_and_cli(rig, tmp_path):
    ds = tiny_rig_subset(rig, tmp_path / "tiny")
    cfg = FitConfig(popsize=6, max_generations=2, workers=2, progress=False, seed=1)
    res = F.fit_dataset(ds.root, cfg)
    p = res.params
    assert set(p.classes) == set(CLASSES)
    assert p.preprocess.gate is not None  # calibrated from the baselines
    prov = p.provenance
    assert prov["dataset"] == "rig-v1-tiny" and prov["split_seed"] == 1
    assert 0.004 < prov["st_noise_n"] < prov["noisy_st_noise_n"] == 0.0065 and not prov["noisy_singletact"]  # rig-v1's: 5 mN
    assert prov["optimizer"]["restarts"] == {"SA1": 0, "RA": 0, "PC": 0}  # a quiet SingleTact: no restart
    assert prov["optimizer"]["saturated_classes"] == []  # nor a saturated start
    assert res.n_train > 0 and res.n_validation > 0
    for c, f in res.classes.items():
        assert f.train is not None and f.validation is not None and np.isfinite(f.validation.total)
        # search: start grid (directions x 81) + 2 generations of 6 per run (on a noisy SingleTact SA1 also
        # restarts, 1 generation of 12, and runs from its saturated grid); RA and PC (the default) are then
        # refined from the search's best point: a grid of 81 around it + 2 generations of 6
        search = f.search if c in ("RA", "PC") else f
        assert (f.search is not None) == (c in ("RA", "PC"))
        saturated = len(S.SATURATED_STARTS.get(c, ())) if c in prov["optimizer"]["saturated_classes"] else 0
        plan = [(6, 2)] + [(12, 1)] * prov["optimizer"]["restarts"][c] + [(6, 2)] * saturated
        grid = len(INITIAL_WEIGHTS[c]) * 81 * (1 + saturated)
        assert [(r.popsize, r.budget) for r in search.runs] == plan
        assert grid < search.evaluations <= grid + sum(p * g for p, g in plan) and search.generations <= sum(g for _, g in plan)
        if f.search is not None:
            assert 81 < f.evaluations <= 81 + 2 * 6 and f.generations <= 2
        # the input stage is fitted for RA and PC only (FitConfig default); no input high-pass off a film-limited build
        assert (f.params.lowpass_hz is not None) == (c in ("RA", "PC"))
        assert f.params.highpass_hz is None
    # reproducible
    res2 = F.fit_dataset(ds.root, FitConfig(popsize=6, max_generations=2, workers=1, progress=False, seed=1))
    for c in CLASSES:
        assert res2.params.classes[c] == p.classes[c]
    # the CLI writes a loadable file; --classes keeps the others from --init
    out = tmp_path / "p.json"
    p.save(tmp_path / "init.json")
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "RA", "--generations", "1", "--popsize", "4",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1"]) == 0
    q = EncoderParams.load(out)
    for c in ("SA1", "PC"):  # kept: the same class, re-expressed on the new alignment (same reference-clock spikes)
        assert q.classes[c].model_copy(update={"delay_ms": 0.0}) == p.classes[c].model_copy(update={"delay_ms": 0.0})
        assert q.classes[c].delay_ms - q.alignment.lag_ms == pytest.approx(p.classes[c].delay_ms - p.alignment.lag_ms, abs=1e-9)
    assert min(cp.delay_ms for cp in q.classes.values()) == 0.0  # the smallest alignment with every delay >= 0
    assert json.loads(out.read_text())["provenance"]["fitted_classes"] == ["RA"]
    assert q.window_ms("RA") == 16.0 and q.window_ms("PC") == 128.0  # the default: the shipped windows (fast path)
    objective = json.loads(out.read_text())["provenance"]["objective"]
    assert objective["count_weight"] == 1.0 and objective["refine"] == {"RA": 3.0}  # the defaults: the paper's search, then RA refined
    assert objective["vr_distance_classes"] == []  # RA's refinement keeps the kernel distance
    assert objective["excitatory_classes"] == ["RA"] and min(q.classes["RA"].weights[4:6]) >= 0.0  # pressing and releasing both excite RA
    assert objective["refine_sine_count_weights"] == {}  # on this build every count term weighs the sines as its distance
    prov = json.loads(out.read_text())["provenance"]
    assert prov["contact_snr"] > prov["weak_signal_snr"] == 50.0 and not prov["weak_signal"]  # rig-v1's film stands well out of its noise
    assert prov["gate_factor"] == 3.0 == q.preprocess.gate.factor  # so the gate keeps its factor
    # a build below --weak-signal-snr gets the weak-signal gate and PC sine count weight; given options win
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "PC", "--generations", "1", "--popsize", "4",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1", "--count-weight", "3",
                 "--weak-signal-snr", "1e6"]) == 0
    prov = json.loads(out.read_text())["provenance"]
    objective = prov["objective"]
    assert objective["count_weight"] == 3.0 and objective["refine"] == {"PC": 5.0} and objective["refine_sine_count_weights"] == {"PC": 10.0}
    assert prov["optimizer"]["restarts"] == {"PC": 0}  # only SA1 restarts, and only on a noisy SingleTact
    assert EncoderParams.load(out).preprocess.gate.factor == 2.0 == prov["gate_factor"] and prov["weak_signal_snr"] == 1e6 and prov["weak_signal"]
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "PC", "--generations", "1", "--popsize", "4",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1", "--weak-signal-snr", "1e6",
                 "--gate-factor", "2.5", "--refine-sine-count-weights", "none"]) == 0
    prov = json.loads(out.read_text())["provenance"]
    assert prov["gate_factor"] == 2.5 and prov["objective"]["refine_sine_count_weights"] == {}
    assert prov["objective"]["highpass_hz"] == {} and not prov["film_limited"] and EncoderParams.load(out).classes["PC"].highpass_hz is None
    # a build below --film-limited-snr gets PC's input high-pass, its count margin and a plain count; given options win
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "PC", "--generations", "1", "--popsize", "4",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1", "--film-limited-snr", "1e6"]) == 0
    prov = json.loads(out.read_text())["provenance"]
    assert prov["film_limited"] and prov["film_limited_snr"] == 1e6 and prov["weak_signal"] is False and prov["gate_factor"] == 3.0
    assert prov["objective"]["highpass_hz"] == {"PC": 5.0} and EncoderParams.load(out).classes["PC"].highpass_hz == 5.0
    assert prov["objective"]["refine_count_margins"] == {"PC": 0.22} and prov["objective"]["refine_sine_count_weights"] == {"PC": 1.0}
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "PC", "--generations", "1", "--popsize", "4",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1", "--film-limited-snr", "1e6",
                 "--highpass", "none", "--refine-count-margins", "PC=0.1"]) == 0
    prov = json.loads(out.read_text())["provenance"]
    assert prov["objective"]["highpass_hz"] == {} and prov["objective"]["refine_count_margins"] == {"PC": 0.1}
    assert EncoderParams.load(out).classes["PC"].highpass_hz is None  # the paper's input: no high-pass
    assert objective["segmented_count_classes"] == ["PC"] and objective["vr_distance_classes"] == ["PC"]  # the defaults
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "RA,PC", "--generations", "1", "--popsize", "4",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1", "--refine", "none",
                 "--segmented-count-classes", "none"]) == 0
    prov = json.loads(out.read_text())["provenance"]
    assert prov["objective"]["refine"] == {} and prov["objective"]["segmented_count_classes"] == []  # the paper's objective
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "RA", "--generations", "1", "--popsize", "4",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1", "--excitatory-classes", "none"]) == 0
    assert json.loads(out.read_text())["provenance"]["objective"]["excitatory_classes"] == []  # the paper's unconstrained weights
    assert "search" not in prov["loss"]["PC"]
    # the file records every CMA-ES run of a class (a restart: population x2, generations /2)
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "PC", "--generations", "2", "--popsize", "4", "--restarts", "1",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1"]) == 0
    prov = json.loads(out.read_text())["provenance"]
    for stage in (prov["loss"]["PC"], prov["loss"]["PC"]["search"]):  # the refinement, and the search it started from
        assert [(r["popsize"], r["generations"], r["stop"]) for r in stage["runs"]] == [(4, 2, "budget"), (8, 1, "budget")]
        assert stage["generations"] == 3
    assert prov["optimizer"]["restarts"] == {"PC": 1}
    # a SingleTact above --noisy-st-noise gets SA1's noisy-SingleTact search: its saturated start and a restart
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "SA1", "--generations", "2", "--popsize", "4",
                 "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1", "--noisy-st-noise", "1e-4"]) == 0
    prov = json.loads(out.read_text())["provenance"]
    assert prov["noisy_singletact"] is True and prov["noisy_st_noise_n"] == 1e-4
    assert prov["optimizer"]["restarts"] == {"SA1": 1} and prov["optimizer"]["saturated_classes"] == ["SA1"]
    assert [(r["popsize"], r["generations"]) for r in prov["loss"]["SA1"]["runs"]] == [(4, 2), (8, 1), (4, 2)]
    assert parse_restarts("2") == {"SA1": 2, "RA": 2, "PC": 2}  # every class
    assert parse_restarts("PC=2") == {"PC": 2}  # the named ones; the others none
    assert parse_restarts("1,PC=2") == {"SA1": 1, "RA": 1, "PC": 2}  # a bare number: the classes not named
    for bad in ("1.5", "-1", "9", "SA2=1"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_restarts(bad)
    assert FitConfig(restarts=2).restarts == {"SA1": 2, "RA": 2, "PC": 2} and FitConfig().restarts is None
    noisy, quiet = FitConfig().for_singletact(0.012), FitConfig().for_singletact(0.005)  # 3x and 1x the nominal noise
    assert noisy.restarts_of("SA1") == 1 and noisy.restarts_of("RA:refine") == 0 and quiet.restarts == {}
    assert FitConfig().for_singletact(None).restarts == {}  # not measured: none
    assert FitConfig(restarts={"RA": 1}).for_singletact(0.012).restarts_of("RA:refine") == 1  # given: kept
    assert FitConfig(noisy_st_noise_n=0.02).for_singletact(0.012).restarts == {}
    assert noisy.saturated("SA1") and not noisy.saturated("SA1:refine") and not quiet.saturated("SA1")
    assert FitConfig(saturated_classes=()).for_singletact(0.012).saturated_classes == ()  # given: kept
    with pytest.raises(ValueError, match="noisy_st_noise_n"):
        FitConfig(noisy_st_noise_n=float("nan"))
    with pytest.raises(ValueError, match="restarts must be integers"):
        FitConfig(restarts={"PC": 1.5})
    with pytest.raises(ValueError):
        FitConfig(count_weight=-1.0)
    with pytest.raises(ValueError, match="weights of refine"):
        FitConfig(refine={"PC": float("nan")})
    with pytest.raises(ValueError, match="refine must be a subset"):
        FitConfig(refine={"SA2": 1.0})
    with pytest.raises(ValueError, match="refine_sine_count_weights must be >= 0"):
        FitConfig(refine_sine_count_weights={"PC": float("inf")})
    with pytest.raises(ValueError, match="refine_sine_count_weights must be a subset"):
        FitConfig(refine_sine_count_weights={"SA2": 1.0})
    with pytest.raises(ValueError, match="gate_factor"):
        FitConfig(gate_factor=0.0)
    with pytest.raises(ValueError, match="weak_signal_snr"):
        FitConfig(weak_signal_snr=float("nan"))
    cfg = FitConfig(count_weight=2.0)
    assert cfg.objective_of("PC").count_weight == 2.0 and cfg.objective_of("PC:refine").count_weight == 5.0
    assert cfg.refined() == ("RA", "PC") and FitConfig(classes=("SA1", "PC")).refined() == ("PC",)
    with pytest.raises(ValueError, match="segmented_count_classes"):
        FitConfig(segmented_count_classes=("PC", "SA2"))
    assert main(["fit", str(ds.root), "--out", str(out), "--classes", "XX"]) == 2


@pytest.mark.shared
def test_ramp_count_segments_are_the_turning_point_windows(rig, tmp_path):
    ds = tiny_rig_subset(rig, tmp_path / "tiny")
    entries = [e for e in ds.entries() if e["protocol"] in ("ramp", "sine")]
    tset = build_trial_set(ds, entries, PreprocessParams(), ["PC"])
    for e, t in zip(entries, tset.trials):
        if e["protocol"] == "ramp":
            tps = [x for _, x, _ in turning_points(e)]
            assert len(tps) in (3, 4)
            np.testing.assert_allclose(t.window_edges_s, [(a + b) / 2 for a, b in zip(tps[:-1], tps[1:])])
        else:
            assert t.window_edges_s.size == 0
    whole = tset.reference_set("PC", 0.01, 80)
    seg = tset.reference_set("PC", 0.01, 80, segmented_count=True)
    assert whole.n_t_seg.size == whole.n_conditions
    n_seg = np.diff(seg.edge_off) + 1
    assert set(n_seg.tolist()) <= {1, 3, 4} and (n_seg > 1).any()
    # the segments of a condition add up to its whole-trial reference count
    np.testing.assert_allclose(np.bincount(np.repeat(np.arange(seg.n_conditions), n_seg), seg.n_t_seg), whole.n_t)
    # the fit's reference sets: the search's (segmented, sine weight in distance and count) and PC's
    # refinement's (whole trials, VR-normalised; a sine may weigh less in its count than in its distance)
    cfg = FitConfig(sine_weight=30.0)
    sine = np.zeros(len(tset.conditions), dtype=bool)
    sine[tset.cond_index] = [t.protocol == "sine" for t in tset.trials]
    assert sine.any() and (~sine).any()
    search, refine = F._references(tset, "PC", cfg), F._references(tset, "PC:refine", cfg)
    np.testing.assert_array_equal(search.weights, np.where(sine, 30.0, 1.0))
    assert search.count_weights is None and search.vr_norm is None and search.edges.size > 0
    np.testing.assert_array_equal(refine.weights, search.weights)
    assert refine.count_weights is None  # by default the count terms weigh as the distance
    assert refine.vr_norm is not None and refine.edges.size == 0
    custom = F._references(tset, "PC:refine", FitConfig(sine_weight=30.0, refine_sine_count_weights={"PC": 10.0}))
    np.testing.assert_array_equal(custom.count_weights, np.where(sine, 10.0, 1.0))
    np.testing.assert_array_equal(custom.weights, search.weights)
    assert F._references(tset, "PC", FitConfig(refine_sine_count_weights={"PC": 10.0})).count_weights is None  # the search's stay


@pytest.mark.shared
def test_fit_per_class_windows_without_holdout_and_its_evaluation(rig, tmp_path):
    """Each class fitted on its own window's channels; every trial trains; the file records the
    rig's lag as its alignment (delays >= 0), and `evaluate --split auto` knows nothing was held out."""
    from touchreal.analysis.report import EvalConfig, evaluate
    from touchreal.analysis.trials import run_trials

    ds = tiny_rig_subset(rig, tmp_path / "tiny", sine_repeats=1)
    cfg = FitConfig(classes=("SA1", "RA"), class_window_ms={"SA1": 16.0, "RA": 32.0}, holdout=False, popsize=4,
                      max_generations=1, restarts=0, workers=1, progress=False, input_stage_classes=(), no_pvdf_classes=("SA1",))
    res = F.fit_dataset(ds.root, cfg)
    p = res.params
    n = len([e for e in ds.entries() if e["protocol"] in ("ramp", "sine")])
    assert res.n_train == n and res.n_validation == 0
    assert p.provenance["n_validation_trials"] == 0 and p.provenance["class_window_ms"] == {"SA1": 16.0, "RA": 32.0}
    assert p.window_ms("SA1") == 16.0 and p.window_ms("RA") == 32.0 and p.preprocess.window_ms == 128.0
    assert p.classes["SA1"].weights[4:] == [0.0] * 4  # SingleTact only
    assert 40.0 < p.provenance["rig_lag_ms"] < 120.0 and p.alignment.dataset == "rig-v1-tiny"
    assert all(c.delay_ms >= 0 for c in p.classes.values()) and min(c.delay_ms for c in p.classes.values()) == 0.0
    # the fit's own loss is the loss of the product encoder at each class's window, on the reference clock
    entries = [e for e in ds.entries() if e["protocol"] in ("ramp", "sine")]
    trials = run_trials(ds, entries, p, ["SA1", "RA"])
    for cls in ("SA1", "RA"):
        tset = build_trial_set(ds, entries, p.preprocess.model_copy(update={"window_ms": p.window_ms(cls)}), [cls])
        fast = simulate(tset.trials, [p.classes[cls]], p.alignment.lag_ms / 1000.0)[0]
        for a, t in zip(fast, trials):
            np.testing.assert_allclose(a, t.tr[cls], atol=1e-9)
    # ... and of the online stream (every class on its own source; SA1 on the SingleTact alone)
    from touchreal.stream import StreamEncoder, encode_trial

    assert StreamEncoder(p).latency_s["SA1"] < StreamEncoder(p).latency_s["RA"]
    for e, t in list(zip(entries, trials))[:2]:
        stream = encode_trial(ds.load(e), p)
        for cls in ("SA1", "RA"):
            np.testing.assert_allclose(p.reference_times(stream[cls]) - t.onset, t.tr[cls], atol=1e-9)
    m = evaluate(ds.root, p, tmp_path / "rep", EvalConfig(with_sweep=False, with_spatial=False, latency_trials=1, bound_jitters_ms=()))
    assert m["n_held_out"] == n and "TRAINED on every one" in m["evaluated_on"]
    lat = m["latency"]
    assert lat["SA1"]["window_ms"] == 16.0 and lat["RA"]["window_ms"] == 32.0
    assert lat["SA1"]["algorithmic_ms"] < lat["RA"]["algorithmic_ms"]
    assert lat["SA1"]["measured_spikes"] > 0
    for c in ("SA1", "RA"):  # measured: never later than the bound (+ one 1 ms chunk), never before the causing sample
        r = lat[c]
        if r["measured_spikes"]:
            assert r["measured_median_ms"] <= r["bound_emission_minus_stamp_ms"] + 1.0 and r["measured_median_after_sample_ms"] > 0
    assert "Per-class latency" in (tmp_path / "rep" / "report.md").read_text()


def test_window_option_per_class():
    import argparse

    from touchreal.fitting.command import parse_class_weights, parse_highpass, parse_windows

    assert parse_windows("64") == (64.0, {})
    assert parse_windows("SA1=16,RA=16,PC=128") == (128.0, {"SA1": 16.0, "RA": 16.0, "PC": 128.0})
    assert parse_windows("32, SA1=16") == (32.0, {"SA1": 16.0})
    assert parse_class_weights("PC=4,RA=2") == {"PC": 4.0, "RA": 2.0} and parse_class_weights("none") == {}
    for bad in ("SA2=16", "SA1=fast", "x"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_windows(bad)
        with pytest.raises(argparse.ArgumentTypeError):
            parse_class_weights(bad)
    with pytest.raises(argparse.ArgumentTypeError, match="a weight per class"):
        parse_class_weights("3")
    with pytest.raises(ValueError, match="window_ms"):
        FitConfig(class_window_ms={"RA": 2.0})
    assert parse_highpass("PC=5,RA=0.5") == {"PC": 5.0, "RA": 0.5} and parse_highpass("none") == {}
    for bad in ("PC=0", "PC=500", "3", "PC=x", "SA9=5"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_highpass(bad)
    with pytest.raises(ValueError, match="highpass_hz cutoffs"):
        FitConfig(highpass_hz={"PC": 0.01})
    with pytest.raises(ValueError, match="highpass_hz must be a subset"):
        FitConfig(highpass_hz={"SA9": 5.0})
    with pytest.raises(ValueError, match="refine_count_margins must be in"):
        FitConfig(refine_count_margins={"PC": 1.0})
    with pytest.raises(ValueError, match="film_limited_snr"):
        FitConfig(film_limited_snr=-1.0)
    assert FitConfig(window_ms=64.0, class_window_ms={"SA1": 16.0}).window_of("RA") == 64.0


@pytest.mark.parametrize("name", ["input_stage_classes", "no_pvdf_classes", "excitatory_classes", "segmented_count_classes", "vr_distance_classes"])
def test_fit_config_refuses_unknown_classes_in_every_class_list(name):
    with pytest.raises(ValueError, match=f"{name} must be a subset"):
        FitConfig(**{name: ("PC", "SA9")})
    assert getattr(FitConfig(**{name: ("PC",)}), name) == ("PC",)


def test_the_weak_signal_settings_apply_below_the_snr_threshold_where_not_given():
    cfg = FitConfig()
    assert not cfg.weak_signal(None) and not cfg.weak_signal(50.0) and cfg.weak_signal(49.9)
    strong, weak = cfg.for_snr(107.0), cfg.for_snr(37.0)  # nominal and noisy-amplifier builds (docs/fitting.md)
    assert (strong.gate_factor, strong.refine_sine_count_weights) == (3.0, {})
    assert (weak.gate_factor, weak.refine_sine_count_weights) == (2.0, {"PC": 10.0})
    assert cfg.for_snr(None) == strong and cfg.refine_sine_count_weights is None  # not measured: no change; cfg itself kept
    given = FitConfig(gate_factor=2.5, refine_sine_count_weights={"RA": 5.0}).for_snr(37.0)
    assert (given.gate_factor, given.refine_sine_count_weights) == (2.5, {"RA": 5.0})
    never = FitConfig(weak_signal_snr=0.0, film_limited_snr=0.0).for_snr(1e-3)  # 0: no build is weak (nor film-limited)
    assert (never.gate_factor, never.refine_sine_count_weights) == (3.0, {})
    assert weak.objective_of("PC:refine") == cfg.objective_of("PC:refine")  # the rest is the same
    assert (weak.highpass_hz, weak.refine_count_margins) == ({}, {})  # not film-limited


def test_the_film_limited_settings_apply_below_their_snr_where_not_given():
    cfg = FitConfig()
    assert cfg.film_limited(34.9) and not cfg.film_limited(35.0) and not cfg.film_limited(None)
    film = cfg.for_snr(19.0)  # the corner build (docs/fitting.md)
    assert (film.gate_factor, film.refine_sine_count_weights) == (2.0, {"PC": 1.0})  # a weak-signal gate, a plain count
    assert (film.highpass_hz, film.refine_count_margins) == ({"PC": 5.0}, {"PC": 0.22})
    assert film.objective_of("PC:refine").count_margin == 0.22 and film.objective_of("PC").count_margin == 0.0  # the refinement's only
    assert film.objective_of("RA:refine").count_margin == 0.0
    given = FitConfig(highpass_hz={}, refine_count_margins={"PC": 0.1}, refine_sine_count_weights={"PC": 10.0}).for_snr(19.0)
    assert (given.highpass_hz, given.refine_count_margins, given.refine_sine_count_weights) == ({}, {"PC": 0.1}, {"PC": 10.0})
    never = FitConfig(film_limited_snr=0.0).for_snr(19.0)  # 0: no build is film-limited; it is still weak-signal
    assert (never.highpass_hz, never.refine_count_margins, never.refine_sine_count_weights) == ({}, {}, {"PC": 10.0})


def test_a_fit_on_the_corner_build_gives_pc_the_film_limited_settings(tmp_path, corner_build, capsys):
    assert main(["simulate", "ramp", "--trials", "ramp=16", "--seed", "3", "--build", str(corner_build), "--out", str(tmp_path / "ds"), "--quiet"]) == 0
    out = tmp_path / "pc.json"
    capsys.readouterr()
    assert main(["fit", str(tmp_path / "ds"), "--out", str(out), "--classes", "PC", "--generations", "1", "--popsize", "4",
                 "--quiet", "--workers", "1"]) == 0
    p = EncoderParams.load(out)
    prov = p.provenance
    assert prov["contact_snr"] < prov["film_limited_snr"] == 35.0 and prov["film_limited"] and prov["weak_signal"]
    assert p.classes["PC"].highpass_hz == 5.0 and p.version == 4  # the high-pass needs schema version 4
    assert prov["objective"]["refine_count_margins"] == {"PC": 0.22} and prov["objective"]["refine_sine_count_weights"] == {"PC": 1.0}
    said = capsys.readouterr().err
    assert "(film-limited), input high-pass {'PC': 5.0} Hz, refinement count margins {'PC': 0.22}" in said  # the log says so
