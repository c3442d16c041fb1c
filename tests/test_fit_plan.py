"""The fit's plan: resolved from a build's profile by one table of rules, overridden by a recipe,
and equal, for every build profile, to what the fit chose before it became a plan
(tests/data/fit_plan_old_resolution.json, written by running that code)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import pytest

from touchreal.fitting.config import FitConfig
from touchreal.fitting.describe import log_line, plan_text, policy_markdown
from touchreal.fitting.fit import references
from touchreal.fitting.plan import FitPlan, PlanError, leaves, stage_key
from touchreal.fitting.policy import MEASURED_WITH, RULES, Bound, Rule, checked, default_plan, resolve
from touchreal.fitting.profile import BuildProfile
from touchreal.fitting.search import Budget
from touchreal.settings import CLASSES

DATA = Path(__file__).parent / "data"
DOCS = Path(__file__).resolve().parents[1] / "docs" / "fitting.md"
OLD = json.loads((DATA / "fit_plan_old_resolution.json").read_text())


def old_options_as_recipe(options: dict, classes: tuple[str, ...]) -> dict:
    """The recipe that says what the fit's former options said (each given option replaced the
    build's choice for every class)."""
    shared = {"window_ms": "window_ms", "popsize": "popsize", "max_generations": "generations", "sine_weight": "sine_weight",
              "count_weight": "count_weight", "kernel_ms": "kernel_ms", "gate_factor": "gate_factor",
              "max_ramp_conditions": "max_ramp_conditions"}
    recipe: dict = {new: options[old] for old, new in shared.items() if old in options}
    per_class: dict = {c: {} for c in classes}
    refine: dict = {c: {} for c in classes}
    default_window = options.get("window_ms", 128.0)
    for c in classes:
        if "class_window_ms" in options:
            per_class[c]["window_ms"] = options["class_window_ms"].get(c, default_window)
        if "restarts" in options:
            r = options["restarts"]
            per_class[c]["restarts"] = r if isinstance(r, int) else r.get(c, 0)
        if "saturated_classes" in options:
            per_class[c]["saturated_starts"] = [-2.0] if c in options["saturated_classes"] else []
        if "highpass_hz" in options:
            per_class[c]["highpass_hz"] = options["highpass_hz"].get(c)
        for old, new in (("input_stage_classes", "input_stage"), ("excitatory_classes", "excitatory"),
                         ("segmented_count_classes", "segmented_count")):
            if old in options:
                per_class[c][new] = c in options[old]
        if "no_pvdf_classes" in options:
            per_class[c]["pvdf"] = c not in options["no_pvdf_classes"]
        if "refine_sine_count_weights" in options:
            refine[c]["sine_count_weight"] = options["refine_sine_count_weights"].get(c)
        if "refine_count_margins" in options:
            refine[c]["count_margin"] = options["refine_count_margins"].get(c, 0.0)
        if "vr_distance_classes" in options:
            refine[c]["vr_distance"] = c in options["vr_distance_classes"]
        if "refine" in options:
            refine[c]["count_weight"] = options["refine"].get(c)
    refined = {c for c in classes if (c in options["refine"] if "refine" in options else default_plan(classes).classes[c].refine)}
    for c in classes:
        if c in refined:
            per_class[c]["refine"] = refine[c]
        elif "refine" in options:
            per_class[c]["refine"] = None
    recipe["classes"] = {c: v for c, v in per_class.items() if v}
    return recipe


class _Recorder:
    """Stands in for a trial set: what the fit asks its reference set for."""

    def reference_set(self, cls, tau_s, max_refs, sine_weight=1.0, segmented_count=False, vr_normalised=False, sine_count_weight=None):
        return {"segmented_count": segmented_count, "vr_normalised": vr_normalised, "sine_weight": sine_weight,
                "sine_count_weight": sine_count_weight, "max_refs": max_refs}


def normalised(plan: FitPlan) -> dict:
    """A plan in the fixture's form: what the search, its spaces, references and objectives receive."""

    def stage(cls: str, refinement: bool) -> dict:
        key = stage_key(cls, refinement)
        budget = Budget.of(plan, key)
        return {"objective": {k: float(v) for k, v in asdict(plan.objective_of(key)).items()},
                "references": references(_Recorder(), key, plan),  # type: ignore[arg-type]
                "restarts": budget.restarts, "saturations": list(budget.saturated_starts)}

    return {
        "gate_factor": plan.gate_factor, "window_ms": plan.window_ms, "popsize": plan.popsize, "max_generations": plan.generations,
        "max_ramp_conditions": plan.max_ramp_conditions,
        "classes": {c: {"window_ms": cp.window_ms,
                        "space": {"input_stage": cp.input_stage, "pvdf": cp.pvdf, "excitatory": cp.excitatory, "highpass_hz": cp.highpass_hz},
                        "search": stage(c, False), "refine": stage(c, True) if cp.refine is not None else None}
                    for c, cp in plan.classes.items()},
    }


@pytest.mark.parametrize("case", OLD["cases"], ids=lambda c: c.get("build") or f"{c['profile']}-{sorted(c['options'])}")
def test_the_plan_is_what_the_fit_chose_before_it_became_a_plan(case):
    classes = tuple(case["options"].get("classes", CLASSES))
    profile = BuildProfile(**case["profile"])
    recipe = old_options_as_recipe({k: v for k, v in case["options"].items() if k != "classes"}, classes)
    assert normalised(resolve(profile, classes, recipe).plan) == case["resolved"]


def test_the_fixture_covers_both_sides_of_every_threshold_and_every_build():
    profiles = [BuildProfile(**c["profile"]) for c in OLD["cases"]]
    for rule in RULES:
        for bound in rule.when:
            below = [p for p in profiles if getattr(p, bound.measure) is not None and getattr(p, bound.measure) < bound.value]
            at = [p for p in profiles if getattr(p, bound.measure) == bound.value]
            above = [p for p in profiles if getattr(p, bound.measure) is not None and getattr(p, bound.measure) > bound.value]
            assert below and at and above, (rule.name, bound)
        assert any(rule.applies(p) for p in profiles) and not all(rule.applies(p) for p in profiles)
    assert {c.get("build") for c in OLD["cases"]} >= {"rig-v1", "nominal", "weak-film-60hz", "noisy-amplifier", "stiff-film-slow-rig",
                                                      "noisy-singletact", "weak-noisy-film"}


def test_every_rule_sets_fields_of_the_plan_and_no_two_rules_that_apply_together_set_the_same_field():
    fields = leaves(default_plan(CLASSES).model_dump())
    for rule in RULES:
        assert set(rule.sets) <= set(fields) and not set(rule.sets) & set(MEASURED_WITH) and rule.why
    weak, film = (Rule(n, w, {"gate_factor": 2.0}, "-") for n, w in (("a", (Bound("contact_snr", "<", 50.0),)),
                                                                       ("b", (Bound("contact_snr", "<", 35.0),))))
    with pytest.raises(ValueError, match="both set \\['gate_factor'\\] and can apply together"):
        checked([weak, film])  # nested conditions: one would silently beat the other
    noisy = Rule("c", (Bound("st_noise_n", ">", 0.0065),), {"gate_factor": 1.0}, "-")
    with pytest.raises(ValueError, match="can apply together"):
        checked([film, noisy])  # conditions on different measures may hold at once
    assert checked([Rule("d", (Bound("contact_snr", ">=", 35.0),), {"gate_factor": 2.0}, "-"), film])  # disjoint: fine
    with pytest.raises(ValueError, match="can apply together"):  # both hold at 35 itself
        checked([Rule("d", (Bound("contact_snr", ">=", 35.0),), {"gate_factor": 2.0}, "-"),
                 Rule("g", (Bound("contact_snr", "<=", 35.0),), {"gate_factor": 1.0}, "-")])
    with pytest.raises(ValueError, match="measured with"):
        checked([Rule("e", (Bound("contact_snr", "<", 1.0),), {"window_ms": 32.0}, "-")])
    with pytest.raises(ValueError, match="condition on the profile"):
        checked([Rule("f", (Bound("rig_lag_ms", "<", 1.0),), {"gate_factor": 2.0}, "-")])


def test_a_rule_applies_on_its_side_of_the_threshold_and_never_on_an_unmeasured_profile():
    by_name = {r.name: r for r in RULES}
    assert [r.name for r in resolve(BuildProfile(34.99, 0.0066), CLASSES).rules] == ["film-limited", "noisy-singletact"]
    assert [r.name for r in resolve(BuildProfile(35.0, 0.0065), CLASSES).rules] == ["weak-signal"]
    assert resolve(BuildProfile(), CLASSES).rules == () and resolve(BuildProfile(50.0, None), CLASSES).rules == ()
    assert by_name["weak-signal"].condition() == "35 <= contact SNR < 50"
    assert by_name["noisy-singletact"].condition() == "SingleTact noise > 6.5 mN"
    pc_only = resolve(BuildProfile(19.0, 0.012), ("PC",))  # SA1 not fitted: its rule's fields are skipped
    assert set(pc_only.plan.classes) == {"PC"} and "classes.SA1.restarts" not in pc_only.origins
    assert pc_only.origins["classes.PC.highpass_hz"] == "rule film-limited" and [r.name for r in pc_only.rules] == ["film-limited", "noisy-singletact"]


def test_a_recipe_overrides_any_field_and_refuses_what_the_plan_has_not():
    res = resolve(BuildProfile(19.0, 0.012), CLASSES, {"gate_factor": 2.5, "classes": {"PC": {"highpass_hz": None, "refine": {"count_margin": 0.1}},
                                                                                      "SA1": {"refine": {"count_weight": 2.0}}}})
    pc = res.plan.classes["PC"]
    assert res.plan.gate_factor == 2.5 and pc.highpass_hz is None and pc.refine.count_margin == 0.1
    assert pc.refine.sine_count_weight == 1.0 and pc.refine.vr_distance  # the rest as the rule and the defaults set it
    assert res.plan.classes["SA1"].refine.count_weight == 2.0 and res.plan.refined() == CLASSES
    assert res.origins["gate_factor"] == "recipe" and res.origins["classes.PC.refine.sine_count_weight"] == "rule film-limited"
    with pytest.raises(PlanError, match=r"classes\.PC\.refine\.count_margn: unknown field \(fields there: count_weight, sine_count_weight, "
                                        r"count_margin, vr_distance\)"):
        resolve(BuildProfile(), CLASSES, {"classes": {"PC": {"refine": {"count_margn": 0.1}}}})
    with pytest.raises(PlanError, match=r"gate: unknown field \(fields there: window_ms, max_ramp_conditions, gate_factor"):
        resolve(BuildProfile(), CLASSES, {"gate": 2.0})
    with pytest.raises(PlanError, match="classes.SA1: SA1 is not fitted"):
        resolve(BuildProfile(), ("PC",), {"classes": {"SA1": {"restarts": 1}}})
    with pytest.raises(PlanError, match="classes.SA9: unknown class"):
        resolve(BuildProfile(), CLASSES, {"classes": {"SA9": {}}})
    with pytest.raises(PlanError, match="classes.PC.restarts: Input should be less than or equal to 8"):
        resolve(BuildProfile(), CLASSES, {"classes": {"PC": {"restarts": 9}}})
    with pytest.raises(PlanError, match="classes.RA.excitatory: Input should be a valid boolean"):
        resolve(BuildProfile(), CLASSES, {"classes": {"RA": {"excitatory": "yes"}}})
    with pytest.raises(PlanError, match="classes.SA1.saturated_starts.0: Input should be less than or equal to 8"):
        resolve(BuildProfile(), CLASSES, {"classes": {"SA1": {"saturated_starts": [9.0]}}})
    with pytest.raises(PlanError, match="classes.PC.window_ms"):
        FitConfig(recipe={"classes": {"PC": {"window_ms": 2.0}}})  # refused before any data is read
    with pytest.raises(ValueError, match="classes must be"):
        FitConfig(classes=("PC", "SA9"))
    assert FitConfig(classes=("PC", "SA1")).classes == ("SA1", "PC")


def test_the_plan_prints_its_reasons_and_the_log_line_and_docs_are_generated_from_it():
    res = resolve(BuildProfile(19.0, 0.0119), CLASSES, {"popsize": 6})
    text = plan_text(res)
    assert "build profile: contact SNR 19.0, SingleTact noise 11.9 mN" in text
    assert "film-limited      contact SNR < 35           applies" in text and "weak-signal       35 <= contact SNR < 50     -" in text
    assert "rule film-limited (contact SNR < 35) sets gate_factor 2, PC.highpass_hz 5, PC.refine.count_margin 0.22" in text
    assert "the recipe sets popsize 6" in text
    line = log_line(res)
    assert "\n" not in line and line.startswith("build profile: contact SNR 19.0") and line.endswith("recipe: popsize 6")
    assert log_line(resolve(BuildProfile(105.0, 0.005), CLASSES)).endswith("rules: none; recipe: none")
    assert policy_markdown() in DOCS.read_text(), "docs/fitting.md's policy tables are not the generated ones: paste policy_markdown()"
