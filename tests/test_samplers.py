"""Specification of query selection, feedback schedules and candidate pairs (paper Section 4.2,
appendix "Sampling schemes"). Statistical tests use fixed seeds and ~4 standard-error tolerances."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from samplers import (SAMPLERS, SCHEDULES, draw_segments, planned_labels, random_pairs, schedule_sizes, session_steps,  # noqa: E402
                      select)


def binary_entropy(p):
    p = np.asarray(p, dtype=np.float64)
    return -(p * np.log(p) + (1 - p) * np.log(1 - p))


def brute_force_nearest(features, centers):
    """Exact Euclidean distance from each feature row to its nearest center (inf if no center)."""
    if len(centers) == 0:
        return np.full(len(features), np.inf)
    diff = features[:, None, :] - centers[None, :, :]
    return np.sqrt((diff**2).sum(axis=2)).min(axis=1)


def four_clusters(rng, per_cluster=25, spread=0.5):
    corners = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 100.0], [100.0, 100.0]])
    points = np.concatenate([c + spread * rng.standard_normal((per_cluster, 2)) for c in corners])
    cluster = np.repeat(np.arange(4), per_cluster)
    return points, cluster, corners


# --------------------------------------------------------------------------------------------
# Uncertainty-based sampling
# --------------------------------------------------------------------------------------------


def test_sampler_and_schedule_names():
    assert set(SAMPLERS) == {
        "uniform", "disagreement", "entropy", "coverage", "disagreement-coverage", "entropy-coverage"
    }
    assert set(SCHEDULES) == {"uniform", "decay", "increase"}


def test_disagreement_picks_largest_std_across_members():
    probs = np.array(
        [
            #  0     1     2     3     4
            [0.5, 0.1, 0.4, 0.0, 0.2],
            [0.5, 0.9, 0.6, 1.0, 0.8],
            [0.5, 0.5, 0.5, 0.5, 0.5],
        ]
    )
    # std over members: 0, 0.327, 0.082, 0.408, 0.245
    assert list(select("disagreement", 1, probs=probs)) == [3]
    assert sorted(select("disagreement", 2, probs=probs)) == [1, 3]
    assert sorted(select("disagreement", 3, probs=probs)) == [1, 3, 4]


def test_disagreement_ignores_how_undecided_members_are():
    # candidate 0: all members say 0.5 (max entropy, zero disagreement)
    # candidate 1: members 0.9 and 0.99 (low entropy, some disagreement)
    probs = np.array([[0.5, 0.9], [0.5, 0.99]])
    assert list(select("disagreement", 1, probs=probs)) == [1]


def test_disagreement_returns_distinct_indices_highest_first():
    rng = np.random.default_rng(0)
    probs = rng.random((5, 200))
    chosen = select("disagreement", 20, probs=probs)
    assert len(set(chosen.tolist())) == 20
    std = probs.std(axis=0)
    np.testing.assert_array_equal(chosen, np.argsort(-std)[:20])
    assert np.issubdtype(chosen.dtype, np.integer)


def test_entropy_ranks_by_mean_of_member_entropies_not_entropy_of_mean():
    # candidate 0: members 0.01 / 0.99 -> mean 0.5 (entropy of mean ln 2 = 0.693), but each member
    #   is confident: mean of entropies H(0.01) = 0.056
    # candidate 1: members 0.3 / 0.3 -> both measures H(0.3) = 0.611
    probs = np.array([[0.01, 0.3], [0.99, 0.3]])
    assert binary_entropy(0.5) > binary_entropy(0.3) > binary_entropy(0.01)
    assert list(select("entropy", 1, probs=probs)) == [1]


def test_entropy_prefers_undecided_candidates():
    probs = np.array([[0.99, 0.5, 0.01, 0.7, 0.5], [0.99, 0.5, 0.01, 0.7, 0.5]])
    # entropies: 0.056, 0.693, 0.056, 0.611, 0.693
    assert sorted(select("entropy", 2, probs=probs)) == [1, 4]
    assert sorted(select("entropy", 3, probs=probs)) == [1, 3, 4]


def test_entropy_is_symmetric_in_p_and_one_minus_p():
    # candidates 0 (p=0.2) and 1 (p=0.8) have equal entropy; 2 (p=0.1) is lower
    probs = np.array([[0.2, 0.8, 0.1]])
    assert sorted(select("entropy", 2, probs=probs)) == [0, 1]


def test_entropy_handles_exact_zero_and_one_without_nan():
    probs = np.array([[0.0, 1.0, 0.6], [0.0, 1.0, 0.6]])
    with np.errstate(all="raise"):
        chosen = select("entropy", 1, probs=probs)
    assert list(chosen) == [2]


# --------------------------------------------------------------------------------------------
# Uniform sampling
# --------------------------------------------------------------------------------------------


def test_uniform_returns_n_distinct_indices_in_range():
    chosen = select("uniform", 30, features=np.zeros((50, 3)), rng=np.random.default_rng(0))
    assert len(chosen) == 30 and len(set(chosen.tolist())) == 30
    assert chosen.min() >= 0 and chosen.max() < 50


def test_uniform_is_uniform_over_candidates():
    rng = np.random.default_rng(1)
    m, n, draws = 10, 3, 4000
    counts = np.zeros(m)
    probs = np.full((2, m), 0.5)
    for _ in range(draws):
        counts[select("uniform", n, probs=probs, rng=rng)] += 1
    expected = draws * n / m  # 1200 each
    chi2 = ((counts - expected) ** 2 / expected).sum()
    # 9 degrees of freedom: P[chi2 > 33.7] ~ 1e-4 (sampling without replacement makes it smaller)
    assert chi2 < 33.7, counts


def test_uniform_reproducible_with_seeded_rng():
    features = np.zeros((100, 2))
    a = select("uniform", 10, features=features, rng=np.random.default_rng(5))
    b = select("uniform", 10, features=features, rng=np.random.default_rng(5))
    c = select("uniform", 10, features=features, rng=np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


# --------------------------------------------------------------------------------------------
# Coverage sampling: greedy k-center
# --------------------------------------------------------------------------------------------


def assert_greedy_k_center(features, chosen, labeled=None, first_is_free=False):
    """Each pick is a candidate farthest from its nearest already-chosen center (brute force)."""
    features = np.asarray(features, dtype=np.float64)
    centers = np.zeros((0, features.shape[1])) if labeled is None else np.asarray(labeled, np.float64)
    assert len(set(np.asarray(chosen).tolist())) == len(chosen)
    for i, pick in enumerate(chosen):
        nearest = brute_force_nearest(features, centers)
        if not (first_is_free and i == 0):
            nearest[chosen[:i]] = -np.inf
            best = nearest.max()
            assert nearest[pick] >= best - 1e-9 * max(best, 1.0), (i, pick, nearest[pick], best)
        centers = np.vstack([centers, features[pick]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_coverage_is_greedy_k_center_with_labeled_centers(seed):
    rng = np.random.default_rng(seed)
    features = rng.standard_normal((300, 6))
    labeled = rng.standard_normal((20, 6))
    chosen = select("coverage", 25, features=features, labeled_features=labeled, rng=rng)
    assert len(chosen) == 25
    assert_greedy_k_center(features, chosen, labeled)


def test_coverage_first_pick_is_farthest_from_labeled_queries():
    features = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0], [3.0, 0.0]])
    labeled = np.array([[0.0, 0.0], [6.0, 0.0]])
    # nearest distances to labeled: 0, 1, 1, 3 -> candidate 3 first
    chosen = select("coverage", 1, features=features, labeled_features=labeled)
    assert list(chosen) == [3]


def test_coverage_without_labeled_queries_is_greedy_after_the_first_pick():
    rng = np.random.default_rng(3)
    features = rng.standard_normal((200, 4))
    chosen = select("coverage", 15, features=features, rng=rng)
    assert_greedy_k_center(features, chosen, first_is_free=True)


def test_coverage_hand_checked_line():
    # points on a line; start from labeled 0: picks 10 (farthest), then 5, then 2 or 8 ...
    features = np.array([[0.0], [2.0], [5.0], [8.0], [10.0]])
    chosen = select("coverage", 2, features=features, labeled_features=np.array([[0.0]]))
    assert list(chosen) == [4, 2]


@pytest.mark.parametrize("seed", range(5))
def test_coverage_picks_one_point_per_cluster(seed):
    rng = np.random.default_rng(seed)
    points, cluster, _ = four_clusters(rng)
    chosen = select("coverage", 4, features=points, rng=rng)
    assert sorted(cluster[chosen]) == [0, 1, 2, 3]


def test_coverage_avoids_clusters_near_labeled_queries():
    rng = np.random.default_rng(0)
    points, cluster, corners = four_clusters(rng)
    labeled = corners[:1] + 0.1  # a labelled query at cluster 0
    for seed in range(3):
        chosen = select("coverage", 3, features=points, labeled_features=labeled, rng=np.random.default_rng(seed))
        assert sorted(cluster[chosen]) == [1, 2, 3]


def test_coverage_returns_distinct_indices_with_duplicate_points():
    features = np.repeat(np.array([[0.0, 0.0], [1.0, 1.0], [5.0, 5.0]]), 3, axis=0)  # 9 points
    for n in (3, 5, 9):
        chosen = select("coverage", n, features=features, rng=np.random.default_rng(n))
        assert len(chosen) == n and len(set(chosen.tolist())) == n
    # the first 3 picks cover the 3 distinct locations
    chosen = select("coverage", 3, features=features, rng=np.random.default_rng(0))
    assert sorted(chosen // 3) == [0, 1, 2]
    # all identical points
    chosen = select("coverage", 4, features=np.ones((4, 3)), rng=np.random.default_rng(0))
    assert sorted(chosen) == [0, 1, 2, 3]


def test_coverage_float32_features_match_float64_choice():
    rng = np.random.default_rng(4)
    features = rng.standard_normal((300, 20))
    labeled = rng.standard_normal((10, 20))
    a = select("coverage", 20, features=features, labeled_features=labeled)
    b = select("coverage", 20, features=features.astype(np.float32), labeled_features=labeled.astype(np.float32))
    np.testing.assert_array_equal(a, b)


def test_coverage_float32_is_translation_invariant():
    rng = np.random.default_rng(0)
    features = rng.standard_normal((200, 100))
    labeled = rng.standard_normal((20, 100))
    offset = 1000.0  # same points, shifted: distances unchanged
    chosen = select(
        "coverage", 1, features=(features + offset).astype(np.float32), labeled_features=(labeled + offset).astype(np.float32)
    )
    nearest = brute_force_nearest(features, labeled)
    assert nearest[chosen[0]] >= nearest.max() * (1 - 1e-4), (nearest[chosen[0]], nearest.max())


def test_coverage_with_empty_labeled_set_behaves_like_none():
    rng = np.random.default_rng(0)
    features = rng.standard_normal((50, 3))
    chosen = select("coverage", 5, features=features, labeled_features=np.zeros((0, 3)), rng=rng)
    assert_greedy_k_center(features, chosen, first_is_free=True)


# --------------------------------------------------------------------------------------------
# Hybrid sampling: uncertainty first (n_inter), then k-center among those
# --------------------------------------------------------------------------------------------


def _hybrid_case():
    """8 candidates; disagreement ranks 0 > 3 > 1 > 2 > (4..7). Features: 4..7 are far outliers."""
    probs = np.array(
        [
            # 0    1    2     3     4    5    6    7
            [0.0, 0.2, 0.3, 0.1, 0.5, 0.5, 0.5, 0.5],
            [1.0, 0.8, 0.7, 0.9, 0.5, 0.5, 0.5, 0.5],
        ]
    )  # std: 0.5, 0.3, 0.2, 0.4, 0, 0, 0, 0
    features = np.array(
        [
            [0.0, 0.0],
            [0.1, 0.0],
            [10.0, 0.0],
            [0.05, 0.05],
            [1000.0, 0.0],
            [0.0, 1000.0],
            [-1000.0, 0.0],
            [0.0, -1000.0],
        ]
    )
    labeled = np.array([[0.0, 0.0]])
    return probs, features, labeled


def test_disagreement_coverage_chooses_k_centers_among_most_uncertain_half():
    probs, features, labeled = _hybrid_case()
    # default n_inter = 8 // 2 = 4: candidates {0, 1, 2, 3}
    # k-center from labeled (0,0): farthest is 2 (dist 10); then nearest to {(0,0), (10,0)}:
    # 0 -> 0, 1 -> 0.1, 3 -> 0.0707 -> pick 1
    chosen = select("disagreement-coverage", 2, probs=probs, features=features, labeled_features=labeled)
    assert list(chosen) == [2, 1]
    # contrast: pure disagreement picks {0, 3}, pure coverage picks the outliers
    assert sorted(select("disagreement", 2, probs=probs)) == [0, 3]
    assert set(select("coverage", 2, features=features, labeled_features=labeled).tolist()) <= {4, 5, 6, 7}


def test_hybrid_never_leaves_the_n_inter_most_uncertain():
    probs, features, _ = _hybrid_case()
    for seed in range(10):
        chosen = select("disagreement-coverage", 3, probs=probs, features=features, rng=np.random.default_rng(seed))
        assert set(chosen.tolist()) <= {0, 1, 2, 3}
        assert len(set(chosen.tolist())) == 3


def test_hybrid_explicit_n_inter():
    probs, features, labeled = _hybrid_case()
    # n_inter = n_query: exactly the most uncertain ones
    chosen = select("disagreement-coverage", 2, probs=probs, features=features, labeled_features=labeled, n_inter=2)
    assert sorted(chosen) == [0, 3]
    # n_inter = 3: {0, 3, 1}; k-center from (0,0): farthest is 1 (0.1) then 3
    chosen = select("disagreement-coverage", 2, probs=probs, features=features, labeled_features=labeled, n_inter=3)
    assert list(chosen) == [1, 3]
    # n_inter = M: same as coverage
    np.testing.assert_array_equal(
        select("disagreement-coverage", 3, probs=probs, features=features, labeled_features=labeled, n_inter=8),
        select("coverage", 3, features=features, labeled_features=labeled),
    )


def test_entropy_coverage_chooses_k_centers_among_highest_entropy():
    # entropies: candidates 0..3 near 0.5 (high), 4..7 confident (low)
    probs = np.array([[0.5, 0.45, 0.55, 0.4, 0.99, 0.01, 0.98, 0.02]] * 3)
    features = np.array([[0.0], [1.0], [2.0], [9.0], [100.0], [-100.0], [200.0], [-200.0]])
    chosen = select("entropy-coverage", 2, probs=probs, features=features, labeled_features=np.array([[0.0]]))
    # among {0, 1, 2, 3}: farthest from 0 is 3 (9), then nearest to {0, 9}: 1 -> 1, 2 -> 2 -> pick 2
    assert list(chosen) == [3, 2]
    # pure entropy would pick 0 (p = 0.5) and then 1 or 2
    assert 0 in select("entropy", 2, probs=probs).tolist()


def test_hybrid_is_greedy_k_center_on_random_data():
    rng = np.random.default_rng(7)
    probs = rng.random((4, 400))
    features = rng.standard_normal((400, 5))
    labeled = rng.standard_normal((10, 5))
    chosen = select("disagreement-coverage", 30, probs=probs, features=features, labeled_features=labeled, n_inter=120)
    pool = np.argsort(-probs.std(axis=0))[:120]
    assert set(chosen.tolist()) <= set(pool.tolist())
    local = np.array([np.flatnonzero(pool == c)[0] for c in chosen])
    assert_greedy_k_center(features[pool], local, labeled)


# --------------------------------------------------------------------------------------------
# Feedback schedules (Section 4.2)
# --------------------------------------------------------------------------------------------

COMBOS = [(500, 50), (1000, 100), (2000, 200), (10000, 50), (20000, 100), (7, 3), (1, 1), (100, 7), (3, 3)]


@pytest.mark.parametrize("budget, per_session", COMBOS)
def test_uniform_schedule_is_per_session_then_remainder(budget, per_session):
    k, remainder = divmod(budget, per_session)
    expected = [per_session] * k + ([remainder] if remainder else [])
    sizes = schedule_sizes("uniform", budget, per_session)
    assert sizes.tolist() == expected and np.issubdtype(sizes.dtype, np.integer) and sizes.sum() == budget


def test_decay_and_increase_are_the_reference_codes_formulas_computed_by_hand():
    # T = 1000, sessions after t = 100, 300, 500, 700, 900 steps, 10 per session, budget 50.
    # decay: int(2 * 10 * (T - t) / T) = 18, 14, 10, 6, 2 (sum 50)
    # increase: int(10 / 2 * T / (T - t + 1)) = int(5.549), int(7.13), int(9.98), int(16.6) = 5, 7, 9, 16; then
    # int(49.5) = 49 capped at the 13 left of the budget
    steps = [100, 300, 500, 700, 900]
    assert schedule_sizes("decay", 50, 10, steps, 1000).tolist() == [18, 14, 10, 6, 2]
    assert schedule_sizes("increase", 50, 10, steps, 1000).tolist() == [5, 7, 9, 16, 13]
    # a budget spent early ends the schedule; one the sessions cannot spend is what they ask
    assert schedule_sizes("decay", 30, 10, steps, 1000).tolist() == [18, 12]
    assert schedule_sizes("decay", 100, 10, steps, 1000).sum() == 50
    # never a session of 0: late in a decaying run int(...) would be 0, the session asks 1
    assert schedule_sizes("decay", 50, 10, [999], 1000).tolist() == [1]


def test_walker_walk_preset_schedules_are_the_reference_runs():
    """The paper's walker-walk setting (1000 labels, 100 per session every 20K steps from step 10K, 500K steps) with
    the reference's walker scripts (reward_batch 200 for decay, 50 for increase)."""
    steps = session_steps(10_001, 20_000, 500_000) - 1  # pebble.py: steps done before each session
    assert steps[:3].tolist() == [10_000, 30_000, 50_000] and len(steps) == 25
    assert schedule_sizes("decay", 1000, 100, steps, 500_000).tolist() == [196, 188, 180, 172, 164, 100]
    assert schedule_sizes("increase", 1000, 100, steps, 500_000).tolist() == [51, 53, 55, 58, 60, 64, 67, 71, 75, 80,
                                                                             86, 92, 99, 89]


@pytest.mark.parametrize("name", ["decay", "increase"])
def test_decay_and_increase_need_the_steps_of_the_sessions(name):
    with pytest.raises(ValueError, match="needs the steps of the sessions and total_steps"):
        schedule_sizes(name, 100, 10)
    with pytest.raises(ValueError, match="session steps must be in"):
        schedule_sizes(name, 100, 10, [1000], 1000)


def test_session_steps_follow_the_plan_of_the_runs():
    assert session_steps(11, 30, 100).tolist() == [11, 41, 71]
    assert session_steps(32_000, 32_000, 99_999, granularity=3000).tolist() == [33_000, 66_000, 99_000]
    assert session_steps(11, 30, 10).tolist() == []


# --------------------------------------------------------------------------------------------
# Candidate pairs
# --------------------------------------------------------------------------------------------


def test_random_pairs_shapes_and_integer_dtypes():
    out = random_pairs([100, 80, 120], 50, 37, np.random.default_rng(0))
    assert len(out) == 4
    for a in out:
        assert a.shape == (37,)
        assert np.issubdtype(a.dtype, np.integer)
    empty = random_pairs([100], 50, 0, np.random.default_rng(0))
    assert all(a.shape == (0,) for a in empty)


def test_random_pairs_positions_are_uniform_and_reach_the_last_start():
    # one episode of 60 steps, segments of 50: starts 0..10 (11 positions)
    rng = np.random.default_rng(0)
    n = 22_000
    e0, s0, e1, s1 = random_pairs([60], 50, n, rng)
    assert (e0 == 0).all() and (e1 == 0).all()
    for starts in (s0, s1):
        assert starts.min() == 0 and starts.max() == 10
        freq = np.bincount(starts, minlength=11) / n
        p = 1 / 11
        assert np.abs(freq - p).max() < 4.5 * math.sqrt(p * (1 - p) / n), freq


def test_random_pairs_never_pair_a_segment_with_itself():
    rng = np.random.default_rng(1)
    e0, s0, e1, s1 = random_pairs([51], 50, 1000, rng)  # exactly two positions
    assert ((s0 == 0) & (s1 == 1) | (s0 == 1) & (s1 == 0)).all()
    e0, s0, e1, s1 = random_pairs([52, 53, 40], 50, 20_000, rng)
    assert not ((e0 == e1) & (s0 == s1)).any()


def test_random_pairs_joint_distribution_uniform_over_ordered_distinct_pairs():
    # episodes of 52 and 54 steps: 3 + 5 = 8 positions, 56 ordered distinct pairs
    rng = np.random.default_rng(2)
    n = 56_000
    e0, s0, e1, s1 = random_pairs([52, 54], 50, n, rng)
    offsets = np.array([0, 3])
    flat0 = offsets[e0] + s0
    flat1 = offsets[e1] + s1
    assert ((0 <= s0) & (s0 <= np.where(e0 == 0, 2, 4))).all()
    assert ((0 <= s1) & (s1 <= np.where(e1 == 0, 2, 4))).all()
    counts = np.zeros((8, 8))
    np.add.at(counts, (flat0, flat1), 1)
    assert np.diag(counts).sum() == 0
    expected = n / 56
    off_diagonal = counts[~np.eye(8, dtype=bool)]
    chi2 = ((off_diagonal - expected) ** 2 / expected).sum()
    assert chi2 < 110, chi2  # 55 dof: mean 55, sd 10.5 -> ~5 sd margin


def test_random_pairs_skip_episodes_shorter_than_segment():
    rng = np.random.default_rng(3)
    e0, s0, e1, s1 = random_pairs([10, 60, 3], 50, 5000, rng)
    for e, s in ((e0, s0), (e1, s1)):
        assert (e == 1).all()
        assert set(np.unique(s).tolist()) == set(range(11))


def test_random_pairs_episode_weight_proportional_to_its_positions():
    # episode 0: 51 steps -> 2 positions; episode 1: 57 -> 8 positions; episode 2: 49 -> none
    rng = np.random.default_rng(4)
    n = 20_000
    e0, s0, _, _ = random_pairs([51, 57, 49], 50, n, rng)
    assert not (e0 == 2).any()
    frac = (e0 == 0).mean()
    assert abs(frac - 0.2) < 4 * math.sqrt(0.2 * 0.8 / n)
    assert s0[e0 == 0].max() == 1 and s0[e0 == 1].max() == 7


def test_random_pairs_segment_covering_whole_episode_is_eligible():
    e0, s0, e1, s1 = random_pairs([50, 50], 50, 200, np.random.default_rng(5))
    assert (s0 == 0).all() and (s1 == 0).all()
    assert (e0 != e1).all()


def test_random_pairs_reproducible_with_seeded_rng():
    a = random_pairs([100, 200], 50, 100, np.random.default_rng(9))
    b = random_pairs([100, 200], 50, 100, np.random.default_rng(9))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("lengths", [[50], [10, 49, 3], [], [49, 49], [50, 10]])
def test_random_pairs_needs_two_distinct_positions(lengths):
    for n_pairs in (10, 0):
        with pytest.raises(ValueError, match="segment"):
            random_pairs(lengths, 50, n_pairs, np.random.default_rng(0))


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def test_draw_segments_cuts_the_drawn_windows_out_of_every_part_of_the_episodes():
    # episode e: observations 100 e + t (one feature), actions -(100 e + t), true rewards 1000 e + t
    episodes = [(100.0 * e + np.arange(n)[:, None], -(100.0 * e + np.arange(n)[:, None]), 1000.0 * e + np.arange(n))
                for e, n in enumerate([60, 5, 80])]  # the middle one is shorter than a segment: never drawn
    segments = draw_segments(episodes, 10, 500, np.random.default_rng(3))
    e0, s0, e1, s1 = random_pairs([60, 5, 80], 10, 500, np.random.default_rng(3))  # the same draws
    window = np.arange(10)
    for side, (e, s) in enumerate(((e0, s0), (e1, s1))):
        start = 100 * e + s
        np.testing.assert_array_equal(segments[f"obs{side}"][..., 0], start[:, None] + window)
        np.testing.assert_array_equal(segments[f"actions{side}"][..., 0], -(start[:, None] + window))
        np.testing.assert_array_equal(segments[f"rewards{side}"], (1000 * e + s)[:, None] + window)
        np.testing.assert_array_equal(segments[f"episode{side}"], e)  # where each segment was cut
        np.testing.assert_array_equal(segments[f"start{side}"], s)
    assert segments["obs0"].shape == (500, 10, 1) and segments["rewards1"].shape == (500, 10)
    assert 1 not in set(e0) | set(e1)


def test_planned_labels_counts_the_sessions_that_fit_before_the_last_step():
    sizes = np.array([5, 5, 5, 5, 5])
    # sessions at steps 11, 41, 71 (101 is past the end): 3 x 5
    assert planned_labels(sizes, 11, 30, 100) == 15
    assert planned_labels(sizes, 11, 30, 71) == 15  # a session on the last step still happens
    assert planned_labels(sizes, 11, 30, 70) == 10
    assert planned_labels(sizes, 11, 30, 10_000) == 25  # never more than the schedule's budget
    assert planned_labels(np.array([8, 4, 2, 1]), 11, 30, 100) == 14  # a decaying schedule: its first 3
    assert planned_labels(sizes, 11, 30, 10) == 0  # the run ends before the first session


def test_planned_labels_at_rollout_ends_rounds_each_session_up_to_a_multiple():
    sizes = np.full(10, 100)
    # rollouts of 3000 steps: sessions at 33000 (the first rollout end >= 32000), 66000 (>= 33000 + 32000),
    # 99000; the next, 132000, is past the last step
    assert planned_labels(sizes, 32_000, 32_000, 99_999, granularity=3000) == 300
    assert planned_labels(sizes, 32_000, 32_000, 98_999, granularity=3000) == 200
    assert planned_labels(sizes, 32_000, 32_000, 3_999_999, granularity=16_000) == 1000  # all ten fit


def test_unknown_sampler_raises_and_lists_known_ones():
    with pytest.raises(ValueError) as info:
        select("bald", 1, probs=np.full((2, 3), 0.5))
    message = str(info.value)
    assert "bald" in message
    for name in SAMPLERS:
        assert name in message


def test_unknown_schedule_raises_and_lists_known_ones():
    with pytest.raises(ValueError) as info:
        schedule_sizes("cosine", 100, 10)
    for name in SCHEDULES:
        assert name in str(info.value)


PROBS = np.full((3, 10), 0.5)
FEATURES = np.zeros((10, 4))


@pytest.mark.parametrize(
    "method, kwargs, fragment",
    [
        ("uniform", dict(n_query=11, probs=PROBS), "n_query"),
        ("disagreement", dict(n_query=0, probs=PROBS), "n_query"),
        ("coverage", dict(n_query=-1, features=FEATURES), "n_query"),
        ("disagreement", dict(n_query=1, features=FEATURES), "probs"),
        ("entropy", dict(n_query=1), "probs"),
        ("coverage", dict(n_query=1, probs=PROBS), "features"),
        ("disagreement-coverage", dict(n_query=1, probs=PROBS), "features"),
        ("entropy-coverage", dict(n_query=1, features=FEATURES), "probs"),
        ("disagreement", dict(n_query=1, probs=np.full(10, 0.5)), "probs"),
        ("coverage", dict(n_query=1, features=np.zeros(10)), "features"),
        ("disagreement-coverage", dict(n_query=1, probs=PROBS, features=np.zeros((9, 4))), "candidates"),
        ("coverage", dict(n_query=1, features=FEATURES, labeled_features=np.zeros((2, 3))), "labeled_features"),
        ("coverage", dict(n_query=1, features=FEATURES, labeled_features=np.zeros(4)), "labeled_features"),
        ("disagreement-coverage", dict(n_query=3, probs=PROBS, features=FEATURES, n_inter=2), "n_inter"),
        ("disagreement-coverage", dict(n_query=3, probs=PROBS, features=FEATURES, n_inter=11), "n_inter"),
        ("uniform", dict(n_query=1), "probs or features"),
    ],
)
def test_bad_select_argument_raises_value_error_naming_it(method, kwargs, fragment):
    kwargs = dict(kwargs)
    n_query = kwargs.pop("n_query")
    with pytest.raises(ValueError, match=fragment):
        select(method, n_query, rng=np.random.default_rng(0), **kwargs)


@pytest.mark.parametrize(
    "name, budget, per_session",
    [("uniform", 0, 1), ("decay", 0, 10), ("increase", -5, 1), ("uniform", 10, 0), ("decay", 10, 11), ("increase", 5, 6)],
)
def test_bad_schedule_argument_raises(name, budget, per_session):
    with pytest.raises(ValueError, match="budget|per_session"):
        schedule_sizes(name, budget, per_session)


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        (dict(episode_lengths=[100], segment_len=50, n_pairs=-1), "n_pairs"),
        (dict(episode_lengths=[100], segment_len=0, n_pairs=1), "segment_len"),
        (dict(episode_lengths=[[100, 100]], segment_len=50, n_pairs=1), "episode_lengths"),
    ],
)
def test_bad_random_pairs_argument_raises_naming_it(kwargs, fragment):
    with pytest.raises(ValueError, match=fragment):
        random_pairs(rng=np.random.default_rng(0), **kwargs)


def test_hybrid_default_n_inter_grows_to_n_query():
    # default n_inter = max(n_query, M // 2): asking for 6 of 8 keeps the 6 most uncertain
    probs = np.array([[0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5], [0.9, 0.8, 0.7, 0.6, 0.5, 0.5, 0.5, 0.5]])
    features = np.arange(8, dtype=np.float64)[:, None]
    chosen = select("disagreement-coverage", 6, probs=probs, features=features, rng=np.random.default_rng(0))
    assert set(chosen.tolist()) == set(np.argsort(-probs.std(axis=0), kind="stable")[:6].tolist())
