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
from touchreal.fitting.config import FitConfig
from touchreal.fitting.executor import FitState, LocalExecutor
from touchreal.fitting.objective import evaluate_loss
from touchreal.fitting.policy import default_plan
from touchreal.fitting.space import INITIAL_WEIGHTS, N_DIM, ParamSpace
from touchreal.fitting.trials import TrialData, TrialSet, build_trial_set, simulate
from touchreal.params import ClassParams, EncoderParams, PreprocessParams
from touchreal.recording import write_dataset
from touchreal.settings import CLASSES
from touchreal.splits import split_repeats


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
    plan = default_plan(("SA1",)).overridden({"popsize": 8, "generations": 40})
    objective = plan.objective_of("SA1")
    refs = tset.reference_set("SA1", objective.kernel_tau_s, 80)
    ev = LocalExecutor(FitState(plan=plan, spaces={"SA1": space}, refs={"SA1": refs}, train={"SA1": tset}, lag_s=0.0), 1)

    def loss(x):
        return ev("SA1", np.array([x]))[0][0]

    l_true = loss(x_true)
    x_start = space.initial(10.0)
    x_start[:8] = [0.5, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0]
    l_start = loss(x_start)
    fit = S.Searcher(space, ev, 0).stage("SA1", S.Budget.of(plan, "SA1"), [x_start], 0.0)
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
    terms = evaluate_loss(simulate(trials, [fit.params])[0], tset.cond_index, refs, objective)
    assert np.mean(np.abs(terms.n_s - terms.n_t) / terms.n_t) < 0.15


# ------------------------------------------------------------------------ rig-v1, end to end


def _recipe(tmp_path, name: str, recipe: dict) -> str:
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(recipe))
    return str(path)


@pytest.mark.shared
@pytest.mark.slow  # ~14 s: two small fits through the CLI; .ci/run runs it (pytest -m slow)
def test_tiny_fit_on_rig_trials_and_cli(rig, tmp_path, capsys):
    ds = tiny_rig_subset(rig, tmp_path / "tiny")
    cfg = FitConfig(recipe={"popsize": 6, "generations": 2}, workers=2, progress=False, seed=1)
    res = F.fit_dataset(ds.root, cfg)
    p = res.params
    assert set(p.classes) == set(CLASSES)
    assert p.preprocess.gate is not None  # calibrated from the baselines
    prov = p.provenance
    assert prov["dataset"] == "rig-v1-tiny" and prov["split_seed"] == 1
    assert 0.004 < prov["profile"]["st_noise_n"] < 0.0065 and prov["profile"]["contact_snr"] > 50  # rig-v1's: 5 mN, a strong film
    assert prov["rules"] == [] and prov["recipe"] == {"popsize": 6, "generations": 2}  # no rule applies: the defaults
    assert prov["plan"] == res.resolution.plan.model_dump(mode="json") and prov["plan"]["gate_factor"] == 3.0 == p.preprocess.gate.factor
    assert {c: (cp["restarts"], cp["saturated_starts"]) for c, cp in prov["plan"]["classes"].items()} == {c: (0, []) for c in CLASSES}
    assert res.n_train > 0 and res.n_validation > 0
    for c, f in res.classes.items():
        assert f.train is not None and f.validation is not None and np.isfinite(f.validation.total)
        # search: start grid (directions x 81) + 2 generations of 6; RA and PC (the default) are then
        # refined from the search's best point: a grid of 81 around it + 2 generations of 6
        search = f.search if c in ("RA", "PC") else f
        assert (f.search is not None) == (c in ("RA", "PC"))
        grid = len(INITIAL_WEIGHTS[c]) * 81
        assert [(r.popsize, r.budget) for r in search.runs] == [(6, 2)]
        assert grid < search.evaluations <= grid + 12 and search.generations <= 2
        if f.search is not None:
            assert 81 < f.evaluations <= 81 + 2 * 6 and f.generations <= 2
        # the input stage is fitted for RA and PC only (the default); no input high-pass off a film-limited build
        assert (f.params.lowpass_hz is not None) == (c in ("RA", "PC"))
        assert f.params.highpass_hz is None
    # reproducible
    res2 = F.fit_dataset(ds.root, FitConfig(recipe={"popsize": 6, "generations": 2}, workers=1, progress=False, seed=1))
    for c in CLASSES:
        assert res2.params.classes[c] == p.classes[c]
    # the CLI writes a loadable file; --classes keeps the others from --init
    out = tmp_path / "p.json"
    p.save(tmp_path / "init.json")
    short = _recipe(tmp_path, "short", {"generations": 1, "popsize": 4})
    fit = ["fit", str(ds.root), "--out", str(out), "--init", str(tmp_path / "init.json"), "--quiet", "--workers", "1"]
    assert main([*fit, "--classes", "RA", "--recipe", short]) == 0
    q = EncoderParams.load(out)
    for c in ("SA1", "PC"):  # kept: the same class, re-expressed on the new alignment (same reference-clock spikes)
        assert q.classes[c].model_copy(update={"delay_ms": 0.0}) == p.classes[c].model_copy(update={"delay_ms": 0.0})
        assert q.classes[c].delay_ms - q.alignment.lag_ms == pytest.approx(p.classes[c].delay_ms - p.alignment.lag_ms, abs=1e-9)
    assert min(cp.delay_ms for cp in q.classes.values()) == 0.0  # the smallest alignment with every delay >= 0
    prov = q.provenance
    assert prov["fitted_classes"] == ["RA"] and list(prov["plan"]["classes"]) == ["RA"]
    assert q.window_ms("RA") == 16.0 and q.window_ms("PC") == 128.0  # the default: the shipped windows (fast path)
    ra = prov["plan"]["classes"]["RA"]
    assert prov["plan"]["count_weight"] == 1.0 and ra["refine"] == {"count_weight": 3.0, "sine_count_weight": None, "count_margin": 0.0,
                                                                    "vr_distance": False}  # the paper's search, then RA refined on its distance
    assert ra["excitatory"] and min(q.classes["RA"].weights[4:6]) >= 0.0  # pressing and releasing both excite RA
    assert prov["init"]["fitted_classes"] == list(CLASSES) and prov["init"]["class_window_ms"] == {"SA1": 16.0, "RA": 16.0, "PC": 128.0}
    # a recipe overrides any field of the plan; the file records the plan it ran
    assert main([*fit, "--classes", "RA,PC", "--recipe", _recipe(tmp_path, "paper", {
        "generations": 1, "popsize": 4, "gate_factor": 2.5, "count_weight": 3.0,
        "classes": {"RA": {"refine": None, "excitatory": False}, "PC": {"refine": None, "segmented_count": False, "highpass_hz": 5.0}}})]) == 0
    q = EncoderParams.load(out)
    plan = q.provenance["plan"]
    assert q.preprocess.gate.factor == 2.5 == plan["gate_factor"] and plan["count_weight"] == 3.0 and q.provenance["rules"] == []
    assert plan["classes"]["PC"]["refine"] is None and not plan["classes"]["PC"]["segmented_count"] and "search" not in q.provenance["loss"]["PC"]
    assert q.classes["PC"].highpass_hz == 5.0 and plan["classes"]["PC"]["highpass_hz"] == 5.0
    assert not plan["classes"]["RA"]["excitatory"] and plan["classes"]["RA"]["refine"] is None
    # every CMA-ES run of a class is recorded (a restart: population x2, generations /2), as are a saturated start's
    assert main([*fit, "--classes", "SA1,PC", "--recipe", _recipe(tmp_path, "runs", {
        "generations": 2, "popsize": 4, "classes": {"PC": {"restarts": 1}, "SA1": {"restarts": 1, "saturated_starts": [-2.0]}}})]) == 0
    prov = json.loads(out.read_text())["provenance"]
    for stage in (prov["loss"]["PC"], prov["loss"]["PC"]["search"]):  # the refinement, and the search it started from
        assert [(r["popsize"], r["generations"], r["stop"]) for r in stage["runs"]] == [(4, 2, "budget"), (8, 1, "budget")]
        assert stage["generations"] == 3
    assert [(r["popsize"], r["generations"]) for r in prov["loss"]["SA1"]["runs"]] == [(4, 2), (8, 1), (4, 2)]  # the saturated run last
    # --plan prints the plan and writes nothing; a bad recipe or class is a clear error
    out.unlink()
    capsys.readouterr()
    assert main([*fit, "--plan", "--recipe", short]) == 0
    said = capsys.readouterr().out
    assert "build profile: contact SNR" in said and "the recipe sets generations 1, popsize 4" in said and not out.exists()
    assert main([*fit, "--recipe", _recipe(tmp_path, "bad", {"classes": {"PC": {"highpass": 5.0}}})]) == 2
    err = capsys.readouterr().err
    assert "the plan's overrides (--recipe" in err and "classes.PC.highpass: unknown field (fields there: window_ms, input_stage" in err
    assert main(["fit", str(ds.root), "--plan", "--classes", "XX"]) == 2
    assert main(["fit", str(ds.root)]) == 2 and "--out is required" in capsys.readouterr().err


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
    plan = default_plan(CLASSES)  # a sine weighs 30 ramp conditions
    sine = np.zeros(len(tset.conditions), dtype=bool)
    sine[tset.cond_index] = [t.protocol == "sine" for t in tset.trials]
    assert sine.any() and (~sine).any()
    search, refine = F.references(tset, "PC", plan), F.references(tset, "PC:refine", plan)
    np.testing.assert_array_equal(search.weights, np.where(sine, 30.0, 1.0))
    assert search.count_weights is None and search.vr_norm is None and search.edges.size > 0
    np.testing.assert_array_equal(refine.weights, search.weights)
    assert refine.count_weights is None  # by default the count terms weigh as the distance
    assert refine.vr_norm is not None and refine.edges.size == 0
    ten = plan.overridden({"classes": {"PC": {"refine": {"sine_count_weight": 10.0}}}})
    custom = F.references(tset, "PC:refine", ten)
    np.testing.assert_array_equal(custom.count_weights, np.where(sine, 10.0, 1.0))
    np.testing.assert_array_equal(custom.weights, search.weights)
    assert F.references(tset, "PC", ten).count_weights is None  # the search's stay


@pytest.mark.shared
def test_fit_per_class_windows_without_holdout_and_its_evaluation(rig, tmp_path):
    """Each class fitted on its own window's channels; every trial trains; the file records the
    rig's lag as its alignment (delays >= 0), and `evaluate --split auto` knows nothing was held out."""
    from touchreal.analysis.report import EvalConfig, evaluate
    from touchreal.analysis.trials import run_trials

    ds = tiny_rig_subset(rig, tmp_path / "tiny", sine_repeats=1)
    cfg = FitConfig(classes=("SA1", "RA"), holdout=False, workers=1, progress=False, recipe={
        "popsize": 4, "generations": 1, "classes": {"SA1": {"window_ms": 16.0, "pvdf": False}, "RA": {"window_ms": 32.0, "input_stage": False}}})
    res = F.fit_dataset(ds.root, cfg)
    p = res.params
    n = len([e for e in ds.entries() if e["protocol"] in ("ramp", "sine")])
    assert res.n_train == n and res.n_validation == 0
    assert p.provenance["n_validation_trials"] == 0 and [cp["window_ms"] for cp in p.provenance["plan"]["classes"].values()] == [16.0, 32.0]
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
    from touchreal.commands.fit import parse_windows, window_recipe

    assert parse_windows("64") == (64.0, {})
    assert parse_windows("SA1=16,RA=16,PC=128") == (128.0, {"SA1": 16.0, "RA": 16.0, "PC": 128.0})
    assert parse_windows("32, SA1=16") == (32.0, {"SA1": 16.0})
    assert parse_windows("SA1=32,RA=16") == (128.0, {"SA1": 32.0, "RA": 16.0})  # the others: 128
    for bad in ("SA2=16", "SA1=fast", "x"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_windows(bad)
    recipe = window_recipe(*parse_windows("32, SA1=16"), ("SA1", "PC"))
    assert recipe == {"window_ms": 32.0, "classes": {"SA1": {"window_ms": 16.0}, "PC": {"window_ms": 32.0}}}
    plan = FitConfig(classes=("SA1", "PC"), recipe=recipe)
    assert plan.recipe == recipe
    with pytest.raises(ValueError, match="classes.RA.window_ms"):
        FitConfig(recipe={"classes": {"RA": {"window_ms": 2.0}}})


def test_a_fit_on_the_corner_build_gives_pc_the_film_limited_settings(tmp_path, corner_build, capsys):
    assert main(["simulate", "ramp", "--trials", "ramp=16", "--seed", "3", "--build", str(corner_build), "--out", str(tmp_path / "ds"), "--quiet"]) == 0
    out = tmp_path / "pc.json"
    fit = ["fit", str(tmp_path / "ds"), "--out", str(out), "--classes", "PC", "--quiet", "--workers", "1"]
    capsys.readouterr()
    assert main([*fit, "--plan"]) == 0 and not out.exists()  # the plan first, without fitting
    said = capsys.readouterr().out
    assert "film-limited      contact SNR < 35           applies" in said and "noisy-singletact  SingleTact noise > 6.5 mN  applies" in said
    assert "rule film-limited (contact SNR < 35) sets gate_factor 2, PC.highpass_hz 5, PC.refine.count_margin 0.22, PC.refine.sine_count_weight 1: " in said
    assert "rule noisy-singletact (SingleTact noise > 6.5 mN) sets none of the fitted classes' fields" in said  # SA1's only
    assert main([*fit, "--recipe", _recipe(tmp_path, "short", {"generations": 1, "popsize": 4})]) == 0
    p = EncoderParams.load(out)
    prov = p.provenance
    assert prov["profile"]["contact_snr"] < 35.0 and prov["rules"] == ["film-limited", "noisy-singletact"]
    assert p.classes["PC"].highpass_hz == 5.0 and p.version == 4  # the high-pass needs schema version 4
    assert prov["plan"]["classes"]["PC"]["refine"] == {"count_weight": 5.0, "sine_count_weight": 1.0, "count_margin": 0.22, "vr_distance": True}
    assert prov["plan"]["gate_factor"] == 2.0 == p.preprocess.gate.factor
    said = capsys.readouterr().err  # the log says so, in one line
    assert "; rules: film-limited (contact SNR < 35: gate_factor 2, PC.highpass_hz 5, PC.refine.count_margin 0.22, " in said
