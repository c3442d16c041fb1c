"""CIs and the two-way ANOVA against hand-computed results on designs with known effects."""

import numpy as np
import pytest
from scipy import stats as sps

from touchreal.analysis import stats


def test_mean_ci_matches_t_interval():
    x = np.array([3.0, 4.5, 5.0, 6.5, 2.0])
    m, lo, hi = stats.mean_ci(x)
    lo_ref, hi_ref = sps.t.interval(0.95, x.size - 1, loc=x.mean(), scale=sps.sem(x))
    assert (m, lo, hi) == pytest.approx((x.mean(), lo_ref, hi_ref))
    assert stats.mean_ci([2.0]) == (2.0, 2.0, 2.0)
    assert all(np.isnan(stats.mean_ci([])))


def _balanced(rng, effect_a, effect_b, inter, n=12):
    y, a, b = [], [], []
    for i, la in enumerate((10, 100, 200)):
        for j, lb in enumerate(("TouchSim", "TouchReal")):
            mu = effect_a[i] + effect_b[j] + inter[i][j]
            y += list(mu + rng.normal(0, 1.0, n))
            a += [la] * n
            b += [lb] * n
    return np.array(y), a, b


def test_anova_balanced_matches_textbook_sums_of_squares():
    rng = np.random.default_rng(0)
    y, a, b = _balanced(rng, [0, 5, 2], [0, 0.0], [[0, 0], [0, 0], [0, 0]])
    res = stats.two_way_anova(y, a, b)
    # textbook two-way ANOVA for a balanced design
    A, B = np.array(a), np.array(b)
    grand = y.mean()
    ss_a = sum(12 * 2 * (y[A == la].mean() - grand) ** 2 for la in set(a))
    ss_b = sum(12 * 3 * (y[B == lb].mean() - grand) ** 2 for lb in set(b))
    cell = {(la, lb): y[(A == la) & (B == lb)] for la in set(a) for lb in set(b)}
    ss_e = sum(((v - v.mean()) ** 2).sum() for v in cell.values())
    ss_ab = ((y - grand) ** 2).sum() - ss_a - ss_b - ss_e
    df_e = y.size - 6
    assert res["frequency"]["sum_sq"] == pytest.approx(ss_a)
    assert res["source"]["sum_sq"] == pytest.approx(ss_b)
    assert res["interaction"]["sum_sq"] == pytest.approx(ss_ab)
    f_a = (ss_a / 2) / (ss_e / df_e)
    assert res["frequency"]["F"] == pytest.approx(f_a)
    assert res["frequency"]["p"] == pytest.approx(sps.f.sf(f_a, 2, df_e))
    assert res["frequency"]["p"] < 1e-10  # strong frequency effect found
    assert res["source"]["p"] > 0.05  # no source effect built in
    assert res["residual"]["df"] == df_e


def test_anova_detects_source_effect_and_interaction():
    rng = np.random.default_rng(1)
    y, a, b = _balanced(rng, [0, 5, 2], [0, 3.0], [[0, 0], [0, 0], [0, 0]])
    assert stats.two_way_anova(y, a, b)["source"]["p"] < 1e-6
    y, a, b = _balanced(rng, [0, 5, 2], [0, 0], [[0, 0], [0, 4.0], [0, -4.0]])
    res = stats.two_way_anova(y, a, b)
    assert res["interaction"]["p"] < 1e-6
    with pytest.raises(ValueError):
        stats.two_way_anova([1.0, 2.0], [1, 1], ["a", "b"])


def test_significance_labels():
    assert stats.significance(1e-5) == "p < 0.001"
    assert stats.significance(0.03) == "p < 0.05"
    assert stats.significance(0.2) == "n.s."
