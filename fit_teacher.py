# Which simulated teacher of B-Pref (sim_teacher.py) most likely gave these labels; see
# docs/teacher_fit.md
"""Maximum-likelihood fit of SimTeacher(beta, gamma, eps_mistake, eps_skip, eps_equal) to labels.

    python fit_teacher.py runs/<run>             # a run directory, its labels/ or one .npz
    python fit_teacher.py runs/check --simulate  # simulated labels written there, fitted

The likelihood of Algorithm 1 is a product of three factors, each fitted on its own:
  - skip: a pair is skipped iff max(R0, R1) < delta_skip (undiscounted returns);
  - equal (kept pairs): y = 0.5 iff |R1 - R0| < delta_equal;
  - choice (strict pairs, y = 0 or 1): P(y = 1) = eps + (1 - 2 eps) sigmoid(beta (A1 - A0)),
    with the myopic returns A = sum_t gamma^(H-t) r_t and eps = eps_mistake; with a side bias b
    (SimTeacher's, not in the paper), P(y = 1) = b+ + (1 - |b|) times that.
Each session's thresholds are delta = eps * scale, scale = (H / T) * R_avg, which its label file
saves as threshold_scale; older runs' files lack it, and then one delta per threshold is fitted in
return units and the eps cannot be given.

Intervals are profile-likelihood intervals, not a bootstrap: a bootstrap is unreliable at the
boundaries this problem lives on (beta = inf, eps = 0, gamma = 1) and for a threshold, whose
estimate is an order statistic. Identifiability: beta and eps_mistake trade off (both make labels
disagree with the returns); only pairs whose returns differ a lot separate them, where a stochastic
teacher is sure and only a mistake flips the label. gamma matters only where rewards vary along the
segments. beta is per unit of return: it carries over to the same task only (gamma, eps: any task).
"""

import json
import math
import os
import sys
from dataclasses import dataclass
from typing import Annotated

import numpy as np
import tyro
from scipy.optimize import minimize, minimize_scalar
from scipy.special import expit, log_expit
from scipy.stats import chi2

import sim_teacher
from sim_teacher import SimTeacher

MIN_STRICT = 20  # strict labels (0 or 1) below which beta, gamma and eps_mistake are not estimable
GAMMAS = np.concatenate([1 - np.geomspace(0.99, 1e-4, 39), [1.0]])  # increasing, fine near 1
DENSE_GAMMAS = np.concatenate([1 - np.geomspace(0.99, 1e-4, 2000), [1.0]])  # the rational teacher's
EPSILONS = np.concatenate([[0.0], np.geomspace(1e-3, 0.05, 8, endpoint=False),
                           np.linspace(0.05, 0.5, 19)])
N_BETAS = 48  # grid of beta: 0, N_BETAS values log-spaced over the relevant range, inf
BISECTIONS = 8  # steps locating an end of an interval between two grid values
CHECK_BINS = 10  # equal-count bins of each part of the goodness-of-fit check
CHECK_LEVEL = 0.01  # p-value below which the fitted teacher does not describe the labels
MAX_LAPSE = 0.05  # share of a threshold's decisions that may go against it (a person's slips)
TEACHER = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal", "bias")  # --teacher-*


@dataclass
class Args:
    run_dir: Annotated[str | None, tyro.conf.Positional,
                       tyro.conf.arg(metavar="RUN_DIR", help_behavior_hint="")] = None
    """a run directory, its labels/ directory, or one session_*.npz (pebble.py, prefppo.py)"""
    labels: Annotated[str | None, tyro.conf.arg(metavar="RUN_DIR", help_behavior_hint="")] = None
    """the same, as a flag (one of the two)"""
    level: float = 0.95
    """confidence level of the profile-likelihood intervals"""
    simulate: bool = False
    """if toggled, first write a simulated run to RUN_DIR (the --teacher-* below label it)"""
    pairs: int = 1000
    """--simulate: the number of labelled pairs"""
    sessions: int = 10
    """--simulate: the number of feedback sessions (each its own R_avg, so its own thresholds)"""
    seed: int = 0
    """--simulate: seed of the segments and of the teacher"""
    teacher_beta: float = 1.0
    """--simulate: the teacher's rationality beta (inf = rational)"""
    teacher_gamma: float = 0.95
    """--simulate: the teacher's myopic discount gamma in (0, 1]"""
    teacher_eps_mistake: float = 0.1
    """--simulate: the teacher's mistake probability"""
    teacher_eps_skip: float = 0.1
    """--simulate: the teacher's adaptive skip fraction"""
    teacher_eps_equal: float = 0.05
    """--simulate: the teacher's adaptive equal fraction"""
    teacher_bias: float = 0.0
    """--simulate: the teacher's side bias (> 0: right, < 0: left, whatever the segments)"""


# -------------------------------------------------------------------------------------------------
# Label files
# -------------------------------------------------------------------------------------------------


def load_labels(path: str) -> dict:
    """Every session's rewards0, rewards1 (N, H), y, keep (N,) and threshold_scale (N,: each pair's
    session scale; None when a file lacks it), read by sim_teacher.load_labels (ValueError for
    missing or malformed files)."""
    sessions = sim_teacher.load_labels(path)
    data = {key: np.concatenate([s[key] for s in sessions]) for key in sim_teacher.LABEL_KEYS}
    scales = [s["threshold_scale"] for s in sessions]
    data["threshold_scale"] = None if None in scales else np.concatenate(
        [np.full(len(s["y"]), s["threshold_scale"]) for s in sessions])
    return data


def simulate(directory: str, teacher: SimTeacher, pairs: int = 1000, sessions: int = 10,
             segment_len: int = 50, episode_len: int = 1000, seed: int = 0) -> None:
    """A simulated run in `directory`: config.json naming the teacher, and labels/session_*.npz of
    synthetic pairs that `teacher` labels. Per-step rewards lie in [0, 1] like DMC's; each pair has
    its own scale (log-uniform over 1.5 decades: near-ties and clear pairs both occur), each segment
    a level and a linear trend (so the myopic discount matters), and the levels rise from session to
    session as a learning policy's. R_avg = the session's mean segment return * T / H."""
    if sim_teacher.label_files(directory):
        raise ValueError(f"{directory!r} already holds label files: simulate into a new directory")
    rng = np.random.default_rng([seed, 23])  # a stream apart from a teacher's own default_rng(seed)
    os.makedirs(os.path.join(directory, "labels"), exist_ok=True)
    config = {"teacher": "oracle", "simulated": True, "segment_len": segment_len}
    config |= {f"teacher_{name}": getattr(teacher, name) for name in TEACHER}
    with open(os.path.join(directory, "config.json"), "w") as f:
        json.dump(config, f, indent=2)
    t = np.linspace(-0.5, 0.5, segment_len)
    for session, n in enumerate(np.diff(np.linspace(0, pairs, sessions + 1).round().astype(int))):
        progress = 0.4 + 0.6 * session / max(sessions - 1, 1)
        scale = progress * np.exp(rng.uniform(math.log(0.03), 0, (n, 1, 1)))
        level, trend = rng.uniform(0, 1, (n, 2, 1)), rng.uniform(-1.5, 1.5, (n, 2, 1))
        noise = 0.1 * rng.standard_normal((n, 2, segment_len))
        rewards = (scale * np.clip(level + trend * t + noise, 0, 1)).astype(np.float32)  # as saved
        mean_return = float(rewards.sum(2).mean()) * episode_len / segment_len
        teacher.set_thresholds(mean_return, segment_len, episode_len)
        y, keep = teacher.label(rewards[:, 0], rewards[:, 1])
        sim_teacher.save_labels(directory, session, step=session, y=y, keep=keep,
                                rewards0=rewards[:, 0], rewards1=rewards[:, 1],
                                threshold_scale=segment_len / episode_len * mean_return)


# -------------------------------------------------------------------------------------------------
# The choice: beta, gamma, eps_mistake
# -------------------------------------------------------------------------------------------------


def advantages(diff: np.ndarray, gammas: np.ndarray) -> np.ndarray:
    """Myopic A1 - A0 for each gamma, (G, N), from the per-step differences r1 - r0 (N, H)."""
    weights = gammas[:, None] ** np.arange(diff.shape[1] - 1, -1, -1)[None]  # the last weighs 1
    return weights @ diff.T


def rational_loglik(wrong, ties, n: int, eps=None):
    """log P(labels) of a rational teacher (beta = inf): the better segment, flipped with
    probability eps (an exact tie is a coin), from the counts of labels against the returns and of
    exact ties. eps None: the maximum over eps (eps = wrong / decided). Arrays give arrays."""
    decided = n - ties
    if eps is None:  # the MLE within SimTeacher's range [0, 0.5]
        eps = np.minimum(wrong / np.maximum(decided, 1), 0.5)
    with np.errstate(divide="ignore", invalid="ignore"):  # 0 log 0 = 0
        return (np.where(wrong > 0, wrong * np.log(eps), 0.0) + ties * math.log(0.5)
                + np.where(decided > wrong, (decided - wrong) * np.log1p(-eps), 0.0))


def choice_loglik(beta: float, gamma: float, eps: float, diff: np.ndarray, sign: np.ndarray,
                  gradient: bool = False):
    """log P(labels) of the strict pairs (sign = +1 where the second segment was preferred, else
    -1); gradient (finite beta): also its derivatives in (log beta, gamma, eps)."""
    agree = sign * advantages(diff, np.array([gamma]))[0]
    if math.isinf(beta):
        return float(rational_loglik((agree < 0).sum(), (agree == 0).sum(), len(agree), eps))
    z = beta * agree
    log_q = log_expit(z)  # log P(label | no mistake)
    with np.errstate(divide="ignore"):  # eps = 0 or 0.5
        log_p = np.logaddexp(np.log(eps), np.log1p(-2 * eps) + log_q)  # a mistake, or none
    if not gradient:
        return float(log_p.sum())
    with np.errstate(divide="ignore"):  # d log p / dz = (1 - 2 eps) q (1 - q) / p, finite as q -> 0
        dz = np.exp(np.log1p(-2 * eps) + log_q - log_p + log_expit(-z))
    powers = np.arange(diff.shape[1] - 1, -1, -1)
    dgamma = diff @ (powers * gamma ** np.maximum(powers - 1, 0))  # d A / d gamma
    grad = [(dz * z).sum(), (dz * beta * sign * dgamma).sum(),
            ((1 - 2 * np.exp(log_q)) * np.exp(-np.maximum(log_p, -700))).sum()]
    return float(log_p.sum()), np.array(grad)


def choice_grid(diff: np.ndarray, sign: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """log-likelihood on the grid betas x GAMMAS x EPSILONS (betas may hold inf)."""
    loglik = np.empty((len(betas), len(GAMMAS), len(EPSILONS)))
    finite = np.isfinite(betas)
    for g, agree in enumerate(sign * advantages(diff, GAMMAS)):
        log_q = np.empty((len(betas), len(agree)))  # log P(label | no mistake)
        log_q[finite] = log_expit(betas[finite, None] * agree[None])
        with np.errstate(divide="ignore"):  # beta = inf: log 0 for a label against the returns
            log_q[~finite] = np.log(0.5 * (1 + np.sign(agree)))
        q = np.exp(log_q)
        loglik[:, g, 0] = log_q.sum(1)
        for e, eps in enumerate(EPSILONS[1:], 1):
            loglik[:, g, e] = np.log(eps + (1 - 2 * eps) * q).sum(1)
    return loglik


def fit_choice(diff: np.ndarray, sign: np.ndarray, level: float) -> dict:
    """MLE of beta, gamma, eps_mistake from the strict pairs, with profile-likelihood intervals.

    theta = (log beta, gamma, eps). A grid finds the global maximum and a local optimiser polishes
    it (TNC with the exact gradient; L-BFGS-B calls LAPACK, whose threads crawl on a busy machine).
    The rational teacher (beta = inf) is solved exactly on a dense grid of gamma and wins ties:
    labels that never contradict the returns give beta = inf and eps = 0. An interval holds the
    values whose profile log-likelihood (the maximum over the other two parameters, found the same
    way) is within chi2_1(level) / 2 of the maximum; each end is walked outward from the last grid
    value known to be inside (the grid's maximum is a lower bound of the profile), then bisected."""
    n = len(sign)
    dense = sign * advantages(diff, DENSE_GAMMAS)
    wrong, ties = (dense < 0).sum(1), (dense == 0).sum(1)
    magnitude = np.median(np.abs(advantages(diff, GAMMAS[[0, -1]])), axis=1)  # of A, at both ends
    magnitude = np.maximum(magnitude, 1e-12 * max(magnitude.max(), 1e-12))
    betas = np.concatenate([[0.0], np.geomspace(1e-2 / magnitude.max(), 1e3 / magnitude.min(),
                                                N_BETAS), [math.inf]])
    grid = choice_grid(diff, sign, betas)
    with np.errstate(divide="ignore"):
        axes = [np.log(betas), GAMMAS, EPSILONS]
    bounds = [(axes[0][1] - 2, axes[0][-2] + 2), (GAMMAS[0], 1.0), (0.0, 0.5)]

    def maximise(fixed: int | None, value: float, starts: list) -> tuple[float, list]:
        """The largest log-likelihood, and its theta, with theta[fixed] = value (None: all free)."""
        best = (-math.inf, None)
        if fixed != 0 or value < math.inf:  # finite beta: the optimiser over the free parameters
            free = [i for i in range(3) if i != fixed]
            for start in starts:
                theta = list(start)
                if fixed is not None:
                    theta[fixed] = value

                def full(x):  # theta with the free parameters set to x
                    return [float(x[free.index(i)]) if i in free else theta[i] for i in range(3)]

                def objective(x):
                    t = full(x)
                    loglik, grad = choice_loglik(math.exp(t[0]), t[1], t[2], diff, sign, True)
                    return -loglik, -grad[free]
                result = minimize(objective, [min(max(theta[i], bounds[i][0]), bounds[i][1])
                                              for i in free],
                                  jac=True, method="TNC", bounds=[bounds[i] for i in free])
                if -result.fun > best[0]:
                    best = (-float(result.fun), full(result.x))
        if fixed is None or (fixed == 0 and value == math.inf):  # beta = inf, gamma and eps free
            loglik = rational_loglik(wrong, ties, n)
            tied = np.flatnonzero(loglik >= loglik.max() - 1e-9)  # an interval, when deterministic
            i = tied[-1] if DENSE_GAMMAS[tied[-1]] == 1.0 else tied[len(tied) // 2]  # 1, or middle
            eps = min(wrong[i] / max(n - ties[i], 1), 0.5)
            rational = (float(loglik[i]), [math.inf, float(DENSE_GAMMAS[i]), eps])
        elif fixed == 1:  # beta = inf at this gamma
            agree = sign * advantages(diff, np.array([value]))[0]
            w, t = (agree < 0).sum(), (agree == 0).sum()
            eps = min(w / max(n - t, 1), 0.5)
            rational = (float(rational_loglik(w, t, n)), [math.inf, value, eps])
        elif fixed == 2:  # beta = inf at this eps
            loglik = rational_loglik(wrong, ties, n, value)
            i = loglik.argmax()
            rational = (float(loglik[i]), [math.inf, float(DENSE_GAMMAS[i]), value])
        else:
            rational = (-math.inf, None)
        return rational if rational[0] >= best[0] - 1e-9 else best  # ties: the simpler, rational

    def grid_start(p: int, value: float) -> list:
        """The grid's best theta on the grid plane nearest to theta[p] = value."""
        finite = np.flatnonzero(np.isfinite(axes[p]))
        j = finite[np.argmin(np.abs(axes[p][finite] - value))] if math.isfinite(value) else (
            np.argmax(axes[p]) if value > 0 else np.argmin(axes[p]))
        plane = np.take(grid, j, axis=p)
        index = list(np.unravel_index(np.argmax(plane), plane.shape))
        index.insert(p, j)
        return [float(axes[i][index[i]]) for i in range(3)]

    top = np.unravel_index(np.argmax(grid[:-1]), grid[:-1].shape)  # the grid's best finite beta
    loglik, mle = maximise(None, 0.0, [[float(axes[i][top[i]]) for i in range(3)]])
    cut = loglik - chi2.ppf(level, 1) / 2

    def inside(p: int, value: float) -> bool:
        return maximise(p, value, [grid_start(p, value), mle])[0] >= cut

    ci = {}
    for p, name in enumerate(("beta", "gamma", "eps_mistake")):
        lower = grid.max(axis=tuple(i for i in range(3) if i != p))  # <= the profile at each value
        ends = []
        for direction in (-1, 1):
            beyond = list(np.flatnonzero(axes[p] > mle[p] if direction > 0 else axes[p] < mle[p]))
            beyond = beyond[::direction]  # outward from the estimate
            known = [i for i in beyond if lower[i] >= cut]
            last = axes[p][known[-1]] if known else mle[p]
            for value in axes[p][beyond[beyond.index(known[-1]) + 1:] if known else beyond]:
                if inside(p, value):
                    last = value
                    continue
                if math.isfinite(value) and math.isfinite(last):
                    within, outside = last, value
                    for _ in range(BISECTIONS):
                        middle = (within + outside) / 2
                        if inside(p, middle):
                            within = middle
                        else:
                            outside = middle
                    last = within
                break
            ends.append(float(last))
        ci[name] = tuple(ends)
    ci["beta"] = tuple(math.exp(v) for v in ci["beta"])
    # The rational teacher's likelihood over gamma is a step function of the count of labels against
    # the returns: its ratio is no chi2 (one label more against them costs log((1 - eps) / eps), 2.2
    # at eps = 0.1, above the cut on its own). Gamma's interval holds, besides, the hull of every
    # gamma whose count is at most one more than the fewest within the cut (as a threshold's lapse)
    within = rational_loglik(wrong, ties, n) >= cut
    inside = DENSE_GAMMAS[wrong <= wrong[within].min() + 1] if within.any() else ()
    if len(inside):
        ci["gamma"] = (min(ci["gamma"][0], float(inside.min())),
                       max(ci["gamma"][1], float(inside.max())))
    return {"loglik": loglik, "beta": math.exp(mle[0]), "gamma": mle[1], "eps_mistake": mle[2],
            "ci": ci}


# -------------------------------------------------------------------------------------------------
# The thresholds: eps_skip, eps_equal (or delta_skip, delta_equal in return units)
# -------------------------------------------------------------------------------------------------


def fit_threshold(values: np.ndarray, scales: np.ndarray, hits: np.ndarray, upper: float,
                  level: float) -> dict:
    """A deterministic threshold rule: a hit (skip, equal) iff value < t * scale, t in [0, upper];
    t = 0 is the rule switched off (SimTeacher with eps_skip = 0 never skips).

    Its likelihood is a step function: 1 on the interval of thresholds that reproduce every
    decision, 0 elsewhere. That interval is the set of MLEs, and an exact confidence set too (the
    true threshold lies in it with probability 1). A person is no threshold, so the rule gets a
    lapse rate lambda <= 1/2 (a decision goes the other way with probability lambda): with lambda at
    its MLE, k disagreements of n have the log-likelihood k log(k/n) + (n - k) log(1 - k/n), largest
    at the fewest disagreements, and the interval is the thresholds within chi2_1(level) / 2 of the
    best (with no disagreement, the interval above: one disagreement costs log n + 1 > 1.92). The
    estimate is 0 when the rule switched off is among the best (the simplest teacher: no hit was
    seen), else the middle of the best thresholds (the posterior mean for a flat prior on them)."""
    n = len(values)
    breaks = np.unique(values[scales != 0] / scales[scales != 0])  # where a pair's prediction flips
    edges = np.concatenate([[0.0], breaks[(breaks > 0) & (breaks < upper)], [upper]])
    spans = np.concatenate([[[0.0, 0.0]], np.stack([edges[:-1], edges[1:]], 1)])  # 0, pieces
    errors = np.array([hits.sum()] + [(hits != (values < t * scales)).sum()
                                      for t in spans[1:].mean(1)])
    lapse = np.minimum(errors / n, 0.5)
    with np.errstate(divide="ignore", invalid="ignore"):
        loglik = np.where(errors > 0, errors * np.log(lapse), 0) + (n - errors) * np.log1p(-lapse)
    best = errors == errors.min()
    within = loglik >= loglik[best][0] - chi2.ppf(level, 1) / 2
    estimate = 0.0 if best[0] else float(spans[best, 0].min() + spans[best, 1].max()) / 2
    return {"estimate": estimate, "disagreements": int(errors.min()),
            "ci": (float(spans[within, 0].min()), float(spans[within, 1].max()))}


# -------------------------------------------------------------------------------------------------
# A side bias (SimTeacher's bias, not in the paper)
# -------------------------------------------------------------------------------------------------


def lapses(eps: float, bias: float) -> tuple[float, float, float]:
    """(l0, l1, k): P(y) = l_y + k P(y | no lapse) with a mistake eps and a side bias b: a strict
    answer is side sign(b) with probability |b|, else Algorithm 1's (mistakes included)."""
    l1 = max(bias, 0.0) + (1 - abs(bias)) * eps
    l0 = max(-bias, 0.0) + (1 - abs(bias)) * eps
    return l0, l1, (1 - abs(bias)) * (1 - 2 * eps)


def biased_loglik(theta, bias: float, diff: np.ndarray, sign: np.ndarray):
    """log P(strict labels) at (log beta, gamma, eps) (finite beta) and a fixed bias, and its
    gradient in (log beta, gamma, eps)."""
    beta, gamma, eps = math.exp(theta[0]), theta[1], theta[2]
    l0, l1, k = lapses(eps, bias)
    agree = sign * advantages(diff, np.array([gamma]))[0]
    q = expit(beta * agree)  # P(the label | no lapse)
    lapse = np.where(sign > 0, l1, l0)
    p = np.maximum(lapse + k * q, 1e-300)
    slope = k * q * (1 - q) / p  # d log p / d (beta * agree)
    powers = np.arange(diff.shape[1] - 1, -1, -1)
    dgamma = sign * (diff @ (powers * gamma ** np.maximum(powers - 1, 0)))
    deps = (1 - abs(bias)) * (1 - 2 * q) / p
    grad = np.array([(slope * beta * agree).sum(), (slope * beta * dgamma).sum(), deps.sum()])
    return float(np.log(p).sum()), grad


def side_counts(agree: np.ndarray, sign: np.ndarray) -> dict:
    """side (+1: the second segment preferred, -1: the first) -> the counts of its labels with,
    against and tied with the returns, (G,) each; agree (G, N)."""
    return {side: [((agree > 0) & (sign == side)).sum(1), ((agree < 0) & (sign == side)).sum(1),
                   ((agree == 0) & (sign == side)).sum(1)] for side in (1.0, -1.0)}


def rational_biased(bias: float, counts: dict) -> tuple[float, float, float]:
    """beta = inf: the best (log-likelihood, gamma, eps) over DENSE_GAMMAS and a grid of eps, from
    the counts of labels with, against and tied with the returns on each side (side_counts)."""
    eps = np.linspace(0.0, 0.5, 201)
    l0, l1, k = (np.array(v) for v in zip(*(lapses(float(e), bias) for e in eps)))
    # P(a label) at each eps, (E, 6), and the number of such labels at each gamma, (6, G): with,
    # against and tied with the returns, on each side
    p = np.stack([lapse + k * share for lapse in (l1, l0) for share in (1.0, 0.0, 0.5)], 1)
    n = np.stack([count for side in (1.0, -1.0) for count in counts[side]]).astype(float)
    with np.errstate(divide="ignore"):
        loglik = np.einsum("ek,kg->eg", np.where(p > 0, np.log(p), 0.0), n)
    loglik[(p == 0) @ (n > 0)] = -np.inf  # a label of probability 0 (0 log 0 = 0 otherwise)
    e, g = np.unravel_index(np.argmax(loglik), loglik.shape)
    return float(loglik[e, g]), float(DENSE_GAMMAS[g]), float(eps[e])


def fit_bias(diff: np.ndarray, sign: np.ndarray, choice: dict, level: float) -> dict:
    """The side bias's MLE and profile-likelihood interval: at each b of a grid (walked outward
    from 0, each fit started from its neighbour's), beta, gamma and eps are fitted again (a local
    optimiser, and the rational teacher exactly); each end of the interval is then bisected. The
    bias-free fit is the profile at b = 0."""
    counts = side_counts(sign * advantages(diff, DENSE_GAMMAS), sign)  # the same at every b
    bounds = [(-30.0, 30.0), (GAMMAS[0], 1.0), (0.0, 0.5)]
    base = [math.log(min(choice["beta"], 1e12)), choice["gamma"], choice["eps_mistake"]]

    def profile(bias: float, start: list) -> tuple[float, list]:
        result = minimize(lambda x: tuple(-v for v in biased_loglik(x, bias, diff, sign)),
                          [min(max(v, lo), hi) for v, (lo, hi) in zip(start, bounds)], jac=True,
                          method="TNC", bounds=bounds)
        best = (-float(result.fun), [float(v) for v in result.x])
        loglik, gamma, eps = rational_biased(bias, counts)
        return best if best[0] > loglik else (loglik, [math.inf, gamma, eps])

    at = {0.0: profile(0.0, base)}
    cut_drop = chi2.ppf(level, 1) / 2
    for direction in (1, -1):
        previous = at[0.0]
        for bias in direction * np.arange(0.05, 0.951, 0.05):
            start = previous[1] if math.isfinite(previous[1][0]) else base
            previous = at[float(bias)] = profile(float(bias), start)
            if previous[0] < max(v[0] for v in at.values()) - cut_drop - 5:
                break  # far below the best: the interval ends before
    grid = sorted(at)
    best = max(grid, key=lambda b: at[b][0])
    refined = minimize_scalar(lambda b: -profile(b, at[best][1] if math.isfinite(at[best][1][0])
                                                 else base)[0],
                              bounds=(max(best - 0.05, -1.0), min(best + 0.05, 1.0)),
                              method="bounded", options={"xatol": 1e-3})
    if -refined.fun > at[best][0]:
        best = float(refined.x)
        at[best] = profile(best, base)
        grid = sorted(at)
    cut = at[best][0] - cut_drop
    ends = []
    for direction in (-1, 1):
        inside, outside = best, None
        for b in (grid[grid.index(best)::-1] if direction < 0 else grid[grid.index(best):]):
            if at[b][0] < cut:
                outside = b
                break
            inside = b
        start = at[inside][1]
        for _ in range(BISECTIONS if outside is not None else 0):
            middle = (inside + outside) / 2
            loglik, theta = profile(middle, start if math.isfinite(start[0]) else base)
            if loglik >= cut:
                inside, start = middle, theta
            else:
                outside = middle
        ends.append(float(inside))
    theta = at[best][1]
    return {"bias": float(best), "ci": tuple(ends), "loglik": at[best][0],
            "beta": math.exp(theta[0]) if math.isfinite(theta[0]) else math.inf, "gamma": theta[1],
            "eps_mistake": theta[2]}


# -------------------------------------------------------------------------------------------------
# Goodness of fit
# -------------------------------------------------------------------------------------------------


def g_test(hits: np.ndarray, predicted: np.ndarray, order: np.ndarray,
           bins: int = CHECK_BINS) -> dict:
    """Observed against predicted share of hits in `bins` equal-count bins of `order`: the G
    statistic over the bins (the likelihood ratio against each bin's own share) and its p-value
    from chi2 with bins - 2 degrees of freedom, as Hosmer and Lemeshow's test."""
    groups = np.array_split(np.argsort(order, kind="stable"), min(bins, len(hits)))
    rows, statistic = [], 0.0
    for group in groups:
        n, observed = len(group), float(hits[group].sum())
        expected = float(np.clip(predicted[group].sum(), 1e-9, n - 1e-9))
        for o, e in ((observed, expected), (n - observed, n - expected)):
            statistic += 2 * o * math.log(o / e) if o > 0 else 0.0
        rows.append({"low": float(order[group].min()), "high": float(order[group].max()), "n": n,
                     "observed": observed / n, "predicted": expected / n})
    p_value = float(chi2.sf(statistic, max(len(groups) - 2, 1)))
    return {"bins": rows, "statistic": statistic, "p_value": p_value}


def check_fit(result: dict, diff: np.ndarray, sign: np.ndarray) -> dict:
    """Does the fitted choice describe the strict labels? The G test of the share of "right"
    (y = 1) in bins of the fitted myopic return difference A1 - A0, and how it fails: `lean`, the
    side whose share is above its prediction in 8 or more of the bins (a side bias), or None."""
    advantage = advantages(diff, np.array([result["gamma"]]))[0]
    if math.isinf(result["beta"]):
        q = 0.5 * (1 + np.sign(advantage))
    else:
        q = expit(result["beta"] * advantage)
    l0, l1, k = lapses(result["eps_mistake"], result.get("bias", 0.0))
    check = g_test(sign > 0, l1 + k * q, advantage)
    below = sum(row["observed"] < row["predicted"] for row in check["bins"])
    above = len(check["bins"]) - below
    lean = "left (0)" if below >= 0.8 * len(check["bins"]) else (
        "right (1)" if above >= 0.8 * len(check["bins"]) else None)
    return check | {"lean": lean, "lean_bins": max(below, above)}


def check_threshold(values: np.ndarray, scales: np.ndarray, hits: np.ndarray, part: dict) -> dict:
    """Does the fitted threshold rule (fit_threshold's `part`) describe the decisions? The G test
    of the share of hits in bins of value / scale (the threshold's unit) against the rule with its
    lapse rate (lapses at random, whatever the value); the lapse rate, which the fitted teacher
    (no lapses) should not need beyond slips; the hits given and those the fitted teacher makes."""
    lapse = min(part["disagreements"] / len(hits), 0.5)
    rule = values < part["estimate"] * scales
    order = np.divide(values, scales, out=np.full(len(values), np.inf), where=scales > 0)
    return g_test(hits, np.where(rule, 1 - lapse, lapse), order) | {
        "lapse": lapse, "n": len(hits), "given": int(hits.sum()), "fitted": int(rule.sum())}


def verdict(result: dict, level: float) -> str:
    """The goodness-of-fit check in words: each part that does not fit and how; and a side bias
    whose interval (at `level`) excludes 0."""
    check = result["check"]
    misfits = []
    choice = check["choice"]
    if choice["p_value"] < CHECK_LEVEL and choice["lean"]:
        misfits.append(f"the strict answers lean {choice['lean']} in {choice['lean_bins']} of "
                       f"{len(choice['bins'])} bins, whatever the segments")
    elif choice["p_value"] < CHECK_LEVEL:
        misfits.append("the share of \"right\" follows the return difference otherwise than any "
                       "B-Pref teacher's")
    unit = " / scale" if "eps_equal" in result["ci"] else ""
    for name, value in (("equal", "|R1 - R0|"), ("skip", "max(R0, R1)")):
        part = check[name]
        why = []
        if part["p_value"] < CHECK_LEVEL:
            why.append(f"follow no one threshold of {value}{unit}, even with random lapses")
        if part["lapse"] > MAX_LAPSE:
            why.append(f"go against the fitted one in {part['lapse']:.0%} of the {part['n']} "
                       f"decisions (more than {MAX_LAPSE:.0%}: slips)")
        if why:
            answers = "\"equal\" answers" if name == "equal" else "skips"
            says = "says \"equal\" on" if name == "equal" else "skips"
            misfits.append(f"the {answers} " + " and ".join(why) + f" ({part['given']} given; "
                           f"the fitted teacher {says} {part['fitted']} of these pairs)")
    if misfits:
        text = "the fitted teacher does NOT describe these labels: " + "; ".join(misfits)
    else:
        text = ("the fitted teacher describes these labels: no bin's share of \"right\", of "
                "\"equal\" or of skips is further from its prediction than chance allows")
    if result["bias"]:
        low, high = result["ci"]["bias"]
        side = "right (1)" if result["bias"] > 0 else "left (0)"
        text += (f". The answers lean {side} whatever the segments: the side bias's interval "
                 f"[{low:.4g}, {high:.4g}] excludes 0, as it does by chance in {1 - level:.0%} of "
                 "the fits of a teacher without a lean (no B-Pref teacher leans; below, the flags "
                 "of the teacher with the bias and of the fit without it)")
    return text


# -------------------------------------------------------------------------------------------------
# The fit
# -------------------------------------------------------------------------------------------------


def fit(rewards0, rewards1, y, keep, threshold_scale=None, level: float = 0.95) -> dict:
    """The SimTeacher that most likely gave the labels. rewards0, rewards1 (N, H): both segments'
    true per-step rewards; y (N,): 0, 1, 0.5 (equal), NaN where skipped; keep (N,): False where
    skipped; threshold_scale: None, a number or (N,): each pair's session (H / T) * R_avg.

    Returns the SimTeacher fields beta, gamma, eps_mistake, eps_skip, eps_equal, bias (an eps is
    None where the scale is missing and the teacher skipped / said equal: then delta_skip,
    delta_equal hold the thresholds in return units), ci (name -> (low, high) at `level`), the
    counts, loglik (of the choice), the threshold rules' disagreements (pairs no single threshold
    explains), check (the goodness of fit of its parts choice, equal, skip, and a verdict) and,
    with a bias, without_bias (beta, gamma, eps_mistake and their ci fitted without it)."""
    rewards0, rewards1 = np.asarray(rewards0, np.float64), np.asarray(rewards1, np.float64)
    y, keep = np.asarray(y, np.float64), np.asarray(keep)
    if rewards0.ndim != 2 or rewards0.shape != rewards1.shape:
        raise ValueError(f"rewards0 and rewards1 must be (N, H) arrays of one shape, got "
                         f"{rewards0.shape} and {rewards1.shape}")
    n = len(rewards0)
    if y.shape != (n,) or keep.shape != (n,):
        raise ValueError(f"y and keep must have shape ({n},), got {y.shape} and {keep.shape}")
    if keep.dtype != bool and not np.isin(keep, [0, 1]).all():
        raise ValueError("keep must hold booleans")
    keep = keep.astype(bool)
    if not (np.isfinite(rewards0).all() and np.isfinite(rewards1).all()):
        raise ValueError("rewards must be finite")
    if not np.isin(y[keep], [0.0, 0.5, 1.0]).all():
        raise ValueError("y must be 0, 0.5 or 1 where keep is True")
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")
    strict = keep & (y != 0.5)
    if strict.sum() < MIN_STRICT:
        raise ValueError(f"{strict.sum()} strict labels (0 or 1): the fit needs {MIN_STRICT}")
    if len(np.unique(y[strict])) == 1:
        side = "right (1)" if y[strict][0] == 1 else "left (0)"
        raise ValueError(f"all {strict.sum()} strict labels say {side}: a teacher who answers one "
                         "side whatever the segments is no B-Pref teacher, and the fit needs both "
                         "answers")
    margin = np.where(y[strict] == 1.0, 1.0, -1.0) * (rewards1 - rewards0)[strict].sum(1)
    if (margin < 0).sum() > (margin > 0).sum():
        raise ValueError(f"{(margin < 0).sum()} of {(margin != 0).sum()} strict labels run against "
                         "the returns: the sides may be swapped (left for right); a B-Pref "
                         "teacher's mistakes are at most half")
    if threshold_scale is not None:
        threshold_scale = np.broadcast_to(np.asarray(threshold_scale, np.float64), (n,))
        if not np.isfinite(threshold_scale).all():
            raise ValueError("threshold_scale must be finite")

    diff, sign = (rewards1 - rewards0)[strict], np.where(y[strict] == 1.0, 1.0, -1.0)
    result = fit_choice(diff, sign, level)
    # gamma whose interval is its whole range: the labels do not tell; 1 is the simplest teacher
    low, high = result["ci"]["gamma"]
    result["gamma_unknown"] = low <= GAMMAS[0] and high >= 1
    if result["gamma_unknown"]:
        result["gamma"] = 1.0
    # The side bias: 0 (the simplest teacher) when its interval holds 0, else its estimate, with
    # beta, gamma and eps fitted again with it (intervals not given); the fit without it is kept
    biased = fit_bias(diff, sign, result, level)
    result["ci"]["bias"] = biased["ci"]
    result["bias"] = 0.0
    if not biased["ci"][0] <= 0 <= biased["ci"][1]:
        choice = ("beta", "gamma", "eps_mistake")
        result["without_bias"] = {name: result[name] for name in choice} | {
            "ci": {name: result["ci"][name] for name in choice}}
        result |= {name: biased[name] for name in ("bias",) + choice}
        result["ci"] |= {name: (None, None) for name in choice}
    # The thresholds in eps units (each session's delta = eps * its scale) when every session has
    # its scale (eps <= 1, as SimTeacher's), else one delta for all sessions in return units.
    returns0, returns1 = rewards0.sum(1), rewards1.sum(1)
    scaled = threshold_scale is not None
    scales = threshold_scale if scaled else np.ones(n)
    upper = 1.0 if scaled else 2 * float(np.abs(np.concatenate([returns0, returns1])).max()) + 1
    decisions = {"skip": (np.maximum(returns0, returns1), scales, ~keep),
                 "equal": (np.abs(returns1 - returns0)[keep], np.abs(scales[keep]),
                           y[keep] == 0.5)}  # (values, scales, hits) of each threshold rule
    result["check"] = {"choice": check_fit(result, diff, sign)}
    for name, (values, rule_scales, hits) in decisions.items():
        part = fit_threshold(values, rule_scales, hits, upper, level)
        known = scaled or part["estimate"] == 0  # a rule switched off is eps = 0 at any scale
        result[f"eps_{name}"] = part["estimate"] if known else None
        result[f"delta_{name}"] = None if scaled else part["estimate"]
        result["ci"][f"eps_{name}" if scaled else f"delta_{name}"] = part["ci"]
        result[f"{name}_disagreements"] = part["disagreements"]
        result["check"][name] = check_threshold(values, rule_scales, hits, part)
    result["check"]["verdict"] = verdict(result, level)
    nonpositive = 0 if threshold_scale is None else int((threshold_scale <= 0).sum())
    return result | {"n_pairs": n, "n_strict": int(strict.sum()), "n_skipped": int((~keep).sum()),
                     "n_equal": int((keep & (y == 0.5)).sum()), "level": level,
                     "nonpositive_scales": nonpositive}


def teacher_overrides(result: dict) -> dict:
    """The fit's make_teacher("oracle", **overrides) fields, rounded as --teacher-* prints them."""
    return {name: float(f"{result[name]:.4g}") for name in TEACHER
            if result[name] is not None and not (name == "bias" and result[name] == 0)}


def teacher_flags(result: dict) -> str:
    """The pebble.py / prefppo.py flags of the fitted teacher."""
    return " ".join(["--teacher oracle"] + [f"--teacher-{name.replace('_', '-')} {value:.4g}"
                                            for name, value in teacher_overrides(result).items()])


def bin_rows(bins: list, share: str) -> list:
    """A check's bins under a header: from .. to, pairs, observed and predicted share."""
    return [f"  {'from .. to':^22} {'pairs':>6}  {'share ' + share:>11}  {'predicted':>9}"] + [
        f"  {row['low']:>9.3g} .. {row['high']:<9.3g} {row['n']:>6}  {row['observed']:>11.2f}  "
        f"{row['predicted']:>9.2f}" for row in bins]


def report(result: dict, truth: dict | None = None) -> str:
    """The table (parameter, estimate, interval, and the run's teacher when known) and the flags."""
    def number(value):
        return "-" if value is None else f"{value:.4g}"

    names = ["beta", "gamma", "eps_mistake"] + [
        f"eps_{k}" if f"eps_{k}" in result["ci"] else f"delta_{k}" for k in ("skip", "equal")]
    rows = [("parameter", "estimate", f"{100 * result['level']:g}% CI (profile likelihood)")
            + (("run's teacher",) if truth else ())]
    names.insert(3, "bias")
    for name in names:
        low, high = result["ci"][name]
        rows.append((name, number(result[name]), f"[{number(low)}, {number(high)}]")
                    + ((number(truth.get(name)),) if truth else ()))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = [f"{result['n_pairs']} pairs: {result['n_strict']} strict, {result['n_equal']} equal, "
             f"{result['n_skipped']} skipped"]
    lines += ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip()
              for row in rows]
    for name in ("skip", "equal"):
        if result[f"{name}_disagreements"]:
            lines.append(f"note: no {name} threshold explains every decision: "
                         f"{result[f'{name}_disagreements']} go the other way (a lapse rate fits)")
    if result["bias"]:
        lines.append("note: the answers lean to one side whatever the segments (bias: the share "
                     "of strict answers given to the right (> 0) or left (< 0) regardless); beta, "
                     "gamma and eps_mistake are fitted again with it, without intervals (the fit "
                     "without it is under the flags)")
    if result.get("gamma_unknown"):
        lines.append("note: gamma's interval is its whole range: the labels do not tell it "
                     "(segments whose rewards hardly change along them), so gamma is 1, the "
                     "simplest teacher")
    if result.get("nonpositive_scales"):
        lines.append(f"warning: {result['nonpositive_scales']} pairs come from sessions whose "
                     "threshold_scale (H / T x R_avg) is 0 or below: a teacher's skip and equal "
                     "thresholds are 0 there whatever its eps, so they tell nothing of eps_skip, "
                     "eps_equal")
    missing = [name for name in ("skip", "equal") if result[f"eps_{name}"] is None]
    if missing:
        lines.append("note: the label files lack threshold_scale: delta_"
                     + " and delta_".join(missing) + " are in return units, and --teacher-eps-"
                     + " and --teacher-eps-".join(missing) + " cannot be given")
    if "check" in result:
        check = result["check"]
        choice = check["choice"]
        unit = " / scale" if "eps_equal" in result["ci"] else ""
        bins = len(choice["bins"])
        lines += ["", f"goodness of fit (observed against predicted shares in {bins} bins each, G "
                  f"on chi2 with {bins - 2} degrees of freedom):",
                  f"strict labels by the fitted A1 - A0: G = {choice['statistic']:.1f}, "
                  f"p = {choice['p_value']:.3g}"]
        lines += bin_rows(choice["bins"], "right")
        for name, value in (("equal", "|R1 - R0|"), ("skip", "max(R0, R1)")):
            part = check[name]
            pairs = "\"equal\" answers (kept pairs)" if name == "equal" else "skips (all pairs)"
            lines.append(f"{pairs} by {value}{unit}: {part['given']} given, the fitted "
                         f"teacher's {part['fitted']}; G = {part['statistic']:.1f}, "
                         f"p = {part['p_value']:.3g}")
            if part["p_value"] < CHECK_LEVEL or part["lapse"] > MAX_LAPSE:
                lines += bin_rows(part["bins"], name)
        lines.append(f"verdict: {check['verdict']}")
    lines += ["", "simulate this teacher with pebble.py or prefppo.py (on the same task: beta is "
              "per unit of return):", f"  {teacher_flags(result)}"]
    if "without_bias" in result:
        without = result["without_bias"]
        fitted = ", ".join(f"{name} {without[name]:.4g} [{low:.4g}, {high:.4g}]"
                           for name, (low, high) in without["ci"].items())
        lines += [f"without the side bias (fitted without it: {fitted}):",
                  f"  {teacher_flags(result | without | {'bias': 0.0})}"]
    return "\n".join(lines)


def run_teacher(path: str) -> dict | None:
    """The simulated teacher of the run whose labels `path` holds (from the config.json of the run
    directory, of --labels or up to two levels above it), None if none is known."""
    path = os.path.abspath(path)
    configs = [os.path.join(d, "config.json")
               for d in (path, os.path.dirname(path), os.path.dirname(os.path.dirname(path)))]
    try:
        with open(next(c for c in configs if os.path.isfile(c))) as f:
            saved = json.load(f)
    except (StopIteration, OSError, ValueError):
        return None
    truth = {name: saved.get(f"teacher_{name}", 0.0 if name == "bias" else None)
             for name in TEACHER}
    if saved.get("teacher") == "human" or not all(isinstance(v, (int, float))
                                                   for v in truth.values()):
        return None
    return truth | {f"delta_{k}": 0.0 for k in ("skip", "equal") if truth[f"eps_{k}"] == 0}


def main():
    args = tyro.cli(Args)
    if (args.run_dir is None) == (args.labels is None):
        print("error: give the labels once: fit_teacher.py RUN_DIR (or --labels RUN_DIR)",
              file=sys.stderr)
        sys.exit(2)
    path = args.run_dir or args.labels
    try:
        if args.simulate and not 1 <= args.sessions <= args.pairs:
            raise ValueError(f"--simulate needs 1 <= --sessions <= --pairs, got {args.sessions} "
                             f"sessions of {args.pairs} pairs")
        if args.simulate:
            teacher = SimTeacher(args.teacher_beta, args.teacher_gamma, args.teacher_eps_mistake,
                                 args.teacher_eps_skip, args.teacher_eps_equal, args.teacher_bias,
                                 seed=args.seed)
            simulate(path, teacher, args.pairs, args.sessions, seed=args.seed)
        data = load_labels(path)
        try:
            result = fit(data["rewards0"], data["rewards1"], data["y"], data["keep"],
                         data["threshold_scale"], args.level)
        except ValueError as error:
            raise ValueError(f"{path!r}: {error}") from None
    except (ValueError, OSError) as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
    print(report(result, run_teacher(path)))


if __name__ == "__main__":
    main()
