"""AP@R40 on small ranked lists whose value is worked out by hand in each comment."""
import numpy as np
import pytest

from detbench.eval import ap_r40, ap_r40_ranked

T, F = True, False


@pytest.mark.parametrize("ranked, num_gt, expected", [
    # perfect list: precision 1 at every recall level
    ([T, T, T, T], 4, 1.0),
    # perfect list with trailing FPs: max_{r' >= r} p(r') still 1 at every level
    ([T, T, F, F, F], 2, 1.0),
    # recall 1/2 only: levels 1..20 precision 1, levels 21..40 unreached -> 20/40
    ([T], 2, 0.5),
    # FP first: precision 1/2 at recall 1 -> every level 1/2
    ([F, T], 1, 0.5),
    # [T F T], 2 GT: k=1 p=1 r=1/2; k=3 p=2/3 r=1 -> (20 * 1 + 20 * 2/3) / 40
    ([T, F, T], 2, (20 + 20 * 2 / 3) / 40),
    # [T F T], 3 GT: r=1/3 at k=1 (levels 1..13, i/40 <= 1/3), r=2/3 at k=3 (levels 14..26,
    # p=2/3), levels 27..40 unreached -> (13 + 13 * 2/3) / 40
    ([T, F, T], 3, (13 + 13 * 2 / 3) / 40),
    # [F F T T], 2 GT: p = 1/3 at r=1/2, 1/2 at r=1; interpolation takes the later, higher 1/2
    # for the first 20 levels as well -> 1/2
    ([F, F, T, T], 2, 0.5),
    # [T F F T], 2 GT: levels 1..20 -> 1, levels 21..40 -> 2/4 -> 0.75
    ([T, F, F, T], 2, 0.75),
    # recall exactly 1/40 reaches the first level and no other: 1/40 (exact integer test)
    ([T], 40, 1 / 40),
    # 39 of 40: levels 1..39 precision 1, level 40 unreached -> 39/40
    ([T] * 39, 40, 39 / 40),
    # only FPs
    ([F, F, F], 5, 0.0),
    # no predictions at all
    ([], 3, 0.0),
])
def test_hand_computed(ranked, num_gt, expected):
    assert ap_r40_ranked(ranked, num_gt) == pytest.approx(expected, abs=1e-12)


def test_recall_half_gives_at_most_half():
    rng = np.random.default_rng(1)
    for _ in range(50):
        n_gt = int(rng.integers(2, 30))
        n_tp = n_gt // 2
        ranked = np.array([T] * n_tp + [F] * int(rng.integers(0, 20)))
        rng.shuffle(ranked)
        ap = ap_r40_ranked(ranked, n_gt)
        assert 0.0 <= ap <= 0.5 + 1e-12


def test_no_ground_truth_is_null():
    assert ap_r40_ranked([], 0) is None
    assert ap_r40_ranked([F, F], 0) is None
    assert ap_r40([0.3], [F], 0) is None


def test_more_tps_than_ground_truth_is_an_error():
    with pytest.raises(ValueError, match="matched once"):
        ap_r40_ranked([T, T], 1)
    with pytest.raises(ValueError):
        ap_r40_ranked([T], -1)


def test_ranking_by_score_with_stable_ties():
    # ranked by score: 0.9 (F), 0.8 (T) -> 0.5
    assert ap_r40([0.8, 0.9], [T, F], 1) == pytest.approx(0.5)
    # tie: input order decides
    assert ap_r40([0.5, 0.5], [F, T], 1) == pytest.approx(0.5)
    assert ap_r40([0.5, 0.5], [T, F], 1) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="same length"):
        ap_r40([0.5], [T, F], 1)


def test_monotone_in_rank_of_fp():
    # Moving an FP further down the ranking never lowers AP.
    base = [T, T, T, T]
    values = [ap_r40_ranked(base[:i] + [F] + base[i:], 4) for i in range(5)]
    assert values == sorted(values)
    assert values[-1] == 1.0 and values[0] < 1.0
