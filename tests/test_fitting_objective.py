"""The fitting objective (eqs. 1-10) on hand-computed cases."""

import numpy as np
import pytest

from touchreal.analysis.spiketrains import kernel_distance
from touchreal.fitting.objective import ObjectiveConfig, ReferenceSet, evaluate_loss, terms_from_stats

TAU = 0.01
CFG = ObjectiveConfig(kernel_tau_s=TAU)


def test_d_basic_is_the_mean_over_all_pairs_then_conditions():
    refs_c0 = [np.array([0.10, 0.20]), np.array([0.105])]
    refs_c1 = [np.array([0.5])]
    refs = ReferenceSet.build([refs_c0, refs_c1], TAU)
    preds = [np.array([0.1, 0.2]), np.array([0.12]), np.array([0.51, 0.6])]
    cond = [0, 0, 1]
    L = evaluate_loss(preds, cond, refs, CFG)
    d0 = np.mean([kernel_distance(p, r, TAU) for p in preds[:2] for r in refs_c0])
    d1 = kernel_distance(preds[2], refs_c1[0], TAU)
    np.testing.assert_allclose(L.d_kernel, [d0, d1], rtol=1e-12)
    assert L.d_basic == pytest.approx((d0 + d1) / 2)
    # N_T: c0 = (2 + 1) / 2 = 1.5, c1 = 1;  N_S: c0 = (2 + 1) / 2 = 1.5, c1 = 2
    np.testing.assert_allclose(L.n_t, [1.5, 1.0])
    np.testing.assert_allclose(L.n_s, [1.5, 2.0])
    assert L.l_rel == pytest.approx((0.0 + 1.0) / 2)
    assert L.l_empty == 0.0
    assert L.l_mgd == pytest.approx((d0 + d1) / 2)  # m = 3 > 2 conditions: mean of all
    assert L.total == pytest.approx(L.d_basic + L.l_rel + L.l_empty + L.l_mgd)


def test_identical_trains_give_zero_distance():
    tr = [np.array([0.1, 0.3, 0.31]), np.array([0.7])]
    refs = ReferenceSet.build([[tr[0]], [tr[1]]], TAU)
    L = evaluate_loss(tr, [0, 1], refs, CFG)
    assert L.total == pytest.approx(0.0, abs=1e-9)


def test_empty_penalty_and_relative_count_loss():
    # eq. 7-8: N_T = 4 >= thres_1, N_S = 0 <= thres_2 -> L_empty = 5 * |4 - 0| / 4 = 5
    refs = ReferenceSet.build([[np.array([0.1, 0.2, 0.3, 0.4])]], TAU)
    L = evaluate_loss([np.zeros(0)], [0], refs, CFG)
    assert L.l_rel == pytest.approx(1.0)
    assert L.l_empty == pytest.approx(5.0)
    assert L.d_basic == 1.0 and L.l_mgd == 1.0
    assert L.total == pytest.approx(8.0)
    # N_S = 1 > thres_2: no empty penalty, relative loss 3/4
    L = evaluate_loss([np.array([0.1])], [0], refs, CFG)
    assert L.l_empty == 0.0 and L.l_rel == pytest.approx(0.75)
    # N_T = 0: relative loss is the absolute count (documented convention), empty-empty pairs are 0
    refs0 = ReferenceSet.build([[np.zeros(0), np.zeros(0)]], TAU)
    assert evaluate_loss([np.array([0.1, 0.2])], [0], refs0, CFG).l_rel == pytest.approx(2.0)
    L = evaluate_loss([np.zeros(0)], [0], refs0, CFG)
    assert L.total == 0.0
    L1 = evaluate_loss([np.zeros(0)], [0], refs0, ObjectiveConfig(kernel_tau_s=TAU, empty_pair_distance=1.0))
    assert L1.d_basic == 1.0


def test_mgd_takes_the_mean_of_the_m_worst_conditions():
    d = np.array([0.1, 0.9, 0.5, 0.7, 0.2])
    n = np.ones(5)
    t = terms_from_stats(d, n, n, np.ones(5), CFG)
    assert t.l_mgd == pytest.approx((0.9 + 0.7 + 0.5) / 3)
    assert t.d_basic == pytest.approx(d.mean())
    t2 = terms_from_stats(d, n, n, np.ones(5), ObjectiveConfig(m_worst=1))
    assert t2.l_mgd == pytest.approx(0.9)


def test_condition_weights_change_only_the_means():
    d = np.array([0.2, 0.8])
    n_t = np.array([2.0, 4.0])
    n_s = np.array([2.0, 2.0])
    t = terms_from_stats(d, n_s, n_t, np.array([1.0, 3.0]), CFG)
    assert t.d_basic == pytest.approx((0.2 + 3 * 0.8) / 4)
    assert t.l_rel == pytest.approx((0 + 3 * 0.5) / 4)
    assert t.l_mgd == pytest.approx(0.5)  # unweighted worst-m mean


def test_count_weights_weigh_the_count_terms_and_leave_the_distance_on_weights():
    # c0 fires 1 of 2 reference spikes, c1 none of 3 (an empty condition: L_empty too)
    groups = [[np.array([0.1, 0.2])], [np.array([0.3, 0.4, 0.5])]]
    preds, cond = [np.array([0.1]), np.array([])], [0, 1]
    same = evaluate_loss(preds, cond, ReferenceSet.build(groups, TAU, weights=[1.0, 3.0]), CFG)
    split = evaluate_loss(preds, cond, ReferenceSet.build(groups, TAU, weights=[1.0, 3.0], count_weights=[1.0, 1.0]), CFG)
    assert split.d_basic == same.d_basic and split.l_mgd == same.l_mgd  # the distance keeps its weights
    assert same.l_rel == pytest.approx((0.5 + 3 * 1.0) / 4)
    assert split.l_rel == pytest.approx((0.5 + 1.0) / 2)  # the plain mean over conditions
    assert split.l_empty == pytest.approx(CFG.lambda_e * 1.0 / 2)
    with pytest.raises(ValueError, match="count_weights"):
        ReferenceSet.build(groups, TAU, count_weights=[1.0])


def test_count_weight_scales_only_the_relative_count_term():
    d = np.array([0.2, 0.8])
    n_t = np.array([2.0, 4.0])
    n_s = np.array([2.0, 2.0])
    base = terms_from_stats(d, n_s, n_t, np.ones(2), CFG)
    assert ObjectiveConfig().count_weight == 1.0  # the paper's eq. 1 by default
    t = terms_from_stats(d, n_s, n_t, np.ones(2), ObjectiveConfig(kernel_tau_s=TAU, count_weight=3.0))
    assert t.l_rel == pytest.approx(base.l_rel)  # reported unweighted
    assert t.d_basic == base.d_basic and t.l_empty == base.l_empty and t.l_mgd == base.l_mgd
    assert t.total == pytest.approx(base.total + 2.0 * base.l_rel)


def test_a_count_margin_leaves_count_errors_within_it_free():
    d = np.array([0.2, 0.8])
    n_t = np.array([2.0, 4.0])
    n_s = np.array([2.0, 2.0])  # L_rel = (0 + 0.5) / 2 = 0.25
    plain = terms_from_stats(d, n_s, n_t, np.ones(2), ObjectiveConfig(kernel_tau_s=TAU, count_weight=3.0))
    assert ObjectiveConfig().count_margin == 0.0  # the paper: every count error is charged
    within = terms_from_stats(d, n_s, n_t, np.ones(2), ObjectiveConfig(kernel_tau_s=TAU, count_weight=3.0, count_margin=0.3))
    beyond = terms_from_stats(d, n_s, n_t, np.ones(2), ObjectiveConfig(kernel_tau_s=TAU, count_weight=3.0, count_margin=0.1))
    assert within.l_rel == beyond.l_rel == plain.l_rel == pytest.approx(0.25)  # reported as it is
    assert within.total == pytest.approx(plain.total - 3.0 * 0.25)  # free within the margin
    assert beyond.total == pytest.approx(plain.total - 3.0 * 0.1)  # charged beyond it at the count weight


def test_errors():
    refs = ReferenceSet.build([[np.array([0.1])], [np.array([0.2])]], TAU)
    with pytest.raises(ValueError, match="without predicted"):
        evaluate_loss([np.array([0.1])], [0], refs, CFG)
    with pytest.raises(ValueError, match="different tau"):
        evaluate_loss([np.array([0.1])] * 2, [0, 1], refs, ObjectiveConfig(kernel_tau_s=0.02))
    with pytest.raises(ValueError):
        ReferenceSet.build([[]], TAU)


def test_segmented_count_loss_stops_misses_and_extras_cancelling():
    # reference: one spike in each half; prediction: two spikes in the first half, none in the second
    refs_whole = ReferenceSet.build([[np.array([0.1, 0.9])]], TAU)
    refs_seg = ReferenceSet.build([[np.array([0.1, 0.9])]], TAU, segment_edges=[np.array([0.5])])
    pred = [np.array([0.1, 0.2])]
    assert evaluate_loss(pred, [0], refs_whole, CFG).l_rel == 0.0  # eq. 7: the counts agree
    seg = evaluate_loss(pred, [0], refs_seg, CFG)
    assert seg.l_rel == pytest.approx((abs(2 - 1) + abs(0 - 1)) / 2)
    assert seg.d_basic == evaluate_loss(pred, [0], refs_whole, CFG).d_basic  # only the count term changes
    # a spike on an edge counts in the later segment; segments are averaged over the trains first
    refs = ReferenceSet.build([[np.array([0.5]), np.array([0.7, 0.2])]], TAU, segment_edges=[np.array([0.5])])  # unsorted is fine
    np.testing.assert_allclose(refs.n_t_seg, [0.5, 1.0])
    L = evaluate_loss([np.array([0.5]), np.array([0.1])], [0, 0], refs, CFG)
    assert L.l_rel == pytest.approx((abs(0.5 - 0.5) + abs(0.5 - 1.0)) / 1.5)


def test_segmented_count_loss_per_condition_and_one_segment_is_the_paper():
    rng = np.random.default_rng(3)
    groups = [[np.sort(rng.uniform(0, 1, rng.integers(0, 6))) for _ in range(4)] for _ in range(5)]
    preds = [np.sort(rng.uniform(0, 1, rng.integers(0, 6))) for _ in range(10)]
    cond = np.repeat(np.arange(5), 2)
    edges = [np.array([0.3, 0.6]), None, np.zeros(0), np.array([0.5]), np.array([0.1, 0.2, 0.9])]
    whole = evaluate_loss(preds, cond, ReferenceSet.build(groups, TAU), CFG)
    seg = evaluate_loss(preds, cond, ReferenceSet.build(groups, TAU, segment_edges=edges), CFG)
    expect = []
    for c in range(5):
        e = np.zeros(0) if edges[c] is None else edges[c]
        ref = np.mean([np.histogram(t, np.r_[-np.inf, e, np.inf])[0] for t in groups[c]], axis=0)
        pr = np.mean([np.histogram(p, np.r_[-np.inf, e, np.inf])[0] for p, k in zip(preds, cond) if k == c], axis=0)
        n_t = ref.sum()
        expect.append(np.abs(pr - ref).sum() / n_t if n_t > 0 else pr.sum())
    assert seg.l_rel == pytest.approx(np.mean(expect), rel=1e-9)
    assert seg.l_rel >= whole.l_rel - 1e-12
    np.testing.assert_array_equal(seg.n_s, whole.n_s)
    with pytest.raises(ValueError, match="increasing"):
        ReferenceSet.build([[np.array([0.1])]], TAU, segment_edges=[np.array([0.5, 0.2])])
    with pytest.raises(ValueError, match="one entry"):
        ReferenceSet.build([[np.array([0.1])]], TAU, segment_edges=[])


def test_vr_normalised_distance_is_the_reports_inter_over_intra_ratio_per_condition():
    from touchreal.analysis.spiketrains import vr_distance
    from touchreal.fitting.objective import VR_NORM_FLOOR

    refs_c0 = [np.array([0.100, 0.200]), np.array([0.104, 0.203]), np.array([0.098])]
    refs_c1 = [np.array([0.5])]  # one reference: normalised by 1 (one unmatched spike)
    refs = ReferenceSet.build([refs_c0, refs_c1], TAU, vr_normalised=True)
    intra = np.mean([vr_distance(refs_c0[i], refs_c0[j], TAU) for i, j in ((0, 1), (0, 2), (1, 2))])
    assert intra > VR_NORM_FLOOR
    np.testing.assert_allclose(refs.vr_norm, [intra, 1.0])
    preds = [np.array([0.101, 0.25]), np.array([0.51, 0.52])]
    L = evaluate_loss(preds, [0, 1], refs, CFG)
    inter0 = np.mean([vr_distance(preds[0], r, TAU) for r in refs_c0])
    np.testing.assert_allclose(L.d_kernel, [inter0 / intra, vr_distance(preds[1], refs_c1[0], TAU)], rtol=1e-12)
    assert L.d_basic == pytest.approx(L.d_kernel.mean())
    # the kernel distance of the same trains differs: the option is what changes the score
    assert not np.allclose(L.d_kernel, evaluate_loss(preds, [0, 1], ReferenceSet.build([refs_c0, refs_c1], TAU), CFG).d_kernel)


def test_vr_normalised_distance_charges_a_missed_and_an_extra_spike_alike():
    ref = np.array([0.1, 0.3])
    refs = ReferenceSet.build([[ref]], TAU, vr_normalised=True)
    missed = evaluate_loss([np.array([0.1])], [0], refs, CFG).d_basic
    extra = evaluate_loss([np.array([0.1, 0.3, 0.5])], [0], refs, CFG).d_basic
    assert missed == pytest.approx(extra) == pytest.approx(1.0)  # sqrt(1): one unmatched spike, floor-free norm 1
    # identical repeats: the floor keeps the normaliser finite
    same = ReferenceSet.build([[ref, ref.copy()]], TAU, vr_normalised=True)
    from touchreal.fitting.objective import VR_NORM_FLOOR

    assert same.vr_norm[0] == VR_NORM_FLOOR
