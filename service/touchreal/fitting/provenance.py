"""What a fitted parameter file records of its fit (its ``provenance``): the dataset and its split,
the build's profile, the rules that applied, the recipe, the plan the fit ran, and per class every
CMA-ES run and its losses."""

from __future__ import annotations

import json
from dataclasses import asdict
from typing import Any

from ..params import EncoderParams
from ..recording import Dataset
from ..splits import FIT_PROTOCOLS, NO_SPLIT_METHOD, SPLIT_METHOD
from .config import FitConfig
from .objective import ObjectiveConfig
from .policy import Resolution
from .search import ClassFit

#: the objective's constants no plan changes (paper eqs. 8-10)
PAPER_CONSTANTS = ("lambda_e", "thres_1", "thres_2", "m_worst")


def provenance(ds: Dataset, cfg: FitConfig, res: Resolution, fits: dict[str, ClassFit], *, init: EncoderParams | None, n_train: int,
               n_validation: int, n_baselines: int, rig_lag_ms: float, seconds: float) -> dict[str, Any]:
    """The provenance of a fit of ``ds`` run with ``cfg`` on the plan of ``res`` (``seconds``: the fit's
    wall time; ``rig_lag_ms``: the SingleTact's rise after the commanded onset)."""
    constants = asdict(ObjectiveConfig())
    prov: dict[str, Any] = {
        "fitted_by": "touchreal fit",
        "dataset": str(ds.manifest.get("name", "")),
        "dataset_dir": str(ds.root.resolve()),
        "protocols": list(FIT_PROTOCOLS),
        "split_method": SPLIT_METHOD if cfg.holdout else NO_SPLIT_METHOD,
        "split_seed": int(cfg.seed),
        "n_train_trials": n_train,
        "n_validation_trials": n_validation,
        "rig_lag_ms": rig_lag_ms,
        "calibration_baselines": n_baselines,
        "profile": res.profile.as_dict(),
        "rules": [r.name for r in res.rules],
        "recipe": json.loads(json.dumps(res.recipe)),
        "plan": res.plan.model_dump(mode="json"),
        "objective": {k: constants[k] for k in PAPER_CONSTANTS},
        "optimizer": "CMA-ES (cma)",
        "fit_seconds": round(seconds, 1),
        "fitted_classes": list(fits),
        "loss": {c: _loss(f) for c, f in fits.items()},
    }
    if init is not None and init.provenance.get("fitted_by") == "touchreal fit":
        prov["init"] = {**{k: init.provenance[k] for k in ("dataset", "fitted_classes") if k in init.provenance},
                        "class_window_ms": {c: init.window_ms(c) for c in init.classes}}
    return prov


def _loss(f: ClassFit) -> dict[str, Any]:
    """A class's losses and runs: its last stage's, and its search's under ``search`` when it was refined."""
    return {
        "start": round(f.start_loss, 5),
        "train": {k: round(v, 5) for k, v in f.train.as_dict().items()} if f.train else {},
        "validation": {k: round(v, 5) for k, v in f.validation.as_dict().items()} if f.validation else {},
        "generations": f.generations,
        "evaluations": f.evaluations,
        "runs": [r.as_dict() for r in f.runs],
        "seconds": round(f.seconds, 1),
        **({"search": {"start": round(f.search.start_loss, 5), "best": round(f.search.best_loss, 5),
                       "generations": f.search.generations, "evaluations": f.search.evaluations,
                       "runs": [r.as_dict() for r in f.search.runs], "seconds": round(f.search.seconds, 1)}}
           if f.search is not None else {}),
    }
