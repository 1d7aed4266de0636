"""Simulated human teachers of B-Pref (Lee et al., 2021), paper Section 3.1 and Algorithm 1.

A teacher sees pairs of segments through their true per-step rewards and answers, for each pair,
which segment it prefers. Every irrationality of the paper is a field, so they combine freely:

    teacher = make_teacher("myopic", seed=0, eps_mistake=0.1)  # myopic and makes mistakes
    teacher.set_thresholds(mean_return=412.0, segment_len=50, episode_len=1000)
    y, keep = teacher.label(rewards0, rewards1)                # arrays (N, H) -> (N,), (N,)

`y[i]` is the weight on the second segment: 0.0 = first preferred, 1.0 = second preferred,
0.5 = equally preferable; `keep[i]` is False where the teacher skipped the query (y is NaN there).
A person is a teacher too: make_teacher("human", run_dir=...) has the same label(...) call; it
writes each session's queries where label_server.py shows them and waits for the answers. This
module also owns the files of labels and of a person's sessions: one format, one reader, one
writer for pebble.py, prefppo.py, label_server.py and fit_teacher.py.
Arrays in, arrays out: no torch and no environment in this module.
"""

import glob
import io
import json
import math
import os
import signal
import sys
import time
import zipfile
from dataclasses import dataclass, field

import numpy as np


@dataclass
class SimTeacher:
    """SimTeacher(beta, gamma, epsilon, delta_skip, delta_equal) of Algorithm 1, and a side bias
    (not in the paper; 0 changes nothing) to simulate a person whom fit_teacher.py finds leaning."""

    beta: float = math.inf
    """rationality constant of Eq. (1): inf = rational and deterministic, 0 = uniformly random"""
    gamma: float = 1.0
    """myopic discount of Eq. (1): step t of H weighs gamma^(H-t), so the last step weighs 1"""
    eps_mistake: float = 0.0
    """probability of flipping a strict preference (Algorithm 1, lines 7 and 10)"""
    eps_skip: float = 0.0
    """epsilon_adapt of the skip threshold: delta_skip = eps_skip * H / T * R_avg (appendix)"""
    eps_equal: float = 0.0
    """epsilon_adapt of the equal threshold: delta_equal = eps_equal * H / T * |R_avg| (appendix)"""
    bias: float = 0.0
    """side bias: with probability |bias| a strict answer is right (bias > 0) or left (< 0) whatever
    the segments; P(y = 1) = bias+ + (1 - |bias|) P_Algorithm1(y = 1)"""
    seed: int | None = None
    """seed of the teacher's own random generator (stochastic choices and mistakes)"""
    delta_skip: float = field(default=0.0, init=False)
    delta_equal: float = field(default=0.0, init=False)

    def __post_init__(self):
        if not (self.beta >= 0):  # also rejects NaN
            raise ValueError(f"beta must be >= 0 (math.inf: a rational teacher), got {self.beta}")
        if not (0 < self.gamma <= 1):
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma}")
        for name in ("eps_mistake", "eps_skip", "eps_equal"):
            value = getattr(self, name)
            if not (0 <= value <= 1):
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        if not (-1 <= self.bias <= 1):
            raise ValueError("bias must be in [-1, 1] (a probability, signed by the side), "
                             f"got {self.bias}")
        self.rng = np.random.default_rng(self.seed)

    def set_thresholds(self, mean_return: float, segment_len: int, episode_len: int) -> None:
        """Adaptive thresholds of the appendix: delta = eps * (H / T) * R_avg, with R_avg the mean
        true return of the current policy's recent episodes. Call before every feedback session.
        Each threshold is eps times the scaled return (the reference code applied eps twice)."""
        if segment_len < 1 or episode_len < segment_len:
            raise ValueError("need 1 <= segment_len <= episode_len, "
                             f"got segment_len={segment_len}, episode_len={episode_len}")
        if not math.isfinite(mean_return):
            raise ValueError(f"mean_return must be finite, got {mean_return}")
        scaled_return = segment_len / episode_len * mean_return
        self.delta_skip = self.eps_skip * scaled_return
        # A difference threshold must be >= 0: on tasks with negative returns (not in the paper,
        # whose rewards are >= 0) the equal threshold uses |R_avg|, so Equal still says "equal".
        self.delta_equal = self.eps_equal * abs(scaled_return)

    def state_dict(self) -> dict:
        """Plain data, as torch modules' state_dict: the fields, thresholds and the generator's
        state (what a checkpoint saves; it loads with torch.load(..., weights_only=True))."""
        names = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal", "bias", "delta_skip",
                 "delta_equal")
        return {name: getattr(self, name) for name in names} | {"rng": self.rng.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        """Back to the teacher that state_dict() saw: the same labels from here on."""
        for name, value in state.items():
            if name != "rng":
                setattr(self, name, value)
        self.rng.bit_generator.state = state["rng"]

    def label(self, rewards0: np.ndarray, rewards1: np.ndarray, queries: dict | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """Algorithm 1 on N queries at once: true rewards (N, H) of both segments -> (y, keep).
        `queries` (what a person needs to watch the segments, HumanTeacher) is not used."""
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
        if math.isinf(self.beta):  # beta -> inf: the better segment; an exact tie is a coin flip
            prob_second = 0.5 * (1.0 + np.sign(advantage))
        else:  # sigmoid(beta * advantage), written with tanh so that no exp overflows
            prob_second = 0.5 * (1.0 + np.tanh(0.5 * self.beta * advantage))
        y = (self.rng.random(len(advantage)) < prob_second).astype(np.float64)

        # Lines 7 and 10: a mistake flips a strict preference with probability eps.
        flip = self.rng.random(len(y)) < self.eps_mistake
        y = np.where(flip, 1.0 - y, y)
        if self.bias:  # the side bias: no draw at all when it is 0 (the paper's teachers unchanged)
            y = np.where(self.rng.random(len(y)) < abs(self.bias), float(self.bias > 0), y)

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


def make_teacher(name: str, seed: int | None = None, run_dir: str = "", episodes=(),
                 **overrides: float):
    """A preset of TEACHERS with any field overridden, e.g. make_teacher("myopic", eps_mistake=0.1);
    "human": a person who answers in label_server.py's page for the run in run_dir, watching the
    segments replayed from `episodes` (the query pool, see HumanTeacher)."""
    if name == "human":
        return HumanTeacher(run_dir, episodes)
    if name not in TEACHERS:
        raise ValueError(f"unknown teacher {name!r}: choose one of {', '.join(TEACHERS)}")
    fields = {"beta", "gamma", "eps_mistake", "eps_skip", "eps_equal", "bias"}
    unknown = set(overrides) - fields
    if unknown:
        raise ValueError(f"unknown teacher field(s) {sorted(unknown)}: "
                         f"choose from {sorted(fields)}")
    return SimTeacher(**{**TEACHERS[name], **overrides}, seed=seed)


# Files: written whole to a temporary file, then renamed, so that a kill never leaves half a file
def save_file(path: str, data: bytes) -> None:
    """`data` to `path`, flushed to disk first: a kill during the write leaves the old file."""
    try:
        with open(f"{path}.tmp", "wb") as f:
            f.write(data)
            os.fsync(f.fileno())
        os.replace(f"{path}.tmp", path)
    finally:
        if os.path.exists(f"{path}.tmp"):
            os.remove(f"{path}.tmp")


def save_npz(path: str, **arrays) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    data = io.BytesIO()
    np.savez(data, **arrays)
    save_file(path, data.getvalue())


# Label files: <run>/labels/session_NNNN.npz, one a feedback session, with the session's step, y and
# keep (as label() returns them), threshold_scale (H / T * R_avg, the unit of the adaptive
# thresholds) and the queried segments: obs0, actions0, rewards0 (N, H, ...), episode0, start0
# (where each was cut from the query pool), the same for side 1
LABEL_KEYS = ("rewards0", "rewards1", "y", "keep")


def save_labels(run_dir: str, session: int, **arrays) -> None:
    save_npz(os.path.join(run_dir, "labels", f"session_{session:04d}.npz"), **arrays)


def label_files(path: str) -> list[str]:
    """The label files of a run directory, of its labels/ directory, or one .npz file."""
    if os.path.isfile(path):
        return [path]
    return sorted(glob.glob(os.path.join(path, "labels", "session_*.npz"))
                  or glob.glob(os.path.join(path, "session_*.npz")))


def load_labels(path: str) -> list[dict]:
    """Every session of `path` (label_files) as a dict of arrays, threshold_scale as a float (None
    when a file lacks it); ValueError naming the file for a missing or malformed one."""
    files = label_files(path)
    if not files:
        raise ValueError(f"{path!r}: no label files (session_*.npz in it or in its labels/)")
    sessions = []
    for file in files:
        if not zipfile.is_zipfile(file):
            raise ValueError(f"{file}: not an .npz file")
        try:
            with np.load(file) as data:
                session = {key: data[key] for key in data.files}
        except (OSError, EOFError, ValueError, zipfile.BadZipFile) as error:
            raise ValueError(f"{file}: not a readable .npz ({error})") from None
        if missing := [key for key in LABEL_KEYS if key not in session]:
            raise ValueError(f"{file}: no {', '.join(missing)} in it")
        for key in LABEL_KEYS:
            value = session[key]
            if not (isinstance(value, np.ndarray) and (value.dtype == bool
                                                       or np.issubdtype(value.dtype, np.number))):
                raise ValueError(f"{file}: its {key} is not an array of numbers")
        shapes = [session[key].shape for key in LABEL_KEYS]
        if not (len(shapes[0]) == 2 and shapes[0] == shapes[1]
                and shapes[2] == shapes[3] == shapes[0][:1]):
            raise ValueError(f"{file}: rewards0, rewards1 must be (N, H) and y, keep (N,); got "
                             f"shapes {', '.join(map(str, shapes))}")
        scale = session.get("threshold_scale")
        if scale is not None and scale.size != 1:
            raise ValueError(f"{file}: threshold_scale must be one number, got shape {scale.shape}")
        session["threshold_scale"] = None if scale is None else float(scale)
        sessions.append(session)
    if len({s["rewards0"].shape[1] for s in sessions}) > 1:
        lengths = sorted({s["rewards0"].shape[1] for s in sessions})
        raise ValueError(f"{path!r}: sessions of different segment lengths {lengths}")
    return sessions


def load_pairs(path: str, shape: tuple) -> tuple[np.ndarray, ...]:
    """--labels-from: every session of `path` as (inputs0, inputs1, y, keep), where inputs are the
    segments' observations and actions side by side, (N, H, obs + action); ValueError when they
    do not fit `shape`."""
    sessions = load_labels(path)
    try:
        inputs = [np.concatenate([np.concatenate([s[f"obs{i}"], s[f"actions{i}"]], -1)
                                  for s in sessions])
                  for i in (0, 1)]
    except (KeyError, ValueError) as error:
        raise ValueError(f"{path!r}: its label files hold no segments' obs and actions "
                         f"({error})") from None
    if inputs[0].shape[1:] != tuple(shape):
        raise ValueError(f"--labels-from: segments of shape {inputs[0].shape[1:]} do not fit this "
                         f"run's {tuple(shape)} (segment length, observation + action size)")
    return (*inputs, *(np.concatenate([s[key] for s in sessions]) for key in ("y", "keep")))


def set_labels_aside(run_dir: str, sessions_done: int, step: int) -> None:
    """--resume from step N: the label files of later sessions go to labels/before_resume_at_step_N
    (the run asks those sessions again)."""
    kept_dir = os.path.join(run_dir, "labels", f"before_resume_at_step_{step}")
    for path in label_files(run_dir)[sessions_done:]:
        os.makedirs(kept_dir, exist_ok=True)
        os.replace(path, os.path.join(kept_dir, os.path.basename(path)))


# A person's sessions: <run>/queries/session_NNNN.npz holds the step and, for side 0 (left) and 1
# (right), each query's episode reset seed (seed0), segment start (start0) and that episode's
# actions (actions0, N x steps x action dim): label_server.py replays the segment from them. The
# answers go to session_NNNN_answers.json: {"order": [query ids as answered], "answers": {"id":
# "left" | "right" | "equal" | "skip"}}
ANSWER_LABELS = {"left": 0.0, "right": 1.0, "equal": 0.5, "skip": math.nan}


def queries_path(run_dir: str, session: int, suffix: str = ".npz") -> str:
    return os.path.join(run_dir, "queries", f"session_{session:04d}{suffix}")


def page_url_path(run_dir: str) -> str:
    """Where label_server.py writes the address of its page while it serves the run."""
    return os.path.join(run_dir, "queries", "page_url.txt")


def load_queries(path: str) -> dict:
    """A session's queries file as arrays; ValueError when its sides do not fit together."""
    with np.load(path) as data:
        queries = {key: data[key] for key in data.files}
    n = len(queries["seed0"])
    for side in (0, 1):
        lengths = {len(queries[f"{key}{side}"]) for key in ("seed", "start", "actions")}
        if lengths != {n}:
            raise ValueError(f"{path}: seed, start and actions of side {side} differ in length")
    return queries


def read_answers(run_dir: str, session: int) -> dict:
    path = queries_path(run_dir, session, "_answers.json")
    if not os.path.exists(path):
        return {"order": [], "answers": {}}
    with open(path) as f:
        return json.load(f)


def write_answers(run_dir: str, session: int, answers: dict) -> None:
    save_file(queries_path(run_dir, session, "_answers.json"), json.dumps(answers).encode())


@dataclass
class HumanTeacher:
    """A person as the teacher: label() writes the session's queries for label_server.py and waits
    until the page has answered each one."""

    run_dir: str
    """the run's directory (its queries/ is where label_server.py looks)"""
    episodes: object = ()
    """the query pool: whole episodes as (observations, actions, true rewards, reset seed)"""
    session: int = 0
    """the next session's number"""

    def set_thresholds(self, mean_return: float, segment_len: int, episode_len: int) -> None:
        """A person has no thresholds: they skip or call a pair equal as they see it."""

    def state_dict(self) -> dict:
        return {"session": self.session}

    def load_state_dict(self, state: dict) -> None:
        self.session = state["session"]

    def label(self, rewards0: np.ndarray, rewards1: np.ndarray, queries: dict | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """(y, keep) as SimTeacher.label's, from a person's answers. `queries`: the session's step
        and where each segment was cut (episode0, start0, episode1, start1: indices into
        `episodes` and first steps); the rewards are not shown. A session asked again (after
        --resume) keeps the answers already given."""
        n = len(rewards0)
        saved = {"step": queries["step"]}
        for side in (0, 1):
            pool = [self.episodes[e] for e in queries[f"episode{side}"]]
            longest = max(len(episode[1]) for episode in pool)
            saved[f"seed{side}"] = np.array([episode[3] for episode in pool])
            saved[f"start{side}"] = queries[f"start{side}"]
            saved[f"actions{side}"] = np.stack([np.pad(np.asarray(episode[1], np.float32),
                                                       ((0, longest - len(episode[1])), (0, 0)))
                                                for episode in pool])
        save_npz(queries_path(self.run_dir, self.session), **saved)
        try:
            with open(page_url_path(self.run_dir)) as f:
                page = f"label_server.py serves them at {f.read()}"
        except OSError:
            page = (f"python label_server.py {self.run_dir} serves them (it prints its page's "
                    "address)")
        print(f"step {queries['step']}: {n} queries wait for a person: {page}; stopping the run "
              "now loses nothing (--resume asks this session again, with the answers given)",
              flush=True)

        def stop(signum, frame):  # the run wrote its checkpoint before the session
            print(f"{signal.Signals(signum).name}: checkpoint saved before the session at step "
                  f"{queries['step']}; continue with --resume {self.run_dir}", flush=True)
            sys.exit(128 + signum)

        # While it waits, SIGTERM or SIGINT end the run at once
        signums = (signal.SIGTERM, signal.SIGINT)
        handlers = {signum: signal.signal(signum, stop) for signum in signums}
        answers = {}
        while len(answers) < n:
            time.sleep(0.2)
            try:
                answers = read_answers(self.run_dir, self.session)["answers"]
            except (OSError, ValueError, KeyError):  # being written
                answers = {}
        for signum, handler in handlers.items():
            signal.signal(signum, handler)
        self.session += 1
        y = np.array([ANSWER_LABELS[answers[str(i)]] for i in range(n)])
        return y, ~np.isnan(y)
