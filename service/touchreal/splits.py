"""A dataset's train / held-out split by repeat, and how a parameter file records it: ``touchreal fit``
splits its ramp and sine trials with it and records the seed; ``touchreal evaluate`` and the
decoders read the split back from the file."""

from __future__ import annotations

import zlib
from typing import Any, Sequence

import numpy as np

from .params import EncoderParams
from .recording import Dataset

FIT_PROTOCOLS = ("ramp", "sine")
SPLIT_METHOD = "per-condition seeded shuffle of repeats (crc32(condition), seed); first half trains"
NO_SPLIT_METHOD = "none: every ramp/sine trial trains, nothing is held out"


def _condition_rng(condition: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([zlib.crc32(condition.encode()), int(seed)])


def split_repeats(entries: Sequence[dict[str, Any]], seed: int) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(train, held-out) entries: per condition, shuffle the repeats with the seed; the first
    ``n // 2`` (at least 1) train, the rest are held out. A condition with one trial only trains."""
    by_cond: dict[str, list[dict[str, Any]]] = {}
    for e in entries:
        by_cond.setdefault(e["condition"], []).append(e)
    train, test = [], []
    for cond in sorted(by_cond):
        group = sorted(by_cond[cond], key=lambda e: (e["repeat"], e["id"]))
        order = _condition_rng(cond, seed).permutation(len(group))
        n_train = max(1, len(group) // 2)
        train += [group[i] for i in sorted(order[:n_train])]
        test += [group[i] for i in sorted(order[n_train:])]
    return train, test


def fitted_on_every_trial(params: EncoderParams, ds: Dataset) -> bool:
    """True if ``params`` were fitted on this dataset by ``touchreal fit`` without a held-out part."""
    prov = params.provenance
    return (prov.get("fitted_by") == "touchreal fit" and prov.get("split_method") == NO_SPLIT_METHOD
            and str(prov.get("dataset", "")) == str(ds.manifest.get("name", "")))


def params_split_seed(params: EncoderParams, ds: Dataset) -> int | None:
    """The split seed if ``params`` were fitted on this dataset by ``touchreal fit`` with a held-out
    half, else None."""
    prov = params.provenance
    if prov.get("fitted_by") != "touchreal fit" or prov.get("split_method") != SPLIT_METHOD:
        return None
    if str(prov.get("dataset", "")) != str(ds.manifest.get("name", "")):
        return None
    seed = prov.get("split_seed")
    return int(seed) if isinstance(seed, (int, float)) else None
