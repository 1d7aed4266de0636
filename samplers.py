"""Query selection, feedback schedules and candidate pairs of B-Pref (Lee et al., 2021),
paper Section 4.2 and appendix "Sampling schemes". Arrays in, arrays out: no torch, no environment.

    e0, s0, e1, s1 = random_pairs(episode_lengths, segment_len=50, n_pairs=1000, rng=rng)
    # episodes: a list of (obs, actions, rewards) tuples
    candidates = draw_segments(episodes, segment_len=50, n_pairs=1000, rng=rng)
    chosen = select("disagreement", 100, probs=probs)  # probs (E, M): member i's P[sigma1 > sigma0]
    steps = session_steps(first_step=10_001, every=20_000, last_step=500_000)
    sizes = schedule_sizes("decay", budget=1000, per_session=100, steps=steps - 1,
                           total_steps=500_000)
    labels = planned_labels(sizes, first_step=10_001, every=20_000, last_step=500_000)
"""

import numpy as np

SAMPLERS = ("uniform", "disagreement", "entropy", "coverage", "disagreement-coverage",
            "entropy-coverage")
SCHEDULES = ("uniform", "decay", "increase")


def disagreement_scores(probs: np.ndarray) -> np.ndarray:
    """Ensemble disagreement: the members' standard deviation of P[sigma1 > sigma0], shape (M,)."""
    return probs.std(axis=0)


def entropy_scores(probs: np.ndarray) -> np.ndarray:
    """The members' mean binary entropy of P[sigma1 > sigma0], shape (M,).

    The paper ranks by "the entropy of a single preference predictor"; with an ensemble we average
    each member's entropy (as the reference code does), not the entropy of the mean prediction, so
    that entropy measures how undecided each predictor is and disagreement how much they differ."""
    p = np.clip(probs, 1e-12, 1 - 1e-12)
    return (-(p * np.log(p) + (1 - p) * np.log(1 - p))).mean(axis=0)


def k_center_greedy(
    features: np.ndarray,
    n_query: int,
    labeled_features: np.ndarray | None,
    rng: np.random.Generator,
) -> np.ndarray:
    """Greedy k-center (Gonzalez): repeatedly pick the candidate farthest from its nearest center.

    Queries labelled earlier are the initial centers; without them the first pick is random.
    Distances to the centers are kept and updated with the newest center only: O(M * D) a pick."""
    dtype = np.result_type(features, np.float32)  # float32 stays float32 (2x faster), else float64
    # Centering keeps |a|^2 + |b|^2 - 2ab accurate in float32 when all states share a large offset
    offset = np.asarray(features, dtype=np.float64).mean(axis=0)
    features = (features - offset).astype(dtype)
    squared_norms = np.einsum("md,md->m", features, features)
    nearest = np.full(len(features), np.inf, dtype=dtype)
    if labeled_features is not None and len(labeled_features):
        centers = (labeled_features - offset).astype(dtype)
        for start in range(0, len(centers), 1024):  # ||a - b||^2 = |a|^2 + |b|^2 - 2ab, in chunks
            chunk = centers[start : start + 1024]
            chunk_norms = np.einsum("kd,kd->k", chunk, chunk)
            squared = squared_norms[:, None] + chunk_norms[None] - 2 * features @ chunk.T
            nearest = np.minimum(nearest, squared.min(axis=1))
    chosen = np.empty(n_query, dtype=np.int64)
    for i in range(n_query):
        if np.isfinite(nearest).any():
            pick = int(np.argmax(nearest))
        else:
            pick = int(rng.integers(len(features)))
        chosen[i] = pick
        squared = squared_norms + squared_norms[pick] - 2 * features @ features[pick]
        nearest = np.minimum(nearest, squared)
        nearest[chosen[: i + 1]] = -np.inf  # never pick a center twice, even among duplicates
    return chosen


def _top(scores: np.ndarray, n: int) -> np.ndarray:
    """Indices of the n highest scores, highest first (ties: lower index first)."""
    return np.argsort(-scores, kind="stable")[:n]


def select(
    method: str,
    n_query: int,
    *,
    probs: np.ndarray | None = None,
    features: np.ndarray | None = None,
    labeled_features: np.ndarray | None = None,
    n_inter: int | None = None,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Choose `n_query` distinct candidates among M by one of the paper's six SAMPLERS.

    probs: (E, M), each ensemble member's P[sigma1 > sigma0] (uncertainty-based and hybrid methods).
    features: (M, D), both segments' states concatenated (coverage and hybrids, appendix).
    labeled_features: (K, D), queries labelled in earlier sessions: existing k-center centers.
    n_inter: hybrids keep the n_inter most uncertain candidates, then pick centers among them
    (default max(n_query, M // 2)).
    rng: for uniform and the first coverage center (default: unseeded)."""
    if method not in SAMPLERS:
        raise ValueError(f"unknown sampler {method!r}: choose one of {', '.join(SAMPLERS)}")
    rng = np.random.default_rng() if rng is None else rng
    uncertainties = {"disagreement": disagreement_scores, "entropy": entropy_scores}
    uncertainty = uncertainties.get(method.split("-")[0])
    needs_coverage = method.endswith("coverage")
    if uncertainty is not None and probs is None:
        raise ValueError(f"sampler {method!r} needs probs, an (ensemble, candidates) array")
    if needs_coverage and features is None:
        raise ValueError(f"sampler {method!r} needs features, a (candidates, dim) array")
    if probs is not None:
        probs = np.asarray(probs)
        if probs.ndim != 2:
            raise ValueError(f"probs must be 2-D (ensemble, candidates), got shape {probs.shape}")
    if features is not None:
        features = np.asarray(features)
        if features.ndim != 2:
            raise ValueError(f"features must be 2-D (candidates, dim), got shape {features.shape}")
    if probs is not None and features is not None and probs.shape[1] != len(features):
        raise ValueError(f"probs has {probs.shape[1]} candidates but features has {len(features)}")
    if labeled_features is not None:
        labeled_features = np.asarray(labeled_features)
        shape = labeled_features.shape
        if features is None or len(shape) != 2 or shape[1] != features.shape[1]:
            raise ValueError("labeled_features must be 2-D with the feature dimension of features, "
                             f"got shape {shape}")
    if probs is None and features is None:
        raise ValueError("select needs probs or features to know the candidates")
    n_candidates = probs.shape[1] if probs is not None else len(features)
    if not (1 <= n_query <= n_candidates):
        raise ValueError(f"n_query must be in [1, {n_candidates}] (the number of candidates), "
                         f"got {n_query}")

    if method == "uniform":
        return rng.choice(n_candidates, size=n_query, replace=False)
    if method == "coverage":
        return k_center_greedy(features, n_query, labeled_features, rng)
    scores = uncertainty(probs)
    if not needs_coverage:
        return _top(scores, n_query)
    n_inter = max(n_query, n_candidates // 2) if n_inter is None else n_inter
    if not (n_query <= n_inter <= n_candidates):
        raise ValueError(f"n_inter must be in [n_query, candidates] = [{n_query}, {n_candidates}], "
                         f"got {n_inter}")
    most_uncertain = _top(scores, n_inter)
    return most_uncertain[k_center_greedy(features[most_uncertain], n_query, labeled_features, rng)]


def schedule_sizes(
    name: str, budget: int, per_session: int, steps=None, total_steps: int | None = None
) -> np.ndarray:
    """Number of queries of each feedback session (paper Section 4.2), as the reference code's
    schedules (the runs of the paper's Fig. 4): a session after t of T environment steps asks

      uniform:  per_session
      decay:    int(2 * per_session * (T - t) / T)  (the paper's T / (t + T) shape, linear in t)
      increase: int(per_session / 2 * T / (T - t + 1))

    (the reference's reward_batch x frac, with the 2x and 0.5x reward_batch of its walker scripts),
    at least 1 and at most what is left of the budget, the last session taking the rest. `steps`:
    t of each planned session (session_steps); decay and increase need them and total_steps T.
    Uniform spends exactly `budget`; decay and increase spend it when the run has sessions enough,
    else what those sessions ask."""
    if name not in SCHEDULES:
        raise ValueError(f"unknown schedule {name!r}: choose one of {', '.join(SCHEDULES)}")
    if budget < 1 or per_session < 1:
        raise ValueError("budget and per_session must be >= 1, "
                         f"got budget={budget}, per_session={per_session}")
    if per_session > budget:
        raise ValueError(f"per_session ({per_session}) cannot exceed budget ({budget})")
    if name == "uniform":
        rest = [budget % per_session] if budget % per_session else []
        return np.array([per_session] * (budget // per_session) + rest, dtype=np.int64)
    if steps is None or total_steps is None:
        raise ValueError(f"schedule {name!r} needs the steps of the sessions and total_steps")
    sizes, remaining = [], budget
    for t in steps:
        if not 0 <= t < total_steps:
            raise ValueError(f"session steps must be in [0, total_steps={total_steps}), got {t}")
        if name == "decay":
            size = int(2 * per_session * (total_steps - t) / total_steps)
        else:
            size = int(per_session / 2 * total_steps / (total_steps - t + 1))
        sizes.append(min(max(1, size), remaining))
        remaining -= sizes[-1]
        if remaining == 0:
            break
    return np.array(sizes, dtype=np.int64)


def session_steps(first_step: int, every: int, last_step: int, granularity: int = 1) -> np.ndarray:
    """The steps of a run's feedback sessions: first_step, then `every` or more steps after the one
    before, each at the next multiple of `granularity` steps (a rollout; 1: at any step), up to
    last_step."""
    steps, step = [], -(-first_step // granularity) * granularity
    while step <= last_step:
        steps.append(step)
        step = -(-(step + every) // granularity) * granularity
    return np.array(steps, dtype=np.int64)


def planned_labels(
    session_sizes, first_step: int, every: int, last_step: int, granularity: int = 1
) -> int:
    """How many labels a run asks for: the sizes of the sessions that fit (session_steps), while
    the schedule lasts. Assumes a complete episode at the first session (a later one asks fewer)."""
    n_sessions = len(session_steps(first_step, every, last_step, granularity))
    return int(np.sum(session_sizes[:n_sessions]))


def random_pairs(
    episode_lengths, segment_len: int, n_pairs: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Draw candidate pairs of segments uniformly over stored episodes of any lengths.

    Every (episode, start) with 0 <= start <= length - segment_len is one position, the last one
    included; the two sides of a pair are two different positions, uniform over such pairs
    (the reference code missed the last start and could pair a segment with itself).
    Returns (episode0, start0, episode1, start1), indices into `episode_lengths`."""
    lengths = np.asarray(episode_lengths, dtype=np.int64)
    if lengths.ndim != 1:
        raise ValueError(f"episode_lengths must be 1-D, got shape {lengths.shape}")
    if segment_len < 1:
        raise ValueError(f"segment_len must be >= 1, got {segment_len}")
    if n_pairs < 0:
        raise ValueError(f"n_pairs must be >= 0, got {n_pairs}")
    positions_per_episode = np.maximum(lengths - segment_len + 1, 0)
    n_positions = int(positions_per_episode.sum())
    if n_positions < 2:
        raise ValueError(
            f"need two distinct segments of length {segment_len}, but the stored episodes "
            f"(longest {lengths.max(initial=0)} steps) hold {n_positions}"
        )
    first = rng.integers(n_positions, size=n_pairs)
    second = rng.integers(n_positions - 1, size=n_pairs)
    second += second >= first  # uniform over the positions other than `first`
    ends = np.cumsum(positions_per_episode)

    def to_episode_start(flat):
        episode = np.searchsorted(ends, flat, side="right")
        return episode, flat - (ends[episode] - positions_per_episode[episode])

    return (*to_episode_start(first), *to_episode_start(second))


def draw_segments(
    episodes, segment_len: int, n_pairs: int, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """n_pairs candidate pairs (random_pairs) cut from stored episodes, each a tuple whose first
    three entries are per-step arrays (observations, actions, true rewards) of one length:
    {"obs0", "actions0", "rewards0", "obs1", "actions1", "rewards1"}, each of shape
    (n_pairs, segment_len, ...), and where each segment was cut: "episode0"/"episode1" (indices
    into `episodes`) and "start0"/"start1" (its first step there), each (n_pairs,); side 0 is
    sigma0, side 1 sigma1."""
    lengths = [len(episode[0]) for episode in episodes]
    e0, s0, e1, s1 = random_pairs(lengths, segment_len, n_pairs, rng)
    window = np.arange(segment_len)
    pairs = {}
    for side, (es, ss) in enumerate(((e0, s0), (e1, s1))):
        for part, key in enumerate(("obs", "actions", "rewards")):
            segments = [episodes[e][part][s + window] for e, s in zip(es, ss)]
            pairs[f"{key}{side}"] = np.stack(segments)
        pairs[f"episode{side}"] = es
        pairs[f"start{side}"] = ss
    return pairs
