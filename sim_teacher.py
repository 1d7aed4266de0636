"""Simulated human teachers of B-Pref (Lee et al., 2021), paper Section 3.1 and Algorithm 1.

A teacher sees pairs of segments through their true per-step rewards and answers, for each pair,
which segment it prefers. Every irrationality of the paper is a field, so they combine freely:

    teacher = make_teacher("myopic", seed=0, eps_mistake=0.1)  # myopic and makes mistakes
    teacher.set_thresholds(mean_return=412.0, segment_len=50, episode_len=1000)
    y, keep = teacher.label(rewards0, rewards1)                # arrays (N, H) -> (N,), (N,)

`y[i]` is the weight on the second segment: 0.0 = first preferred, 1.0 = second preferred,
0.5 = equally preferable; `keep[i]` is False where the teacher skipped the query (y is NaN there).
Arrays in, arrays out: no torch and no environment in this module.
"""

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class SimTeacher:
    """SimTeacher(beta, gamma, epsilon, delta_skip, delta_equal) of Algorithm 1."""

    beta: float = math.inf
    """rationality constant of Eq. (1): inf = perfectly rational and deterministic, 0 = uniformly random"""
    gamma: float = 1.0
    """myopic discount of Eq. (1): step t of H weighs gamma^(H-t), so the last step weighs 1"""
    eps_mistake: float = 0.0
    """probability of flipping a strict preference (Algorithm 1, lines 7 and 10)"""
    eps_skip: float = 0.0
    """epsilon_adapt of the skip threshold: delta_skip = eps_skip * H / T * R_avg (appendix)"""
    eps_equal: float = 0.0
    """epsilon_adapt of the equal threshold: delta_equal = eps_equal * H / T * |R_avg| (appendix)"""
    seed: int | None = None
    """seed of the teacher's own random generator (stochastic choices and mistakes)"""
    delta_skip: float = field(default=0.0, init=False)
    delta_equal: float = field(default=0.0, init=False)

    def __post_init__(self):
        if not (self.beta >= 0):  # also rejects NaN
            raise ValueError(f"beta must be >= 0 (math.inf for a rational teacher), got {self.beta}")
        if not (0 < self.gamma <= 1):
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")
        for name in ("eps_mistake", "eps_skip", "eps_equal"):
            value = getattr(self, name)
            if not (0 <= value <= 1):
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        self.rng = np.random.default_rng(self.seed)

    def set_thresholds(self, mean_return: float, segment_len: int, episode_len: int) -> None:
        """Adaptive thresholds of the appendix: delta = eps * (H / T) * R_avg, with R_avg the mean
        true return of the current policy's recent episodes. Call before every feedback session.
        Each threshold is eps times the scaled return (the reference code applied eps twice)."""
        if segment_len < 1 or episode_len < segment_len:
            raise ValueError(
                f"need 1 <= segment_len <= episode_len, got segment_len={segment_len}, episode_len={episode_len}"
            )
        if not math.isfinite(mean_return):
            raise ValueError(f"mean_return must be finite, got {mean_return}")
        scaled_return = segment_len / episode_len * mean_return
        self.delta_skip = self.eps_skip * scaled_return
        # A difference threshold must be >= 0: on tasks with negative returns (not in the paper, whose
        # rewards are >= 0) the equal threshold uses |R_avg|, so the Equal teacher still says "equal".
        self.delta_equal = self.eps_equal * abs(scaled_return)

    def state_dict(self) -> dict:
        """Plain data, as torch modules' state_dict: the fields, thresholds and the generator's state (what a
        checkpoint saves; it loads with torch.load(..., weights_only=True))."""
        names = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal", "delta_skip", "delta_equal")
        return {name: getattr(self, name) for name in names} | {"rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        """Back to the teacher that state_dict() saw: the same labels from here on."""
        for name, value in state.items():
            if name != "rng":
                setattr(self, name, value)
        self.rng.bit_generator.state = state["rng"]

    def label(self, rewards0: np.ndarray, rewards1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Algorithm 1 on N queries at once: true rewards (N, H) of both segments -> (y, keep)."""
        rewards0 = np.asarray(rewards0, dtype=np.float64)
        rewards1 = np.asarray(rewards1, dtype=np.float64)
        if rewards0.ndim != 2 or rewards0.shape != rewards1.shape:
            raise ValueError("rewards0 and rewards1 must be 2-D arrays (N, H) of one shape, got "
                             f"{rewards0.shape} and {rewards1.shape}")
        n = len(rewards0)
        if self.eps_skip > 0 or self.eps_equal > 0 or self.gamma == 1.0:  # undiscounted returns
            returns0, returns1 = rewards0.sum(axis=1), rewards1.sum(axis=1)

        # Line 1: skip when even the better segment's (undiscounted) return is below delta_skip.
        # Only a teacher with eps_skip > 0 skips: the oracle's delta_skip = 0 must not skip
        # segments of negative return.
        keep = np.ones(n, dtype=bool)
        if self.eps_skip > 0:
            keep = np.maximum(returns0, returns1) >= self.delta_skip
        # Line 3: equally preferable when the undiscounted returns differ by less than delta_equal.
        equal = np.zeros(n, dtype=bool)
        if self.eps_equal > 0:
            equal = np.abs(returns1 - returns0) < self.delta_equal

        # Line 5: Bradley-Terry choice of Eq. (1) on myopic sums sum_t gamma^(H-t) r_t.
        if self.gamma == 1.0:
            advantage = returns1 - returns0
        else:
            weights = self.gamma ** np.arange(rewards0.shape[1] - 1, -1, -1, dtype=np.float64)
            advantage = rewards1 @ weights - rewards0 @ weights
        if math.isinf(self.beta):  # the beta -> inf limit: the better segment; an exact tie is a coin flip
            prob_second = 0.5 * (1.0 + np.sign(advantage))
        else:  # sigmoid(beta * advantage), written with tanh so that no exp overflows
            prob_second = 0.5 * (1.0 + np.tanh(0.5 * self.beta * advantage))
        y = (self.rng.random(len(advantage)) < prob_second).astype(np.float64)

        # Lines 7 and 10: a mistake flips a strict preference with probability eps.
        flip = self.rng.random(len(y)) < self.eps_mistake
        y = np.where(flip, 1.0 - y, y)

        y[equal] = 0.5
        y[~keep] = np.nan
        return y, keep


TEACHERS: dict[str, dict[str, float]] = {
    "oracle": {},
    "stoc": {"beta": 1.0},
    "mistake": {"eps_mistake": 0.1},
    "skip": {"eps_skip": 0.1},
    "equal": {"eps_equal": 0.1},
    "myopic": {"gamma": 0.9},
}
"""The six teachers of the paper (Section 3.3): name -> the fields that differ from the oracle."""


def make_teacher(name: str, seed: int | None = None, **overrides: float) -> SimTeacher:
    """A preset of TEACHERS with any field overridden, e.g. make_teacher("myopic", eps_mistake=0.1)."""
    if name not in TEACHERS:
        raise ValueError(f"unknown teacher {name!r}: choose one of {', '.join(TEACHERS)}")
    fields = {"beta", "gamma", "eps_mistake", "eps_skip", "eps_equal"}
    unknown = set(overrides) - fields
    if unknown:
        raise ValueError(f"unknown teacher field(s) {sorted(unknown)}: choose from {sorted(fields)}")
    return SimTeacher(**{**TEACHERS[name], **overrides}, seed=seed)
