"""Specification of the simulated teachers (paper Algorithm 1, Eq. (1), appendix thresholds).

Conventions of sim_teacher.py: y is the weight on the second segment (1.0 = second preferred,
0.0 = first preferred, 0.5 = equally preferable, NaN = skipped), keep is False where skipped.
Statistical tests use a fixed seed and a tolerance of about 4 standard errors.
"""

import math
import re
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import sim_teacher  # noqa: E402
from sim_teacher import TEACHERS, SimTeacher, make_teacher  # noqa: E402

N_COPIES = 20_000


def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def four_standard_errors(p: float, n: int = N_COPIES) -> float:
    return 4.0 * math.sqrt(max(p * (1.0 - p), 1e-12) / n)


def copies(row, n=N_COPIES) -> np.ndarray:
    """n copies of one segment's rewards: shape (n, H)."""
    return np.tile(np.asarray(row, dtype=np.float64), (n, 1))


def one(teacher: SimTeacher, rewards0, rewards1):
    """Label one pair; returns (y, keep) as Python scalars."""
    y, keep = teacher.label(np.array([rewards0], float), np.array([rewards1], float))
    return float(y[0]), bool(keep[0])


# --------------------------------------------------------------------------------------------
# Presets (paper Section 3.3 / appendix list of teachers)
# --------------------------------------------------------------------------------------------


def test_oracle_preset_is_rational_undiscounted_and_error_free():
    t = make_teacher("oracle")
    assert math.isinf(t.beta) and t.beta > 0
    assert t.gamma == 1.0
    assert t.eps_mistake == 0.0 and t.eps_skip == 0.0 and t.eps_equal == 0.0
    assert t.delta_skip == 0.0 and t.delta_equal == 0.0


@pytest.mark.parametrize(
    "name, field, value",
    [
        ("stoc", "beta", 1.0),
        ("mistake", "eps_mistake", 0.1),
        ("skip", "eps_skip", 0.1),
        ("equal", "eps_equal", 0.1),
        ("myopic", "gamma", 0.9),
    ],
)
def test_each_preset_differs_from_oracle_in_exactly_the_papers_field(name, field, value):
    oracle = {"beta": math.inf, "gamma": 1.0, "eps_mistake": 0.0, "eps_skip": 0.0, "eps_equal": 0.0}
    assert TEACHERS[name] == {field: value}
    t = make_teacher(name)
    for f, default in oracle.items():
        assert getattr(t, f) == (value if f == field else default), f


def test_presets_are_exactly_the_six_teachers_of_the_paper():
    assert set(TEACHERS) == {"oracle", "stoc", "mistake", "skip", "equal", "myopic"}


def test_make_teacher_combines_preset_overrides_and_seed():
    t = make_teacher("myopic", seed=7, eps_mistake=0.1)
    assert t.gamma == 0.9 and t.eps_mistake == 0.1 and math.isinf(t.beta) and t.seed == 7
    # an override replaces the preset's own value
    assert make_teacher("stoc", beta=2.5).beta == 2.5
    # make_teacher does not mutate the preset table
    assert TEACHERS["myopic"] == {"gamma": 0.9}


# --------------------------------------------------------------------------------------------
# Oracle
# --------------------------------------------------------------------------------------------


def test_oracle_prefers_higher_return_segment_deterministically():
    t = make_teacher("oracle", seed=0)
    r0 = np.array([[1.0, 1.0], [5.0, 0.0], [0.0, 0.0], [3.0, 3.0]])
    r1 = np.array([[2.0, 1.0], [1.0, 1.0], [0.0, 0.001], [3.0, 2.0]])
    for _ in range(5):  # same answer on every call: no randomness for strict preferences
        y, keep = t.label(r0, r1)
        np.testing.assert_array_equal(y, [1.0, 0.0, 1.0, 0.0])
        assert keep.all()


def test_oracle_never_skips_even_negative_returns():
    t = make_teacher("oracle", seed=0)
    r0 = np.array([[-10.0, -10.0], [-1.0, -2.0]])
    r1 = np.array([[-5.0, -5.0], [-1.0, -1.5]])
    y, keep = t.label(r0, r1)
    assert keep.all()
    np.testing.assert_array_equal(y, [1.0, 1.0])
    # also after set_thresholds (eps = 0 means thresholds 0)
    t.set_thresholds(mean_return=-100.0, segment_len=2, episode_len=10)
    y, keep = t.label(-np.abs(r1), -np.abs(r0))
    assert keep.all() and not np.isnan(y).any()


def test_oracle_returns_float_labels_and_bool_keep_of_length_n():
    y, keep = make_teacher("oracle").label(np.zeros((3, 4)), np.ones((3, 4)))
    assert y.shape == (3,) and keep.shape == (3,)
    assert y.dtype == np.float64 and keep.dtype == bool


# --------------------------------------------------------------------------------------------
# Stochastic teacher: Bradley-Terry, Eq. (1)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("beta, d", [(1.0, 1.0), (1.0, -0.5), (1.0, 3.0), (2.0, 0.4), (0.5, -2.0)])
def test_stoc_label_frequency_is_sigmoid_beta_times_return_difference(beta, d):
    """P[second preferred] = exp(b R1) / (exp(b R1) + exp(b R0)) = sigmoid(b (R1 - R0))."""
    t = SimTeacher(beta=beta, seed=123)
    r0 = copies([0.25, 0.25])  # R0 = 0.5
    r1 = copies([0.25 + d / 2, 0.25 + d / 2])  # R1 = 0.5 + d
    y, keep = t.label(r0, r1)
    assert keep.all() and set(np.unique(y)) <= {0.0, 1.0}
    expected = sigmoid(beta * d)
    assert abs(y.mean() - expected) < four_standard_errors(expected), (y.mean(), expected)


def test_stoc_beta_zero_is_uniformly_random_regardless_of_returns():
    t = SimTeacher(beta=0.0, seed=5)
    y, _ = t.label(copies([0.0, 0.0]), copies([100.0, 100.0]))
    assert abs(y.mean() - 0.5) < four_standard_errors(0.5)


def test_stoc_preset_beta_one_matches_sigmoid():
    t = make_teacher("stoc", seed=11)
    y, _ = t.label(copies([0.0]), copies([1.0]))  # d = 1
    assert abs(y.mean() - sigmoid(1.0)) < four_standard_errors(sigmoid(1.0))


def test_oracle_exact_tie_is_a_fair_coin():
    """beta -> inf limit of Eq. (1) with equal returns is P = 1/2."""
    y, keep = make_teacher("oracle", seed=2).label(copies([1.0, 2.0]), copies([2.0, 1.0]))
    assert keep.all() and set(np.unique(y)) <= {0.0, 1.0}
    assert abs(y.mean() - 0.5) < four_standard_errors(0.5)


# --------------------------------------------------------------------------------------------
# Myopic teacher: step t of H weighs gamma^(H - t)
# --------------------------------------------------------------------------------------------


def test_myopic_weights_last_step_most_and_overrides_undiscounted_preference():
    # gamma = 0.5, H = 3: weights (0.25, 0.5, 1).
    # seg0 = (4, 0, 0): sum 4, myopic 1.0;  seg1 = (0, 0, 2): sum 2, myopic 2.0
    t = SimTeacher(gamma=0.5, seed=0)
    assert one(t, [4.0, 0.0, 0.0], [0.0, 0.0, 2.0]) == (1.0, True)
    # and the oracle (gamma = 1) prefers the other one on the same pair
    assert one(make_teacher("oracle"), [4.0, 0.0, 0.0], [0.0, 0.0, 2.0]) == (0.0, True)


def test_myopic_weight_of_first_step_is_gamma_to_the_h_minus_one():
    """Reward a at step 1 of seg0 vs reward 1 at step H of seg1: seg0 wins iff a * g^(H-1) > 1."""
    gamma, H = 0.9, 50
    t = make_teacher("myopic", seed=0)
    first_weight = gamma ** (H - 1)
    for factor, expected in [(1.001, 0.0), (0.999, 1.0)]:
        r0 = np.zeros(H)
        r0[0] = factor / first_weight
        r1 = np.zeros(H)
        r1[-1] = 1.0
        assert one(t, r0, r1) == (expected, True), factor
        # swapping sides swaps the answer
        assert one(t, r1, r0) == (1.0 - expected, True), factor


def test_myopic_middle_step_weight_is_exact():
    """Step t of H = 3 weighs gamma^(3 - t): step 2 weighs gamma; compare with last step."""
    t = SimTeacher(gamma=0.5, seed=0)
    # step 2 reward 2 weighs 2 * 0.5 = 1.0; last-step reward 0.99 / 1.01
    assert one(t, [0.0, 2.0, 0.0], [0.0, 0.0, 0.99]) == (0.0, True)
    assert one(t, [0.0, 2.0, 0.0], [0.0, 0.0, 1.01]) == (1.0, True)


def test_stochastic_myopic_uses_discounted_difference_in_sigmoid():
    # gamma 0.5, H 2: weights (0.5, 1). seg1 - seg0 = (2, 0) -> discounted advantage 1.0 (sum 2)
    t = SimTeacher(beta=1.0, gamma=0.5, seed=9)
    y, _ = t.label(copies([0.0, 0.0]), copies([2.0, 0.0]))
    expected = sigmoid(1.0)
    assert abs(y.mean() - expected) < four_standard_errors(expected)


# --------------------------------------------------------------------------------------------
# Mistakes (Algorithm 1 lines 7 and 10)
# --------------------------------------------------------------------------------------------


def test_mistake_flips_oracle_labels_at_rate_eps():
    t = make_teacher("mistake", seed=3)
    y, keep = t.label(copies([0.0, 0.0]), copies([1.0, 1.0]))  # second clearly better
    assert keep.all() and set(np.unique(y)) <= {0.0, 1.0}
    flipped = (y == 0.0).mean()
    assert abs(flipped - 0.1) < four_standard_errors(0.1), flipped
    # and symmetric when the first is better
    y, _ = t.label(copies([1.0, 1.0]), copies([0.0, 0.0]))
    assert abs((y == 1.0).mean() - 0.1) < four_standard_errors(0.1)


def test_mistake_eps_one_always_flips_and_zero_never():
    r0, r1 = copies([0.0], 200), copies([1.0], 200)
    y, _ = SimTeacher(eps_mistake=1.0, seed=0).label(r0, r1)
    np.testing.assert_array_equal(y, 0.0)
    y, _ = SimTeacher(eps_mistake=0.0, seed=0).label(r0, r1)
    np.testing.assert_array_equal(y, 1.0)


def test_mistake_never_flips_equal_labels():
    t = SimTeacher(eps_mistake=1.0, eps_equal=0.5, seed=0)
    t.set_thresholds(mean_return=8.0, segment_len=2, episode_len=4)  # delta_equal = 0.5 * 4 = 2
    assert t.delta_equal == 2.0
    y, keep = t.label(copies([1.0, 1.0], 500), copies([1.5, 1.0], 500))  # |diff| = 0.5 < 2
    assert keep.all()
    np.testing.assert_array_equal(y, 0.5)


def test_mistake_never_unskips_skipped_queries():
    t = SimTeacher(eps_mistake=1.0, eps_skip=0.5, seed=0)
    t.set_thresholds(mean_return=8.0, segment_len=2, episode_len=4)  # delta_skip = 2
    y, keep = t.label(copies([0.0, 0.5], 500), copies([0.5, 0.5], 500))  # max return 1 < 2
    assert not keep.any()
    assert np.isnan(y).all()


# --------------------------------------------------------------------------------------------
# Adaptive thresholds (appendix): delta = eps * H / T * R_avg
# --------------------------------------------------------------------------------------------


def test_set_thresholds_is_eps_times_scaled_return_not_eps_squared():
    t = make_teacher("skip")  # eps_skip = 0.1
    t.set_thresholds(mean_return=400.0, segment_len=50, episode_len=1000)
    assert t.delta_skip == pytest.approx(2.0, rel=1e-12)  # eps^2 would give 0.2
    assert t.delta_equal == 0.0

    t = make_teacher("equal")  # eps_equal = 0.1
    t.set_thresholds(mean_return=400.0, segment_len=50, episode_len=1000)
    assert t.delta_equal == pytest.approx(2.0, rel=1e-12)
    assert t.delta_skip == 0.0


def test_set_thresholds_exact_dyadic_case():
    t = SimTeacher(eps_skip=0.25, eps_equal=0.5)
    t.set_thresholds(mean_return=64.0, segment_len=4, episode_len=16)  # H/T * R = 16
    assert t.delta_skip == 4.0
    assert t.delta_equal == 8.0


def test_set_thresholds_twice_does_not_compound():
    t = make_teacher("skip", eps_equal=0.1)
    for _ in range(3):
        t.set_thresholds(mean_return=400.0, segment_len=50, episode_len=1000)
        assert t.delta_skip == pytest.approx(2.0, rel=1e-12)
        assert t.delta_equal == pytest.approx(2.0, rel=1e-12)
    # a new R_avg replaces, not accumulates
    t.set_thresholds(mean_return=800.0, segment_len=50, episode_len=1000)
    assert t.delta_skip == pytest.approx(4.0, rel=1e-12)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(mean_return=1.0, segment_len=0, episode_len=10),
        dict(mean_return=1.0, segment_len=11, episode_len=10),
        dict(mean_return=math.nan, segment_len=5, episode_len=10),
        dict(mean_return=math.inf, segment_len=5, episode_len=10),
    ],
)
def test_set_thresholds_rejects_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        make_teacher("skip").set_thresholds(**kwargs)


# --------------------------------------------------------------------------------------------
# Skip and equal: exact boundaries, order, undiscounted sums
# --------------------------------------------------------------------------------------------


def _skip_teacher(**extra) -> SimTeacher:
    t = SimTeacher(eps_skip=0.25, seed=0, **extra)
    t.set_thresholds(mean_return=64.0, segment_len=4, episode_len=16)  # delta_skip = 4.0 exactly
    assert t.delta_skip == 4.0
    return t


def test_skip_when_better_return_strictly_below_threshold_and_keep_at_threshold():
    t = _skip_teacher()
    r0 = np.array([[1.0, 1.0, 1.0, 0.5],   # 3.5 vs 1: max 3.5 < 4   -> skip
                   [1.0, 1.0, 1.0, 1.0],   # 4.0 vs 1: max == 4      -> keep
                   [-9.0, 0.0, 0.0, 0.0],  # -9 vs 3.75: max < 4     -> skip
                   [0.0, 0.0, 0.0, 0.0]])  # 0 vs 4.5                -> keep
    r1 = np.array([[0.25, 0.25, 0.25, 0.25],
                   [0.25, 0.25, 0.25, 0.25],
                   [1.0, 1.0, 1.0, 0.75],
                   [1.0, 1.0, 1.0, 1.5]])
    y, keep = t.label(r0, r1)
    np.testing.assert_array_equal(keep, [False, True, False, True])
    assert np.isnan(y[[0, 2]]).all()
    np.testing.assert_array_equal(y[[1, 3]], [0.0, 1.0])


def test_skip_uses_the_better_of_the_two_segments():
    t = _skip_teacher()
    # only one segment reaches the threshold: kept (max, not min, and not the sum of both)
    assert one(t, [0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]) == (1.0, True)
    assert one(t, [1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 0.0, 0.0]) == (0.0, True)
    # each below but their sum above: skipped
    y, keep = one(t, [1.0, 1.0, 1.0, 0.0], [1.0, 1.0, 1.0, 0.0])
    assert not keep and math.isnan(y)


def _equal_teacher(**extra) -> SimTeacher:
    t = SimTeacher(eps_equal=0.25, seed=0, **extra)
    t.set_thresholds(mean_return=64.0, segment_len=4, episode_len=16)  # delta_equal = 4.0 exactly
    assert t.delta_equal == 4.0
    return t


def test_equal_when_return_difference_strictly_below_threshold():
    t = _equal_teacher()
    r0 = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [10.0, 0.0], [10.0, 0.0]])
    r1 = np.array([[3.0, 0.5], [2.0, 2.0], [4.0, 0.5], [7.0, 0.0], [5.0, 1.0]])
    #            diff 3.5 -> eq | diff 4 -> strict  | 4.5     | -3 -> eq  | -4 -> strict
    y, keep = t.label(r0, r1)
    assert keep.all()
    np.testing.assert_array_equal(y, [0.5, 1.0, 1.0, 0.5, 0.0])


def test_equal_teacher_never_skips():
    t = _equal_teacher()
    y, keep = t.label(np.full((3, 2), -50.0), np.full((3, 2), -60.0))
    assert keep.all()
    np.testing.assert_array_equal(y, 0.0)


def test_skip_is_checked_before_equal():
    t = SimTeacher(eps_skip=0.25, eps_equal=0.25, seed=0)
    t.set_thresholds(mean_return=64.0, segment_len=4, episode_len=16)  # both thresholds 4.0
    # returns 1 and 1.5: below skip and within equal -> skipped, not 0.5
    y, keep = one(t, [1.0, 0.0], [1.5, 0.0])
    assert not keep and math.isnan(y)
    # returns 5 and 6: kept and within equal -> 0.5
    assert one(t, [5.0, 0.0], [6.0, 0.0]) == (0.5, True)


def test_skip_and_equal_use_undiscounted_sums_even_for_myopic_teacher():
    # gamma 0.5, H 4: weights (1/8, 1/4, 1/2, 1); delta_skip = delta_equal = 4
    t = SimTeacher(gamma=0.5, eps_skip=0.25, eps_equal=0.25, seed=0)
    t.set_thresholds(mean_return=64.0, segment_len=4, episode_len=16)
    # seg1 = (4, 0, 0, 0): undiscounted 4 (kept), discounted 0.5 (would be skipped)
    # seg0 = (0, 0, 0, 0): return difference 4 is not < 4 -> strict; seg1 preferred
    assert one(t, [0.0, 0.0, 0.0, 0.0], [4.0, 0.0, 0.0, 0.0]) == (1.0, True)
    # seg0 = (0, 0, 0, 9), seg1 = (10, 0, 0, 0): undiscounted diff 1 < 4 -> equal (0.5),
    # although the discounted sums 9 vs 1.25 differ by 7.75 > 4 (a discounted rule gives 0.0)
    assert one(t, [0.0, 0.0, 0.0, 9.0], [10.0, 0.0, 0.0, 0.0]) == (0.5, True)


# --------------------------------------------------------------------------------------------
# Numerical stability
# --------------------------------------------------------------------------------------------


def test_large_beta_is_stable_and_correct():
    t = SimTeacher(beta=1e4, seed=0)
    r0 = np.array([[0.5, 0.5], [1.0, 0.0], [0.25, 0.25]])  # returns ~1, beta * R = 1e4
    r1 = np.array([[0.5, 0.6], [0.5, 0.0], [0.25, 0.25 + 1e-4]])
    with warnings.catch_warnings(), np.errstate(all="raise"):
        warnings.simplefilter("error")
        y, keep = t.label(r0, r1)
    assert keep.all()
    np.testing.assert_array_equal(y[:2], [1.0, 0.0])  # sigmoid(+-1000) is 1 / 0 to machine precision
    assert y[2] in (0.0, 1.0)
    # beta * d = 1 even when beta * R = 1e4: still sigmoid(1)
    with warnings.catch_warnings(), np.errstate(all="raise"):
        warnings.simplefilter("error")
        y, _ = t.label(copies([0.5, 0.5]), copies([0.5, 0.5 + 1e-4]))
    assert abs(y.mean() - sigmoid(1.0)) < four_standard_errors(sigmoid(1.0))


@pytest.mark.parametrize("scale", [1e3, 1e6, 1e100])
@pytest.mark.parametrize("name", ["stoc", "myopic", "oracle"])
def test_large_reward_scales_are_stable_and_correct(name, scale):
    t = make_teacher(name, seed=0)
    H = 50
    r0 = np.full((2, H), scale)
    r1 = np.full((2, H), scale)
    r1[0] *= 1.5  # second much better
    r0[1] *= 1.5  # first much better
    with warnings.catch_warnings(), np.errstate(all="raise"):
        warnings.simplefilter("error")
        y, keep = t.label(r0, r1)
        y_neg, _ = t.label(-r0, -r1)  # very negative returns too
    assert keep.all()
    np.testing.assert_array_equal(y, [1.0, 0.0])
    np.testing.assert_array_equal(y_neg, [0.0, 1.0])


def test_skip_and_equal_thresholds_stable_for_large_scales():
    t = SimTeacher(beta=1.0, eps_skip=0.1, eps_equal=0.1, gamma=0.9, seed=0)
    t.set_thresholds(mean_return=1e9, segment_len=50, episode_len=1000)
    with warnings.catch_warnings(), np.errstate(all="raise"):
        warnings.simplefilter("error")
        y, keep = t.label(np.full((2, 50), 1e6), np.array([np.full(50, 1e6 + 1.0), np.full(50, 2e6)]))
    # returns 5e7 / 5e7+50 and 5e7 / 1e8; delta_skip = delta_equal = 5e6
    assert keep.all()
    np.testing.assert_array_equal(y, [0.5, 1.0])


# --------------------------------------------------------------------------------------------
# Combinations
# --------------------------------------------------------------------------------------------


def test_myopic_and_mistake_combined_flip_the_myopic_preference_at_rate_eps():
    t = make_teacher("myopic", seed=4, eps_mistake=0.1)
    H = 10
    r0 = np.zeros(H)
    r0[0] = 10.0  # undiscounted 10, myopic 10 * 0.9^9 = 3.87
    r1 = np.zeros(H)
    r1[-1] = 5.0  # undiscounted 5, myopic 5
    y, keep = t.label(copies(r0), copies(r1))
    assert keep.all()
    # myopic prefers segment 1; 10% flipped
    assert abs((y == 0.0).mean() - 0.1) < four_standard_errors(0.1)


def test_stoc_and_mistake_combined_mix_sigmoid_and_flip():
    # P[y = 1] = (1 - eps) * sigmoid(beta d) + eps * (1 - sigmoid(beta d))
    t = SimTeacher(beta=1.0, eps_mistake=0.2, seed=8)
    y, _ = t.label(copies([0.0]), copies([1.0]))
    p = sigmoid(1.0)
    expected = 0.8 * p + 0.2 * (1 - p)
    assert abs(y.mean() - expected) < four_standard_errors(expected)


def test_all_irrationalities_at_once():
    t = SimTeacher(beta=math.inf, gamma=0.5, eps_mistake=1.0, eps_skip=0.25, eps_equal=0.25, seed=0)
    t.set_thresholds(mean_return=64.0, segment_len=4, episode_len=16)  # both thresholds 4
    r0 = np.array([[0, 0, 0, 1.0], [0, 0, 0, 5.0], [8.0, 0, 0, 0], [8.0, 0, 0, 0]])
    r1 = np.array([[0, 0, 0, 2.0], [0, 0, 0, 6.0], [0, 0, 0, 2.0], [0, 0, 0, 0.5]])
    # row 0: max 2 < 4 -> skip; row 1: diff 1 < 4 -> equal; row 2: undiscounted prefers seg0
    # (8 vs 2) but myopic 1 vs 2 prefers seg1, mistake (eps 1) flips to 0;
    # row 3: myopic 1 vs 0.5 prefers seg0, flipped to 1.
    y, keep = t.label(r0, r1)
    np.testing.assert_array_equal(keep, [False, True, True, True])
    assert math.isnan(y[0])
    np.testing.assert_array_equal(y[1:], [0.5, 0.0, 1.0])


# --------------------------------------------------------------------------------------------
# Seeds
# --------------------------------------------------------------------------------------------


def test_same_seed_gives_same_labels():
    r0, r1 = copies([0.0], 2000), copies([0.3], 2000)
    for name in ("stoc", "mistake"):
        y_a, _ = make_teacher(name, seed=42).label(r0, r1)
        y_b, _ = make_teacher(name, seed=42).label(r0, r1)
        np.testing.assert_array_equal(y_a, y_b)


def test_different_seeds_give_different_stochastic_labels():
    r0, r1 = copies([0.0], 2000), copies([0.3], 2000)
    y_a, _ = make_teacher("stoc", seed=1).label(r0, r1)
    y_b, _ = make_teacher("stoc", seed=2).label(r0, r1)
    assert (y_a != y_b).any()


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(beta=-1.0), "beta"),
        (dict(beta=math.nan), "beta"),
        (dict(gamma=0.0), "gamma"),
        (dict(gamma=1.5), "gamma"),
        (dict(gamma=math.nan), "gamma"),
        (dict(eps_mistake=-0.1), "eps_mistake"),
        (dict(eps_mistake=1.1), "eps_mistake"),
        (dict(eps_skip=-0.1), "eps_skip"),
        (dict(eps_skip=1.1), "eps_skip"),
        (dict(eps_equal=-0.1), "eps_equal"),
        (dict(eps_equal=1.1), "eps_equal"),
    ],
)
def test_bad_teacher_parameter_raises_value_error_naming_it(kwargs, name):
    with pytest.raises(ValueError, match=name):
        SimTeacher(**kwargs)
    with pytest.raises(ValueError, match=name):
        make_teacher("oracle", **kwargs)


def test_boundary_teacher_parameters_are_accepted():
    SimTeacher(beta=0.0, gamma=1.0, eps_mistake=0.0, eps_skip=1.0, eps_equal=1.0)
    SimTeacher(gamma=1e-6, eps_mistake=1.0)


@pytest.mark.parametrize(
    "shape0, shape1",
    [((3, 4), (3, 5)), ((3, 4), (2, 4)), ((4,), (4,)), ((2, 3, 4), (2, 3, 4)), ((3, 4), (4,))],
)
def test_label_rejects_mismatched_or_non_2d_arrays(shape0, shape1):
    with pytest.raises(ValueError, match="rewards"):
        make_teacher("oracle").label(np.zeros(shape0), np.zeros(shape1))


def test_unknown_preset_raises_and_lists_known_names():
    with pytest.raises(ValueError) as info:
        make_teacher("optimist")
    message = str(info.value)
    assert "optimist" in message
    for name in TEACHERS:
        assert name in message


@pytest.mark.parametrize("field", ["temperature", "delta_skip", "rng"])
def test_unknown_override_field_raises_naming_it(field):
    with pytest.raises(ValueError, match=field):
        make_teacher("oracle", **{field: 1.0})


def test_label_of_zero_pairs_returns_empty_arrays():
    for name in TEACHERS:
        t = make_teacher(name, seed=0)
        t.set_thresholds(mean_return=10.0, segment_len=5, episode_len=10)
        y, keep = t.label(np.zeros((0, 5)), np.zeros((0, 5)))
        assert y.shape == (0,) and keep.shape == (0,)
        assert keep.dtype == bool


def test_equal_threshold_uses_absolute_return_on_negative_return_tasks():
    # R_avg = -400, H/T = 0.05: delta_equal = 0.1 * 0.05 * 400 = 2.0 (a negative threshold would never fire)
    teacher = make_teacher("equal", seed=0)
    teacher.set_thresholds(mean_return=-400.0, segment_len=50, episode_len=1000)
    assert teacher.delta_equal == pytest.approx(2.0)
    y, keep = teacher.label(np.array([[-10.0], [-10.0]]), np.array([[-11.5], [-12.5]]))
    assert y.tolist() == [0.5, 0.0] and keep.all()


def test_state_dict_is_plain_data_and_restores_the_same_labels():
    import io

    import torch

    rewards0, rewards1 = np.random.default_rng(0).normal(size=(2, 200, 5))
    teacher = make_teacher("stoc", seed=3, eps_mistake=0.2, eps_equal=0.1)
    teacher.set_thresholds(40.0, 5, 50)
    teacher.label(rewards0, rewards1)  # the generator has moved on
    data = io.BytesIO()
    torch.save(teacher.state_dict(), data)
    data.seek(0)
    restored = make_teacher("oracle", seed=99)  # another teacher entirely, until its state is loaded
    restored.load_state_dict(torch.load(data, weights_only=True))
    assert (restored.beta, restored.eps_mistake, restored.delta_equal) == (1.0, 0.2, teacher.delta_equal)
    expected, got = teacher.label(rewards0, rewards1), restored.label(rewards0, rewards1)
    np.testing.assert_array_equal(expected[0], got[0])
    np.testing.assert_array_equal(expected[1], got[1])


# ---------------------------------------------------------------- label files and a person's sessions


def write_session(run_dir, number, n=4, segment_len=5, **extra):
    rng = np.random.default_rng(number)
    rewards0, rewards1 = rng.random((n, segment_len)), rng.random((n, segment_len))
    y = (rewards1.sum(1) > rewards0.sum(1)).astype(float)
    sim_teacher.save_labels(str(run_dir), number, step=100 * number, y=y, keep=np.ones(n, bool), rewards0=rewards0,
                            rewards1=rewards1, threshold_scale=0.25 * number, **extra)
    return y


def test_label_files_round_trip_from_a_run_directory_its_labels_or_one_file(tmp_path):
    ys = [write_session(tmp_path, number) for number in range(3)]
    for path in (tmp_path, tmp_path / "labels"):
        sessions = sim_teacher.load_labels(str(path))
        assert [s["step"] for s in sessions] == [0, 100, 200]
        assert [s["threshold_scale"] for s in sessions] == [0.0, 0.25, 0.5]  # a float each
        for session, y in zip(sessions, ys):
            np.testing.assert_array_equal(session["y"], y)
    [one] = sim_teacher.load_labels(str(tmp_path / "labels" / "session_0001.npz"))
    np.testing.assert_array_equal(one["y"], ys[1])
    assert not list((tmp_path / "labels").glob("*.tmp"))  # written whole, then renamed


@pytest.mark.parametrize("problem, message", [
    ("empty", "no label files"), ("not_npz", "not an .npz file"), ("no_keep", "no keep in it"),
    ("shapes", "rewards0, rewards1 must be (N, H)"), ("lengths", "sessions of different segment lengths [5, 6]"),
])
def test_bad_label_files_are_refused_naming_the_file(tmp_path, problem, message):
    labels = tmp_path / "labels"
    labels.mkdir()
    if problem == "not_npz":
        (labels / "session_0000.npz").write_text("not a zip")
    elif problem == "no_keep":
        np.savez(labels / "session_0000.npz", y=np.zeros(2), rewards0=np.zeros((2, 5)), rewards1=np.zeros((2, 5)))
    elif problem == "shapes":
        np.savez(labels / "session_0000.npz", y=np.zeros(3), keep=np.ones(2, bool), rewards0=np.zeros((2, 5)),
                 rewards1=np.zeros((2, 5)))
    elif problem == "lengths":
        write_session(tmp_path, 0)
        write_session(tmp_path, 1, segment_len=6)
    with pytest.raises(ValueError, match=re.escape(message)):
        sim_teacher.load_labels(str(tmp_path))


def test_load_pairs_joins_each_segments_observations_and_actions_in_session_order(tmp_path):
    segments = []
    for number in range(2):
        rng = np.random.default_rng(number)
        segment = {f"{key}{i}": rng.random((4, 5, dim)) for key, dim in (("obs", 3), ("actions", 2)) for i in (0, 1)}
        write_session(tmp_path, number, **segment)
        segments.append(segment)
    inputs0, inputs1, y, keep = sim_teacher.load_pairs(str(tmp_path), (5, 5))
    assert inputs0.shape == inputs1.shape == (8, 5, 5) and y.shape == keep.shape == (8,)
    np.testing.assert_array_equal(inputs1[4:, :, :3], segments[1]["obs1"])  # session 1 after session 0
    np.testing.assert_array_equal(inputs0[:4, :, 3:], segments[0]["actions0"])
    with pytest.raises(ValueError, match=re.escape("do not fit this run's (5, 6)")):
        sim_teacher.load_pairs(str(tmp_path), (5, 6))


def test_load_pairs_refuses_label_files_without_segments(tmp_path):
    write_session(tmp_path, 0)  # rewards and labels only
    with pytest.raises(ValueError, match="hold no segments' obs and actions"):
        sim_teacher.load_pairs(str(tmp_path), (5, 5))


def test_resume_sets_aside_the_sessions_after_the_checkpoint(tmp_path):
    for number in range(4):
        write_session(tmp_path, number)
    sim_teacher.set_labels_aside(str(tmp_path), sessions_done=2, step=250)
    assert [p.name for p in sorted((tmp_path / "labels").glob("session_*.npz"))] == ["session_0000.npz",
                                                                                   "session_0001.npz"]
    aside = tmp_path / "labels" / "before_resume_at_step_250"
    assert sorted(p.name for p in aside.iterdir()) == ["session_0002.npz", "session_0003.npz"]


def test_a_person_answers_a_session_through_its_files(tmp_path):
    # the query pool: (observations, actions, rewards, reset seed) of two episodes of different lengths
    episodes = [(np.zeros((8, 2)), np.arange(8 * 3, dtype=np.float32).reshape(8, 3), np.zeros(8), 11),
                (np.zeros((6, 2)), -np.ones((6, 3), np.float32), np.zeros(6), 22)]
    teacher = sim_teacher.make_teacher("human", seed=0, run_dir=str(tmp_path), episodes=episodes)
    queries = {"step": 300, "episode0": np.array([0, 1, 1]), "start0": np.array([0, 2, 1]),
               "episode1": np.array([1, 0, 0]), "start1": np.array([3, 4, 0])}
    answers = {"order": [2, 0, 1], "answers": {"0": "left", "1": "skip", "2": "equal"}}
    (tmp_path / "queries").mkdir()
    sim_teacher.write_answers(str(tmp_path), 0, answers)  # answered already: label() returns at once
    y, keep = teacher.label(np.zeros((3, 2)), np.zeros((3, 2)), queries)
    np.testing.assert_array_equal(keep, [True, False, True])
    np.testing.assert_array_equal(y[keep], [0.0, 0.5])
    saved = sim_teacher.load_queries(sim_teacher.queries_path(str(tmp_path), 0))
    assert int(saved["step"]) == 300
    np.testing.assert_array_equal(saved["seed0"], [11, 22, 22])
    np.testing.assert_array_equal(saved["start1"], [3, 4, 0])
    assert saved["actions0"].shape == (3, 8, 3)  # each episode's actions, padded to the longest
    np.testing.assert_array_equal(saved["actions0"][1, :6], -1)
    np.testing.assert_array_equal(saved["actions0"][1, 6:], 0)
    np.testing.assert_array_equal(saved["actions1"][1], episodes[0][1])
    assert teacher.state_dict() == {"session": 1}  # the next session gets the next files
    assert sim_teacher.read_answers(str(tmp_path), 1) == {"order": [], "answers": {}}


def test_a_simulated_teacher_takes_the_queries_and_ignores_them():
    rewards0, rewards1 = np.zeros((2, 3)), np.ones((2, 3))
    y, keep = make_teacher("oracle", seed=0).label(rewards0, rewards1, {"step": 5})
    np.testing.assert_array_equal(y, [1.0, 1.0])


# ---------------------------------------------------------------- the side bias (not in the paper; fit_teacher.py)


def test_a_zero_bias_draws_nothing_so_the_paper_s_teachers_label_as_before():
    rng = np.random.default_rng(0)
    r0, r1 = rng.random((500, 10)), rng.random((500, 10))
    teacher = SimTeacher(beta=1.0, eps_mistake=0.1, seed=7)
    teacher.label(r0, r1)
    reference = np.random.default_rng(7)
    reference.random(500)  # the choice
    reference.random(500)  # the mistakes
    assert teacher.rng.bit_generator.state == reference.bit_generator.state


@pytest.mark.parametrize("bias, better, side", [(-0.3, 1, 0.0), (0.4, 0, 1.0)])
def test_a_bias_answers_its_side_with_its_probability_whatever_the_segments(bias, better, side):
    n = 20_000
    rewards = np.zeros((n, 5)), np.ones((n, 5))  # segment 1 better
    r0, r1 = rewards if better == 1 else rewards[::-1]
    y, keep = SimTeacher(bias=bias, seed=3).label(r0, r1)  # rational otherwise: always the better one
    assert keep.all()
    assert abs((y == side).mean() - abs(bias)) < 0.01  # 3 standard deviations at n = 20,000


def test_a_bias_leaves_equal_and_skipped_pairs_alone():
    r0 = np.array([[1.0, 1.0], [0.0, 0.0], [5.0, 0.0]])
    r1 = np.array([[1.0, 1.05], [0.01, 0.0], [0.0, 0.0]])
    teacher = SimTeacher(eps_equal=0.5, eps_skip=0.1, bias=1.0, seed=0)
    teacher.set_thresholds(mean_return=20.0, segment_len=2, episode_len=10)  # delta_equal 2.0, delta_skip 0.4
    y, keep = teacher.label(r0, r1)
    assert keep.tolist() == [True, False, True] and y[0] == 0.5 and y[2] == 1.0  # only the strict pair answers right


def test_a_bias_outside_minus_one_one_is_refused():
    with pytest.raises(ValueError, match=re.escape("bias must be in [-1, 1]")):
        SimTeacher(bias=1.5)
    assert make_teacher("mistake", bias=-0.2).bias == -0.2
