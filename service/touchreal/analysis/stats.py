"""Statistics of the evaluation: confidence intervals and the two-way ANOVA of Tables 2-3."""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy import stats as sps


def mean_ci(x: Sequence[float], level: float = 0.95) -> tuple[float, float, float]:
    """Mean and its two-sided t confidence interval ``(mean, lo, hi)``; a single value has a
    zero-width interval, an empty sample gives NaNs."""
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    m = float(x.mean())
    if x.size < 2:
        return m, m, m
    half = float(sps.t.ppf(0.5 + level / 2.0, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size))
    return m, m - half, m + half


def two_way_anova(
    y: Sequence[float], a: Sequence, b: Sequence, names: tuple[str, str] = ("frequency", "source"), typ: int = 2
) -> dict[str, dict[str, float]]:
    """Two-way ANOVA with interaction, ``y ~ C(a) * C(b)`` (statsmodels OLS + ``anova_lm``).

    Returns ``{names[0]: row, names[1]: row, "interaction": row, "residual": row}`` with
    ``F``, ``p``, ``df`` and ``sum_sq`` per row (F and p are NaN for the residual). Type II sums of
    squares by default (main effects adjusted for each other; appropriate for unbalanced designs).
    """
    import pandas as pd
    import statsmodels.formula.api as smf
    from statsmodels.stats.anova import anova_lm

    df = pd.DataFrame({"y": np.asarray(y, np.float64), "a": [str(v) for v in a], "b": [str(v) for v in b]})
    if df["a"].nunique() < 2 or df["b"].nunique() < 2:
        raise ValueError("each factor needs at least two levels")
    model = smf.ols("y ~ C(a) * C(b)", data=df).fit()
    table = anova_lm(model, typ=typ)
    keys = {"C(a)": names[0], "C(b)": names[1], "C(a):C(b)": "interaction", "Residual": "residual"}
    out: dict[str, dict[str, float]] = {}
    for idx, row in table.iterrows():
        name = keys.get(str(idx))
        if name is None:
            continue
        out[name] = {
            "F": float(row.get("F", np.nan)),
            "p": float(row.get("PR(>F)", np.nan)),
            "df": float(row["df"]),
            "sum_sq": float(row["sum_sq"]),
        }
    return out


def significance(p: float) -> str:
    """Label of a p-value as in the paper's tables."""
    if not np.isfinite(p):
        return "n/a"
    if p < 0.001:
        return "p < 0.001"
    if p < 0.01:
        return "p < 0.01"
    if p < 0.05:
        return "p < 0.05"
    return "n.s."
