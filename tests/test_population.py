"""Afferent populations: layout, spatial rule, the population encoder in the stream, variants, validation."""

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import shipped_notch_gain

from touchreal.analysis.population import FAST_HZ
from touchreal.params import default_params
from touchreal.population.encoder import Population
from touchreal.population.layout import FINGERTIP_DENSITY_PER_CM2, Layout, PopulationPlan, covered, place
from touchreal.population.spatial import cell_kernels
from touchreal.raw import RawChunk
from touchreal.reference.constants import load_constants
from touchreal.settings import CLASSES
from touchreal.simulator.patch import grid_patch, patch_skin, probe_recording
from touchreal.simulator.stimuli import RampHold, SineBurst
from touchreal.stream import StreamEncoder, encode_chunks

N_MODELS = {"SA1": 4, "RA": 9, "PC": 4}


def test_layout_is_reproducible_at_the_plan_densities_and_on_the_taxels_cells():
    taxels = grid_patch(4, 5.0)  # 20 x 20 mm: 4 cm^2
    a = place(taxels, PopulationPlan(seed=7), N_MODELS)
    b = place(taxels, PopulationPlan(seed=7), N_MODELS)
    c = place(taxels, PopulationPlan(seed=8), N_MODELS)
    assert np.array_equal(a.xy_mm, b.xy_mm) and np.array_equal(a.model, b.model)
    assert not np.array_equal(a.xy_mm[:10], c.xy_mm[:10])
    for k, cls in enumerate(CLASSES):
        assert (a.cls == k).sum() == round(FINGERTIP_DENSITY_PER_CM2[cls] * 4.0)
        assert a.model[a.cls == k].max() < N_MODELS[cls]
    assert covered(a.xy_mm, taxels, 5.0).all()
    first = a.describe()[0]
    assert set(first) == {"id", "class", "x_mm", "y_mm", "model"} and first["id"] == 0


def test_plan_rejects_bad_fields_and_round_trips():
    with pytest.raises(ValueError, match="unknown classes"):
        PopulationPlan(density_per_cm2={"Merkel": 10.0})
    with pytest.raises(ValueError, match="unknown population plan fields"):
        PopulationPlan.from_dict({"densities": {}})
    with pytest.raises(ValueError, match="variants"):
        PopulationPlan(variants={"SA1": [0.0]})
    plan = PopulationPlan(seed=3, variants={"SA1": [1.0, 2.0]}).resolved(grid_patch(2, 3.0))
    assert plan.cell_mm == pytest.approx(3.0)
    assert PopulationPlan.from_dict(json.loads(plan.to_json())) == plan


def test_spatial_rule_follows_receptor_depth_and_interpolates_the_films():
    off = np.array([[0.0, 0.0], [2.5, 0.0], [1.5, 1.5]])
    depth = dict(zip(CLASSES, load_constants().depth_mm))
    st_sa1, dy = cell_kernels(off, depth["SA1"], 3.0, 0.5)
    st_ra, _ = cell_kernels(off, depth["RA"], 3.0, 0.5)
    assert st_sa1[0] == pytest.approx(1.0) and st_ra[0] == pytest.approx(1.0)
    assert st_sa1[1] < st_ra[1]  # a deeper receptor sees the load of a cell it is not on more
    # bilinear weights: 1 on the centre, 1/4 on the corner shared by four cells
    assert dy[0] == 1.0 and dy[2] == pytest.approx(0.25)
    pop = Population.build(grid_patch(4, 3.0), PopulationPlan())
    inside = np.all(np.abs(pop.layout.xy_mm) <= 4.5, axis=1)  # within the grid of taxel centres
    films = np.asarray(pop.rule.films.sum(axis=1)).ravel()
    ra = pop.layout.cls == CLASSES.index("RA")  # RA's films come from the contacts (surface_wave)
    assert np.allclose(films[inside & ~ra], 1.0) and not films[ra].any()


def _loads(taxels, probe_xy, radius_mm=2.5):
    """ST channels of a probe at ``probe_xy`` over sensors that feel it within ``radius_mm`` (linear
    falloff), on a 0.04 N baseline; the films carry 1 V at every taxel."""
    d = np.hypot(*(taxels - np.asarray(probe_xy)).T)
    x = np.zeros((1, len(taxels), 4))
    x[0, :, 0] = 0.04 + 2.0 * np.clip(1.0 - d / radius_mm, 0.0, 1.0) + 0.001 * np.arange(len(taxels)) / len(taxels)
    x[0, :, 2] = 1.0
    return x


def test_loads_are_localised_on_the_edge_or_corner_they_share_and_films_decay_as_the_surface_wave():
    from touchreal.population.spatial import wave_weight

    taxels = grid_patch(4, 3.0)  # centres at -4.5, -1.5, 1.5, 4.5
    pop = Population.build(taxels, PopulationPlan())
    for probe in [(1.5, 1.5), (1.5, 0.0), (0.0, 0.0)]:
        pos, contact = pop.rule.localise(_loads(taxels, probe))
        j = int(np.argmax(_loads(taxels, probe)[0, :, 0]))
        assert np.allclose(pos[0, j], probe, atol=0.05), (probe, pos[0, j])
        assert contact[0, j] and contact.sum() == 1  # one contact: the largest load of its neighbourhood
    # an RA afferent's film input falls off as TouchSim's surface wave from where the films localise the vibration
    lay = Layout(np.full(3, CLASSES.index("RA")), np.array([[1.5, 1.5], [1.5, 2.5], [1.5, 4.0]]), np.zeros(3, np.int64))
    pop = Population.with_layout(taxels, PopulationPlan(), lay)
    x = _loads(taxels, (1.5, 1.5))
    x[0, :, 2] = np.exp(-np.hypot(*(taxels - 1.5).T) / 6.8)  # a film reads a vibration less the farther it is
    out = pop.rule.mix(x, pop.rule.rows(np.arange(3)))
    assert np.allclose(out[0, :, 2], wave_weight(np.array([0.0, 1.0, 2.5]), 0.5), rtol=0.01)  # a far contact adds a little


def _one_taxel_recording(stim=None, seed=1):
    return probe_recording(stim or RampHold(1.0, 20.0, 20.0, 0.3), (0.0, 0.0), np.zeros((1, 2)), skin=patch_skin(8.0), seed=seed)


def test_one_afferent_per_class_on_a_taxel_is_the_taxel_encoder_bit_for_bit():
    params = default_params()
    rec = _one_taxel_recording(SineBurst.calibrated(90.0, burst_s=0.3))
    taxel = encode_chunks(params, [rec.raw], 1)
    lay = Layout(np.arange(3, dtype=np.int64), np.zeros((3, 2)), np.zeros(3, np.int64))
    pop = Population.with_layout(np.zeros((1, 2)), PopulationPlan(), lay)
    ev = encode_chunks(params, [rec.raw], 1, population=pop)
    assert len(taxel) > 20
    for k, cls in enumerate(CLASSES):
        assert np.array_equal(ev.train(cls, k), taxel.train(cls, 0)), cls


def _chunks(raw: RawChunk, step_s: float):
    t = np.arange(0.0, raw.pvdf_t[-1] + step_s, step_s)
    for a, b in zip(t, t[1:]):
        yield RawChunk(raw.st_t[(raw.st_t >= a) & (raw.st_t < b)], raw.st[(raw.st_t >= a) & (raw.st_t < b)],
                       raw.pvdf_t[(raw.pvdf_t >= a) & (raw.pvdf_t < b)], raw.pvdf[(raw.pvdf_t >= a) & (raw.pvdf_t < b)])


@pytest.fixture(scope="module")
def patch():
    taxels = grid_patch(2, 3.0)
    pop = Population.build(taxels, PopulationPlan(variants={"SA1": [0.7, 1.3], "RA": [0.8, 1.0, 1.2], "PC": [1.0, 1.5]}))
    rec = probe_recording(RampHold(1.0, 20.0, 20.0, 0.3), (0.8, 0.4), taxels, skin=patch_skin(3.0), seed=2)
    return pop, rec


def test_population_spikes_do_not_depend_on_chunking_or_on_which_afferents_run(patch):
    pop, rec = patch
    params = default_params()
    whole = encode_chunks(params, [rec.raw], 4, population=pop)
    chunked = encode_chunks(params, _chunks(rec.raw, 0.013), 4, population=pop, update_s=0.032)
    assert len(whole) > 50
    order = lambda e: np.lexsort((e.taxel, e.t_s))  # noqa: E731
    assert np.array_equal(whole.t_s[order(whole)], chunked.t_s[order(chunked)])
    assert np.array_equal(whole.taxel[order(whole)], chunked.taxel[order(chunked)])
    # demand per afferent: a subset runs alone and gives the same trains
    some = {c: pop.layout.ids(c)[::3] for c in CLASSES}
    se = StreamEncoder(params, 4, population=pop)
    se.set_active(some)
    part = se.process(rec.raw)
    part = type(part).concatenate([part, se.finish()])
    assert set(np.unique(part.taxel)) <= set(np.concatenate(list(some.values())))
    for c in CLASSES:
        for a in some[c]:
            assert np.array_equal(part.t_s[part.taxel == a], whole.t_s[whole.taxel == a])
    assert sum(len(x) for x in se.active.values()) == sum(len(x) for x in some.values())
    with pytest.raises(ValueError, match="afferents"):
        se.set_active({"SA1": [len(pop)]})


def test_a_population_stream_refuses_blocks_and_a_skin_it_was_not_built_for(patch):
    pop, _ = patch
    with pytest.raises(ValueError, match="one taxel block"):
        StreamEncoder(default_params(), 4, population=pop, taxel_block=2)
    with pytest.raises(ValueError, match="built on 4 taxels"):
        StreamEncoder(default_params(), 9, population=pop)


def test_variants_follow_touchsim_models_relative_sensitivity():
    """`population plan` matches one gain per TouchSim model; the gains rank the models as TouchSim's
    own spike counts on the standard probe set do."""
    from scipy.stats import spearmanr

    from touchreal.fitting.variants import standard_set
    from touchreal.reference.model import ReferenceModel

    out = subprocess.run([sys.executable, "-m", "touchreal", "population", "plan", "--set", "seed=5"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    plan = PopulationPlan.from_dict(json.loads(out.stdout))
    assert plan.seed == 5 and {c: len(g) for c, g in plan.variants.items()} == N_MODELS
    ref = ReferenceModel()
    counts = np.zeros(ref.n_models)
    for i, stim in enumerate(standard_set(patch_skin(8.0).__class__())):
        rec = _one_taxel_recording(stim, seed=i)
        counts += ref.simulate(rec.cmd_depth, afferent_xy_mm=np.zeros((1, 2)), noisy=False).counts()[0, 0]
    for k, cls in enumerate(CLASSES):
        n = counts[ref.constants.class_of_model == k]
        assert spearmanr(plan.variants[cls], n).statistic > 0.7, (cls, plan.variants[cls], n)


def test_validation_writes_metrics_report_and_figures(tmp_path):
    from touchreal.analysis.population_report import evaluate_population

    plan = PopulationPlan(variants={c: [1.0] * n for c, n in N_MODELS.items()})
    doc = evaluate_population(default_params(), plan, tmp_path, pitches_mm=(3.0,), side=2)
    m = doc["pitches"]["3"]["classes"]
    assert set(m) == set(CLASSES)
    for cls in CLASSES:
        assert np.isfinite([m[cls]["map_r"], m[cls]["count_error"]]).all()
        assert m[cls]["spikes"] > 0 and m[cls]["spikes_touchsim"] > 0
    # TouchSim's own extents: the deep, vibration-driven PC responds over a wider area than SA1
    assert m["PC"]["extent_touchsim_mm2"] > m["SA1"]["extent_touchsim_mm2"]
    # RA's films reach the afferents from where the vibration is, not over the whole patch (36 mm^2),
    # and the ramp's SA1 area exceeds RA's as TouchSim's does
    assert m["RA"]["extent_mm2"] < 2.0 * m["RA"]["extent_touchsim_mm2"]
    assert m["RA"]["extent_touchsim_mm2"] < m["SA1"]["extent_touchsim_mm2"] and m["RA"]["extent_mm2"] < m["SA1"]["extent_mm2"]
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["pitches"]["3"]["classes"]["SA1"]["spikes"] == m["SA1"]["spikes"]
    for name in doc["figures"]["3"]:
        assert (tmp_path / name).stat().st_size > 10_000
    assert "| 3 | RA |" in (tmp_path / "report.md").read_text()
    assert set(m["RA"]["extents"]) == {"ramp 1 mm", "sine 40 Hz", "sine 165 Hz"}  # per stimulus at the centre
    assert "| 3 | SA1 | " in (tmp_path / "report.md").read_text().split("Area (mm^2)")[1]


@pytest.mark.parametrize("mains_hz", [50.0, 60.0])
def test_the_validations_fast_vibration_passes_the_shipped_mains_notches(mains_hz):
    # a burst on a notched mains harmonic would measure the notch, not the population (150 Hz, the
    # third harmonic of 50 Hz, reaches the gate at under a tenth of its amplitude)
    assert shipped_notch_gain(mains_hz, FAST_HZ) > 0.95
    if mains_hz == 50.0:
        assert shipped_notch_gain(mains_hz, 150.0) < 0.1
