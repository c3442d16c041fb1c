"""The policy and a resolved plan as text, generated from :mod:`.policy`'s table and the plan's fields:
``touchreal fit --plan``, the fit's log line, the command's help and docs/fitting.md's policy tables."""

from __future__ import annotations

import json
from typing import Any

from ..settings import CLASSES
from .plan import ClassPlan, FitPlan, RefinePlan, leaves
from .policy import RULES, Resolution, Rule, default_plan
from .profile import MEASURES, shown

_CLASS_FIELDS = [f for f in ClassPlan.model_fields if f != "refine"] + ["refine"] + [f"refine.{f}" for f in RefinePlan.model_fields]


def value_text(v: Any) -> str:
    """A plan value as its recipe (JSON) would write it, numbers shortest: ``5``, ``0.22``, ``null``, ``[-2]``."""
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(value_text(x) for x in v) + "]"
    if isinstance(v, RefinePlan):  # its fields are shown one by one
        return "{…}"
    return json.dumps(v)


def short_path(path: str) -> str:
    """A plan field's path without the ``classes.`` prefix (``"PC.highpass_hz"``)."""
    return path.removeprefix("classes.")


def settings_text(values: dict[str, Any]) -> str:
    """``"gate_factor 2, PC.refine.sine_count_weight 10"`` for values by dotted path."""
    return ", ".join(f"{short_path(p)} {value_text(v)}" for p, v in values.items()) or "none"


def profile_text(res: Resolution) -> str:
    """``"contact SNR 105.3, SingleTact noise 5.0 mN"``."""
    return ", ".join(f"{label} {shown(m, getattr(res.profile, m))}" for m, (label, _, _) in MEASURES.items())


def log_line(res: Resolution) -> str:
    """One line for the fit's log: the profile, the rules that applied and what they set, the recipe."""
    rules = "; ".join(f"{r.name} ({r.condition()}: {settings_text(dict(r.sets))})" for r in res.rules) or "none"
    return f"build profile: {profile_text(res)}; rules: {rules}; recipe: {settings_text(leaves(res.recipe))}"


def plan_text(res: Resolution) -> str:
    """The resolved plan and its reasons (``touchreal fit --plan``): the profile, every rule and whether
    it applied, the plan's fields (shared, then per class; ``*`` where a rule or the recipe set it),
    then what set them and why."""
    plan = res.plan
    out = [f"build profile: {profile_text(res)}", "rules:"]
    width = max(len(r.name) for r in RULES)
    cond = max(len(r.condition()) for r in RULES)
    out += [f"  {r.name:<{width}}  {r.condition():<{cond}}  {'applies' if r in res.rules else '-'}" for r in RULES]
    out.append("plan (* set by a rule or the recipe; override any field with --recipe FILE.json):")
    shared = {k: v for k, v in plan.model_dump().items() if k != "classes"}
    out += [f"  {k:<28}{value_text(v)}{'*' if k in res.origins else ''}" for k, v in shared.items()]
    out.append((f"  {'classes.':<28}" + "".join(f"{c:<10}" for c in plan.classes)).rstrip())
    for f in _CLASS_FIELDS:
        cells = []
        for c, cp in plan.classes.items():
            path = f"classes.{c}.{f}"
            v = _class_value(cp, f)
            cells.append("-" if v is _ABSENT else value_text(v) + ("*" if path in res.origins else ""))
        out.append(f"    {f:<26}" + "".join(f"{x:<10}" for x in cells).rstrip())
    for r in res.rules:
        values = {p: v for p, v in r.sets.items() if res.origins.get(p) == f"rule {r.name}"}
        what = f"sets {settings_text(values)}" if values else "sets none of the fitted classes' fields"
        out.append(f"rule {r.name} ({r.condition()}) {what}: {r.why}")
    if res.recipe:
        out.append(f"the recipe sets {settings_text(leaves(res.recipe))}")
    return "\n".join(out)


_ABSENT = object()


def _class_value(cp: ClassPlan, f: str) -> Any:
    """A class plan's field by name (``"refine.count_margin"``); :data:`_ABSENT` inside an absent refinement."""
    if f.startswith("refine."):
        return _ABSENT if cp.refine is None else getattr(cp.refine, f.removeprefix("refine."))
    return getattr(cp, f)


def rule_summary(rule: Rule) -> str:
    """``"film-limited (contact SNR < 35): gate_factor 2, PC.highpass_hz 5, ..."``."""
    return f"{rule.name} ({rule.condition()}): {settings_text(dict(rule.sets))}"


def policy_markdown() -> str:
    """docs/fitting.md's policy: the rules table, then the plan's fields with their defaults."""
    out = ["| rule | when | sets | why |", "|---|---|---|---|"]
    out += [f"| {r.name} | {r.condition()} | {settings_text(dict(r.sets))} | {r.why} |" for r in RULES]
    base = default_plan(CLASSES)
    out += ["", "| plan field | default | meaning |", "|---|---|---|"]
    for name, info in FitPlan.model_fields.items():
        if name != "classes":
            out.append(f"| `{name}` | {value_text(getattr(base, name))} | {info.description} |")
    described = {**ClassPlan.model_fields, **{f"refine.{k}": v for k, v in RefinePlan.model_fields.items()}}
    for f in _CLASS_FIELDS:
        values = [_class_value(base.classes[c], f) for c in CLASSES]
        texts = ["-" if v is _ABSENT else value_text(v) for v in values]
        default = texts[0] if len(set(texts)) == 1 else ", ".join(f"{c} {t}" for c, t in zip(CLASSES, texts))
        out.append(f"| `classes.<class>.{f}` | {default} | {described[f].description} |")
    return "\n".join(out) + "\n"
