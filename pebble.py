# PEBBLE (Lee, Smith, Abbeel 2021) as benchmarked by B-Pref (Lee et al. 2021); docs and choices: README.md
import csv
import glob
import importlib
import io
import json
import math
import os
import pickle
import shutil
import signal
import sys
import time
import warnings
import zlib
from dataclasses import asdict, dataclass, fields
from typing import NamedTuple

import cloudpickle
import gymnasium as gym
import mujoco
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro

from samplers import SAMPLERS, SCHEDULES, random_pairs, schedule_sizes, select
from sim_teacher import TEACHERS, make_teacher


@dataclass
class Args:
    exp_name: str = "pebble"
    """the name of this experiment (part of the run name)"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True` and deterministic algorithms"""
    cuda: bool = False
    """if toggled, run on the GPU (error if there is none)"""
    track: bool = False
    """if toggled, log to Weights & Biases (needs `pip install wandb`)"""
    wandb_project_name: str = "bpref"
    """the Weights & Biases project"""
    capture_video: bool = False
    """if toggled, record one extra mean-action episode after each evaluation to videos/step_N.mp4 (headless: MUJOCO_GL=egl)"""
    output_dir: str | None = None
    """where the run's files go (default: runs/<run name>)"""
    checkpoint_every: int = 50000
    """environment steps between checkpoints (0 = only on SIGTERM/SIGINT and non-finite values)"""
    resume: str | None = None
    """continue the run in this directory from its checkpoint, with its saved configuration"""
    labels_from: str | None = None
    """seed the preference dataset with an earlier run's labels (its directory, labels/ or one .npz)"""

    # Algorithm specific arguments; None = the task's preset (PRESETS below)
    env_id: str = "walker-walk"
    """DMC `domain-task`, Meta-World v3 task name (with or without -v3), or a Gymnasium id"""
    total_timesteps: int | None = None
    """total environment steps"""
    teacher: str = "oracle"
    """simulated teacher: oracle, stoc, mistake, skip, equal, myopic (paper Section 3.3)"""
    teacher_beta: float | None = None
    """overrides the teacher's rationality beta (inf = rational)"""
    teacher_gamma: float | None = None
    """overrides the teacher's myopic discount gamma in (0, 1]"""
    teacher_eps_mistake: float | None = None
    """overrides the teacher's mistake probability"""
    teacher_eps_skip: float | None = None
    """overrides the teacher's adaptive skip fraction"""
    teacher_eps_equal: float | None = None
    """overrides the teacher's adaptive equal fraction"""
    sampler: str = "disagreement"
    """query selection: uniform, disagreement, entropy, coverage, disagreement-coverage, entropy-coverage"""
    schedule: str = "uniform"
    """feedback schedule: uniform, decay, increase (paper Section 4.2)"""
    max_feedback: int | None = None
    """total number of queries (the budget)"""
    feedback_per_session: int | None = None
    """queries per feedback session (uniform schedule)"""
    feedback_every: int | None = None
    """environment steps between feedback sessions"""
    segment_len: int | None = None
    """length H of a queried segment"""
    seed_steps: int = 1000
    """random-action steps at the start"""
    unsup_steps: int = 9000
    """unsupervised pre-training steps (kNN state entropy) after the seed steps"""
    hidden_dim: int | None = None
    """hidden units of the actor and critic"""
    num_layers: int | None = None
    """hidden layers of the actor and critic"""
    batch_size: int | None = None
    """SAC batch size"""
    learning_rate: float | None = None
    """learning rate of actor and critics"""
    alpha_lr: float = 1e-4
    """learning rate of the SAC temperature (reference code: 1e-4 on every task)"""
    eval_every: int = 10000
    """environment steps between evaluations"""
    eval_episodes: int = 10
    """episodes per evaluation"""
    ground_truth_reward: bool = False
    """if toggled, train SAC on the true reward with no teacher (the normalisation denominator)"""
    buffer_size: int | None = None
    """replay buffer capacity (default: total_timesteps)"""
    gamma: float = 0.99
    """discount of SAC"""
    tau: float = 0.005
    """critic target EMA rate"""
    target_update_every: int = 2
    """gradient steps between critic target updates"""
    init_temperature: float = 0.1
    """initial SAC temperature alpha"""
    knn_k: int = 5
    """k of the kNN state-entropy reward"""
    reward_ensemble_size: int = 3
    """reward models in the ensemble"""
    reward_lr: float = 3e-4
    """learning rate of the reward models"""
    reward_batch_size: int = 128
    """preference batch size of reward learning"""
    reward_epochs: int | None = None
    """most epochs of reward learning per session (stops early at 97% accuracy)"""
    label_smoothing: float = 0.0
    """soft labels (1 - s) * y + s / 2 (appendix uses s = 0.1 as a regulariser)"""
    candidate_multiplier: int = 10
    """candidate pairs per query for the uncertainty and coverage samplers"""
    query_recent_episodes: int = 100
    """segments are drawn from the last N complete episodes (0 = all in the buffer)"""
    critic_reset_updates: int = 100
    """SAC updates on relabelled data right after the critic reset of the first reward update"""


# Paper appendix, Table of PEBBLE hyperparameters (see README for the sources of the others). Meta-World: feedback
# every 4950 steps, not the paper's 5000, so that all 200 sessions (10,000 labels) fit in 1M steps (labels_spent)
DMC_PRESET = dict(total_timesteps=500_000, max_feedback=1000, feedback_per_session=100, feedback_every=20_000,
                  segment_len=50, hidden_dim=1024, num_layers=2, batch_size=1024, learning_rate=5e-4, reward_epochs=50)
METAWORLD_PRESET = dict(total_timesteps=1_000_000, max_feedback=10_000, feedback_per_session=50, feedback_every=4950,
                        segment_len=25, hidden_dim=256, num_layers=3, batch_size=512, learning_rate=3e-4, reward_epochs=10)
GYM_PRESET = dict(DMC_PRESET, hidden_dim=256, num_layers=2, batch_size=256, learning_rate=3e-4)
PRESETS = {
    "walker-walk": DMC_PRESET,
    "quadruped-walk": dict(DMC_PRESET, total_timesteps=1_000_000, feedback_every=30_000, learning_rate=1e-4),
    "button-press": METAWORLD_PRESET,
    "sweep-into": METAWORLD_PRESET,
}


class DMCEnv(gym.Env):
    """A dm_control suite task as a Gymnasium env: flat float32 observations, episodes end by truncation."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, domain: str, task: str, seed: int, render_mode: str | None = None):
        from dm_control import suite

        self.dmc = suite.load(domain, task, task_kwargs={"random": seed})
        self.render_mode = render_mode
        obs_dim = sum(int(np.prod(v.shape)) for v in self.dmc.observation_spec().values())
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        spec = self.dmc.action_spec()
        self.action_space = gym.spaces.Box(spec.minimum.astype(np.float32), spec.maximum.astype(np.float32))
        self.max_episode_steps = int(self.dmc._step_limit)

    def _flat(self, observation):
        return np.concatenate([np.asarray(v, dtype=np.float32).ravel() for v in observation.values()])

    def reset(self, *, seed=None, options=None):
        return self._flat(self.dmc.reset().observation), {}

    def step(self, action):
        step = self.dmc.step(action)
        terminated = step.last() and step.discount == 0
        return self._flat(step.observation), step.reward, terminated, step.last() and not terminated, {}

    def render(self):
        return self.dmc.physics.render(height=240, width=320, camera_id=0)


def env_kind(env_id: str) -> str:
    """'dmc', 'metaworld' or 'gym' for a known id; ValueError otherwise."""
    import metaworld

    with warnings.catch_warnings(action="ignore"):  # GLFW's "failed to open display" on a headless machine
        from dm_control import suite

    domain, _, task = env_id.partition("-")
    if (domain, task) in suite.ALL_TASKS:
        return "dmc"
    if f"{env_id.removesuffix('-v3')}-v3" in metaworld.ALL_V3_ENVIRONMENTS:
        return "metaworld"
    module, _, gym_id = env_id.rpartition(":")  # "my_package:MyEnv-v0" registers MyEnv-v0 on import
    if module:
        try:
            importlib.import_module(module)
        except ImportError as error:
            raise ValueError(f"--env-id {env_id!r}: cannot import {module!r} ({error})") from None
    if gym_id in gym.registry:
        return "gym"
    raise ValueError(
        f"--env-id {env_id!r} is not a DMC task (domain-task, e.g. walker-walk), "
        "a Meta-World v3 task (e.g. button-press) or a registered Gymnasium id (optionally module:id)"
    )


def float32_observation(observation) -> np.ndarray:
    return np.asarray(observation, dtype=np.float32)


def make_env(env_id: str, seed: int, render_mode: str | None = None) -> tuple[gym.Env, int]:
    """Returns (env, episode length T); actions rescaled to [-1, 1], observations flat float32."""
    kind = env_kind(env_id)
    if kind == "dmc":
        env = DMCEnv(*env_id.split("-", 1), seed, render_mode)
        episode_len = env.max_episode_steps
    elif kind == "metaworld":
        env = gym.make("Meta-World/MT1", env_name=f"{env_id.removesuffix('-v3')}-v3", seed=seed, render_mode=render_mode)
        env.get_wrapper_attr("toggle_terminate_on_success")(False)  # B-Pref: fixed 500-step episodes
        # Reference code (utils.make_metaworld_env): a fresh goal from the task's whole range at every reset, not
        # one of MT1's 50 fixed goals. One task is set for its settings; then the random vector (object and goal
        # positions) is unfrozen and drawn from the env's own generator, seeded by `seed`. The goal is hidden (its
        # 3 entries are zeros), as in the reference's v2 envs, which were partially observable by default
        env.unwrapped.set_task(env.get_wrapper_attr("tasks")[0])
        env.unwrapped._partially_observable = True
        env.get_wrapper_attr("toggle_sample_tasks_on_reset")(False)
        env.unwrapped._freeze_rand_vec = False
        env.unwrapped.seeded_rand_vec = True
        episode_len = env.spec.max_episode_steps or 500
    else:
        env = gym.make(env_id, **({"render_mode": render_mode} if render_mode else {}))
        episode_len = env.spec.max_episode_steps
        if not isinstance(env.action_space, gym.spaces.Box) or not isinstance(env.observation_space, gym.spaces.Box):
            raise ValueError(f"--env-id {env_id!r} must have Box observation and action spaces")
        if episode_len is None:
            raise ValueError(f"--env-id {env_id!r} has no time limit (max_episode_steps), needed for the thresholds")
    env = gym.wrappers.RescaleAction(env, -1.0, 1.0)
    env = gym.wrappers.TransformObservation(env, float32_observation, env.observation_space)
    env.reset(seed=seed)  # seeds the env's generator once; later resets continue its sequence
    env.action_space.seed(seed)
    return env, episode_len


def mlp(in_dim: int, out_dim: int, hidden_dim: int, num_layers: int, activation=nn.ReLU) -> nn.Sequential:
    layers, dim = [], in_dim
    for _ in range(num_layers):
        layers += [nn.Linear(dim, hidden_dim), activation()]
        dim = hidden_dim
    return nn.Sequential(*layers, nn.Linear(dim, out_dim))


def orthogonal_init(module: nn.Module):
    """Reference code (utils.weight_init, applied to actor and critics): orthogonal weights, zero biases."""
    if isinstance(module, nn.Linear):
        nn.init.orthogonal_(module.weight)
        nn.init.zeros_(module.bias)


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy; log std bounded to [-5, 2] as in the reference SAC."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers):
        super().__init__()
        self.net = mlp(obs_dim, 2 * action_dim, hidden_dim, num_layers)
        self.apply(orthogonal_init)

    def forward(self, obs):
        mean, log_std = self.net(obs).chunk(2, dim=-1)
        return mean, -5 + 0.5 * 7 * (torch.tanh(log_std) + 1)

    def sample(self, obs):
        mean, log_std = self(obs)
        pre_tanh = mean + log_std.exp() * torch.randn_like(mean)
        action = torch.tanh(pre_tanh)
        gaussian_log_prob = (-0.5 * ((pre_tanh - mean) / log_std.exp()) ** 2 - log_std - 0.5 * math.log(2 * math.pi))
        log_prob = (gaussian_log_prob - 2 * (math.log(2) - pre_tanh - F.softplus(-2 * pre_tanh))).sum(-1, keepdim=True)
        return action, log_prob

    def act(self, obs):
        return torch.tanh(self(obs)[0])


class TwinCritic(nn.Module):
    """Two Q-networks, Q(s, a) -> (q1, q2); also the fresh critics of PEBBLE's critic reset."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers):
        super().__init__()
        self.q1 = mlp(obs_dim + action_dim, 1, hidden_dim, num_layers)
        self.q2 = mlp(obs_dim + action_dim, 1, hidden_dim, num_layers)
        self.apply(orthogonal_init)

    def forward(self, obs, action):
        x = torch.cat([obs, action], dim=-1)
        return self.q1(x), self.q2(x)


class RewardEnsemble(nn.Module):
    """Appendix "Reward model": members of 3 x 256 LeakyReLU layers with a tanh-bounded output."""

    def __init__(self, obs_dim, action_dim, size):
        super().__init__()
        self.members = nn.ModuleList(
            nn.Sequential(mlp(obs_dim + action_dim, 1, 256, 3, nn.LeakyReLU), nn.Tanh()) for _ in range(size)
        )

    def forward(self, obs_action):
        """(..., obs+action) -> per-member rewards (members, ..., 1)."""
        return torch.stack([member(obs_action) for member in self.members])


class Batch(NamedTuple):
    """Transitions sampled from the replay buffer, one row each."""

    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor


class ReplayBuffer:
    """Transitions on the training device. `rewards` holds the learned reward r_hat (relabelled after
    each reward update), `true_rewards` the environment's, `intrinsic` is computed per batch."""

    fields = ("obs", "actions", "rewards", "true_rewards", "next_obs", "terminated")

    def __init__(self, capacity, obs_dim, action_dim, device):
        self.capacity, self.size, self.pos, self.added, self.device = capacity, 0, 0, 0, device
        zeros = lambda *shape: torch.zeros(capacity, *shape, device=device)  # noqa: E731
        self.obs, self.next_obs = zeros(obs_dim), zeros(obs_dim)
        self.actions, self.rewards, self.true_rewards, self.terminated = zeros(action_dim), zeros(1), zeros(1), zeros(1)

    def add(self, obs, action, reward, true_reward, next_obs, terminated):
        i = self.pos
        self.obs[i], self.actions[i], self.next_obs[i] = torch.as_tensor(obs), torch.as_tensor(action), torch.as_tensor(next_obs)
        self.rewards[i], self.true_rewards[i], self.terminated[i] = reward, true_reward, float(terminated)
        self.pos, self.size, self.added = (self.pos + 1) % self.capacity, min(self.size + 1, self.capacity), self.added + 1

    def sample(self, batch_size):
        idx = torch.randint(self.size, (batch_size,), device=self.device)
        return Batch(self.obs[idx], self.actions[idx], self.rewards[idx], self.next_obs[idx], self.terminated[idx])


class RunningMeanStd:
    """Running mean and variance over batches (Chan et al.'s parallel update; the reference code's was wrong)."""

    def __init__(self):
        self.mean, self.var, self.count = 0.0, 1.0, 0

    def update(self, x: torch.Tensor):
        batch_mean, batch_var, batch_count = x.mean().item(), x.var(unbiased=False).item(), x.numel()
        total = self.count + batch_count
        delta = batch_mean - self.mean
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total
        self.mean, self.var, self.count = self.mean + delta * batch_count / total, m2 / total, total

    @property
    def std(self):
        return math.sqrt(self.var)


def knn_distance(states: torch.Tensor, reference: torch.Tensor, k: int, chunk: int = 4096) -> torch.Tensor:
    """Distance from each state to its k-th nearest neighbour in `reference`, not counting the state
    itself (its zero distance): the (k+1)-th smallest distance. Eq. (8) without the log (README).
    Blocks of chunk x chunk distances keep the memory bounded; the k+1 nearest are merged per block."""
    kth = []
    for i in range(0, len(states), chunk):
        nearest = torch.empty(len(states[i : i + chunk]), 0, device=states.device)
        for j in range(0, len(reference), chunk):
            candidates = torch.cat([nearest, torch.cdist(states[i : i + chunk], reference[j : j + chunk])], dim=1)
            nearest = candidates.topk(min(k + 1, candidates.shape[1]), dim=1, largest=False).values
        kth.append(nearest[:, -1:])
    return torch.cat(kth)


def intrinsic_reward(batch: Batch, buffer: ReplayBuffer, k: int) -> torch.Tensor:
    """Algorithm 2's r_int(s_t) for a SAC batch, before normalisation: the kNN distance of each batch state
    s_t (obs, not next_obs; reference code: agent/sac.py) among all states in the buffer. s_t is stored there
    itself, and knn_distance skips exactly that one zero distance."""
    return knn_distance(batch.obs, buffer.obs[: buffer.size], k)


def numpy_seeds(seed: int) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
    """Independent streams for the query sampler and the teacher from one run seed (one generator each,
    seeded alike, would draw the same numbers)."""
    sampler_seed, teacher_seed = np.random.SeedSequence(seed).spawn(2)
    return sampler_seed, teacher_seed


def relabel(buffer: ReplayBuffer, reward_model: RewardEnsemble, chunk: int = 16384):
    """PEBBLE's relabelling: r_hat = ensemble mean for every stored transition, including after the
    buffer has wrapped (the reference code only relabelled the prefix up to the write position)."""
    with torch.no_grad():
        for i in range(0, buffer.size, chunk):
            obs_action = torch.cat([buffer.obs[i : i + chunk], buffer.actions[i : i + chunk]], dim=-1)
            buffer.rewards[i : i + chunk] = reward_model(obs_action).mean(0)


def preference_loss(segment_returns: torch.Tensor, y: torch.Tensor, label_smoothing: float = 0.0) -> torch.Tensor:
    """Eq. (3): cross-entropy of P[sigma1 > sigma0] = softmax(sum r_hat) (Eq. (2)) against soft targets
    (1 - y, y); equal labels (y = 0.5) are the uniform target. segment_returns: (batch, 2)."""
    target = (1 - label_smoothing) * y + label_smoothing / 2
    log_probs = F.log_softmax(segment_returns, dim=-1)
    return -((1 - target) * log_probs[:, 0] + target * log_probs[:, 1]).mean()


def preference_accuracy(segment_returns: torch.Tensor, y: torch.Tensor) -> tuple[int, int]:
    """(correct, counted) over strict labels only: an equal label has no right side to pick, so it is
    not counted (the reference code counted it as 'first preferred', biasing the 97% early stop)."""
    strict = y != 0.5
    predicted_second = segment_returns[:, 1] > segment_returns[:, 0]
    return int((predicted_second == (y > 0.5))[strict].sum()), int(strict.sum())


def train_reward(reward_model, optimizer, inputs0, inputs1, y, args, max_epochs) -> tuple[float, float]:
    """Reward learning (Algorithm 3, the gradient steps on L^Reward): up to max_epochs passes over the
    preference dataset, each member with its own shuffle; stop once the training accuracy passes 97%."""
    n, accuracy, loss_value = len(y), float("nan"), float("nan")
    for _ in range(max_epochs):
        orders = [torch.randperm(n, device=y.device) for _ in reward_model.members]
        correct = counted = 0
        losses = []
        for start in range(0, n, args.reward_batch_size):
            loss = 0.0
            for member, order in zip(reward_model.members, orders):
                idx = order[start : start + args.reward_batch_size]
                returns = torch.cat([member(inputs0[idx]).sum(1), member(inputs1[idx]).sum(1)], dim=-1)
                loss = loss + preference_loss(returns, y[idx], args.label_smoothing)
                c, m = preference_accuracy(returns.detach(), y[idx])
                correct, counted = correct + c, counted + m
            check_finite("reward-model loss", loss)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.item() / len(reward_model.members))
        loss_value = float(np.mean(losses))
        accuracy = correct / counted if counted else float("nan")
        if accuracy > 0.97:
            break
    return loss_value, accuracy


def labels_spent(total_timesteps: int, pretrain_steps: int, feedback_every: int, session_sizes) -> int:
    """How many labels the run asks for: the main loop holds session i at step pretrain_steps + 1 + i * feedback_every
    while that is <= total_timesteps, asking session_sizes[i]. Assumes a complete episode at the end of pre-training
    (DMC and Meta-World: 1000- and 500-step episodes, pre-training 10K steps); a later first session asks fewer."""
    n_sessions = max(0, (total_timesteps - pretrain_steps - 1) // feedback_every + 1)
    return int(np.sum(session_sizes[:n_sessions]))


TEACHER_FIELDS = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal")  # SimTeacher's, --teacher-* here


def resolve(args: Args) -> Args:
    """Fill every field left None from the task's preset and the teacher's; a flag the user gave wins."""
    family = {"dmc": DMC_PRESET, "metaworld": METAWORLD_PRESET, "gym": GYM_PRESET}[env_kind(args.env_id)]
    preset = PRESETS.get(args.env_id.removesuffix("-v3"), family)
    if args.teacher in TEACHERS:  # an unknown one is check_args' to report
        teacher = make_teacher(args.teacher)
        preset = preset | {f"teacher_{name}": getattr(teacher, name) for name in TEACHER_FIELDS}
    for key, value in preset.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.buffer_size is None:
        args.buffer_size = args.total_timesteps
    return args


def check_args(args: Args, episode_len: int) -> str | None:
    """The first problem with the configuration as one line, or None."""
    overrides = {"teacher_beta": (args.teacher_beta, "must be >= 0 (inf = rational)", lambda v: v >= 0),
                 "teacher_gamma": (args.teacher_gamma, "must be in (0, 1]", lambda v: 0 < v <= 1)}
    for name in ("teacher_eps_mistake", "teacher_eps_skip", "teacher_eps_equal"):
        overrides[name] = (getattr(args, name), "must be in [0, 1]", lambda v: 0 <= v <= 1)
    checks = [
        (args.teacher in TEACHERS, f"--teacher {args.teacher!r} is not one of {', '.join(TEACHERS)}"),
        (args.sampler in SAMPLERS, f"--sampler {args.sampler!r} is not one of {', '.join(SAMPLERS)}"),
        (args.schedule in SCHEDULES, f"--schedule {args.schedule!r} is not one of {', '.join(SCHEDULES)}"),
        *[(value is None or ok(value), f"--{name.replace('_', '-')} {msg}, got {value}") for name, (value, msg, ok) in overrides.items()],
        (args.max_feedback >= 1, f"--max-feedback must be >= 1, got {args.max_feedback}"),
        (1 <= args.feedback_per_session <= args.max_feedback,
         f"--feedback-per-session must be in [1, --max-feedback={args.max_feedback}], got {args.feedback_per_session}"),
        (args.feedback_every >= 1, f"--feedback-every must be >= 1, got {args.feedback_every}"),
        (1 <= args.segment_len <= episode_len,
         f"--segment-len must be in [1, {episode_len}] (the episode length of {args.env_id}), got {args.segment_len}"),
        (args.seed_steps >= 0 and args.unsup_steps >= 0, "--seed-steps and --unsup-steps must be >= 0"),
        (args.total_timesteps > args.seed_steps + args.unsup_steps,
         f"--total-timesteps ({args.total_timesteps}) must exceed --seed-steps + --unsup-steps ({args.seed_steps + args.unsup_steps})"),
        (args.buffer_size >= max(args.batch_size, episode_len), f"--buffer-size must be >= max(batch size, episode length), got {args.buffer_size}"),
        (min(args.hidden_dim, args.num_layers, args.batch_size, args.reward_batch_size, args.reward_ensemble_size) >= 1,
         "--hidden-dim, --num-layers, --batch-size, --reward-batch-size and --reward-ensemble-size must be >= 1"),
        (min(args.eval_every, args.eval_episodes, args.knn_k, args.candidate_multiplier, args.reward_epochs) >= 1,
         "--eval-every, --eval-episodes, --knn-k, --candidate-multiplier and --reward-epochs must be >= 1"),
        (min(args.learning_rate, args.alpha_lr, args.reward_lr) > 0,
         "--learning-rate, --alpha-lr and --reward-lr must be > 0"),
        (0 < args.gamma <= 1 and 0 < args.tau <= 1, "--gamma and --tau must be in (0, 1]"),
        (args.init_temperature > 0, f"--init-temperature must be > 0, got {args.init_temperature}"),
        (0 <= args.label_smoothing < 1, f"--label-smoothing must be in [0, 1), got {args.label_smoothing}"),
        (args.target_update_every >= 1 and args.critic_reset_updates >= 0 and args.query_recent_episodes >= 0,
         "--target-update-every must be >= 1, --critic-reset-updates and --query-recent-episodes >= 0"),
        (args.checkpoint_every >= 0, f"--checkpoint-every must be >= 0, got {args.checkpoint_every}"),
        (not args.cuda or torch.cuda.is_available(), "--cuda was given but torch sees no GPU"),
    ]
    return next((message for ok, message in checks if not ok), None)


def fail(message: str, code: int = 2):
    print(f"error: {message}", file=sys.stderr)
    sys.exit(code)


def write_atomic_npz(path: str, **arrays):
    """Write then rename, so that a kill never leaves a half-written file."""
    tmp = f"{path}.tmp.npz"
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


# Checkpoint and resume: a run killed at any point continues exactly from its last checkpoint
RESUME_MAY_CHANGE = ("resume", "checkpoint_every", "cuda", "track", "wandb_project_name", "capture_video")
MUJOCO_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # time, qpos, qvel, act, warm start, controls, mocap


class NonFiniteError(Exception):
    """A NaN or infinity in a loss or in what the environment returned; the message names it."""


def check_finite(name: str, value: torch.Tensor):
    if not torch.isfinite(value).all():
        raise NonFiniteError(f"non-finite {name} ({value.detach().flatten()[0].item()})")


def atomic_torch_save(obj, path: str):
    """Write to a temporary file, flush it to disk, then rename: a kill during the write leaves the
    previous file intact. Serialised in memory first, so that a full disk is a plain OSError."""
    tmp, serialised = f"{path}.tmp", io.BytesIO()
    torch.save(obj, serialised)
    try:
        with open(tmp, "wb") as f:
            f.write(serialised.getbuffer())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def env_layers(env) -> list:
    """The env and every env it wraps, outermost first."""
    layers = [env]
    while hasattr(layers[-1], "env"):
        layers.append(layers[-1].env)
    return layers


class MujocoStatePickler(cloudpickle.Pickler):
    """Pickles MuJoCo data as its integration state (restored exactly by MujocoStateUnpickler) and, as
    cloudpickle does, the local functions of wrappers such as RescaleAction."""

    def persistent_id(self, obj):
        if isinstance(obj, mujoco.MjData):
            state = np.empty(mujoco.mj_stateSize(obj.model, MUJOCO_STATE))
            mujoco.mj_getState(obj.model, obj, state, MUJOCO_STATE)
            return obj.model, state
        return None


class MujocoStateUnpickler(pickle.Unpickler):
    def __init__(self, file):
        super().__init__(file)
        self.restored = []

    def persistent_load(self, pid):
        model, state = pid
        self.restored.append((model, mujoco.MjData(model), state))
        return self.restored[-1][1]


def env_state(env) -> bytes:
    """What the env needs to go on exactly: the attributes of every layer (Gymnasium's MuJoCo envs pickle
    only their constructor arguments, so their attributes are pickled instead), renderers left out."""
    layers = [{k: v for k, v in vars(layer).items() if k not in ("env", "mujoco_renderer")} for layer in env_layers(env)]
    buffer = io.BytesIO()
    MujocoStatePickler(buffer).dump(layers)
    return zlib.compress(buffer.getvalue(), 1)  # MuJoCo models carry textures, which compress well


def load_env_state(env, state: bytes):
    """Puts env_state() into a fresh env made by make_env with the same id."""
    unpickler = MujocoStateUnpickler(io.BytesIO(zlib.decompress(state)))
    for layer, attributes in zip(env_layers(env), unpickler.load()):
        vars(layer).update(attributes)
    for model, data, mujoco_state in unpickler.restored:
        mujoco.mj_setState(model, data, mujoco_state, MUJOCO_STATE)
        mujoco.mj_forward(model, data)  # the derived quantities; dm_control's unpickling ran it on the old
        mujoco.mj_setState(model, data, mujoco_state, MUJOCO_STATE)  # state, and it overwrites the warm start


def resumed_args(args: Args) -> Args:
    """--resume DIR: the configuration saved in DIR. A flag that would change the experiment is refused."""
    if not os.path.isfile(os.path.join(args.resume, "checkpoint.pt")):
        raise ValueError(f"--resume {args.resume!r}: no checkpoint.pt there (a run stopped before its first "
                         "checkpoint has to start again)")
    with open(os.path.join(args.resume, "config.json")) as f:
        saved = json.load(f)
    defaults = Args()
    missing = [field.name for field in fields(Args) if field.name not in saved]
    if missing:
        raise ValueError(f"--resume {args.resume!r}: its config.json has no {', '.join(missing)} (written by an older "
                         "pebble.py, whose run this one cannot continue); start a new run")
    for field in fields(Args):
        given = getattr(args, field.name)
        if field.name not in RESUME_MAY_CHANGE and given not in (getattr(defaults, field.name), saved[field.name]):
            raise ValueError(f"--{field.name.replace('_', '-')} cannot change when resuming (the run has "
                             f"{saved[field.name]!r}, got {given!r}); start a new run for another configuration")
    return Args(**{**saved, **{name: getattr(args, name) for name in RESUME_MAY_CHANGE}, "output_dir": args.resume})


def load_labels(path: str, obs_dim: int, action_dim: int, segment_len: int) -> dict:
    """--labels-from: the kept labels of saved sessions (a run directory, its labels/ or one .npz), as
    inputs0, inputs1 (obs and action per step), y and the coverage features."""
    files = [path] if os.path.isfile(path) else sorted(glob.glob(os.path.join(path, "labels", "session_*.npz"))
                                                      or glob.glob(os.path.join(path, "session_*.npz")))
    if not files:
        raise ValueError(f"--labels-from {path!r}: no labels found (expected session_*.npz files)")
    sessions = []
    for file in files:
        with np.load(file) as data:
            if data["obs0"].shape[1:] != (segment_len, obs_dim) or data["actions0"].shape[1:] != (segment_len, action_dim):
                raise ValueError(f"--labels-from {file!r}: segments of shape {data['obs0'].shape[1:]} and actions "
                                 f"{data['actions0'].shape[1:]} do not fit this run ({segment_len}, {obs_dim}) and "
                                 f"({segment_len}, {action_dim})")
            sessions.append({k: data[k][data["keep"]] for k in ("obs0", "actions0", "obs1", "actions1", "y")})
    merged = {k: np.concatenate([s[k] for s in sessions]) for k in sessions[0]}
    return {"inputs0": np.concatenate([merged["obs0"], merged["actions0"]], -1),
            "inputs1": np.concatenate([merged["obs1"], merged["actions1"]], -1), "y": merged["y"].astype(np.float32),
            "features": np.concatenate([merged["obs0"].reshape(len(merged["y"]), -1),
                                        merged["obs1"].reshape(len(merged["y"]), -1)], axis=1)}


def evaluate(actor, reward_model, env, episodes, device) -> dict:
    """Mean-action episodes with the true reward (B-Pref's metric), Meta-World success (success at any
    step), and the Pearson correlation of learned and true per-step rewards (the paper's reward analysis)."""
    returns, successes, true_rewards, learned_rewards = [], [], [], []
    for _ in range(episodes):
        obs, _ = env.reset()
        done, episode_return, success = False, 0.0, False
        while not done:
            with torch.no_grad():
                obs_t = torch.as_tensor(obs, device=device)
                action = actor.act(obs_t[None])[0]
                if reward_model is not None:
                    learned_rewards.append(reward_model(torch.cat([obs_t, action])).mean().item())
            obs, reward, terminated, truncated, info = env.step(action.cpu().numpy())
            done = terminated or truncated
            episode_return += reward
            true_rewards.append(reward)
            success = success or bool(info.get("success", False))
        returns.append(episode_return)
        successes.append(success)
    correlation = float("nan")
    if learned_rewards and np.std(learned_rewards) > 0 and np.std(true_rewards) > 0:
        correlation = float(np.corrcoef(learned_rewards, true_rewards)[0, 1])
    return {"episode_return": float(np.mean(returns)), "episode_return_std": float(np.std(returns)),
            "success_rate": float(np.mean(successes)), "reward_correlation": correlation}


def record_video(actor, video_env, device, name: str):
    """--capture-video: one more mean-action episode, saved as videos/<name>.mp4 and not counted in the
    evaluation (so metrics and resumed runs are the same with or without videos)."""
    obs, _ = video_env.reset()
    video_env.start_recording(name)
    done = False
    while not done:
        with torch.no_grad():
            action = actor.act(torch.as_tensor(obs, device=device)[None])[0]
        obs, _, terminated, truncated, _ = video_env.step(action.cpu().numpy())
        done = terminated or truncated
    video_env.stop_recording()  # writes the file now


if __name__ == "__main__":
    args = tyro.cli(Args)
    try:
        args = resumed_args(args) if args.resume else resolve(args)
        env, episode_len = make_env(args.env_id, args.seed)
        problem = check_args(args, episode_len)
        obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
        if not problem and args.labels_from and not args.resume:
            imported_labels = load_labels(args.labels_from, obs_dim, action_dim, args.segment_len)
    except (ValueError, OSError, KeyError) as error:
        fail(str(error))
    if problem:
        fail(problem)
    try:
        env_state(env)
    except Exception as error:  # an env that cannot be pickled cannot be checkpointed
        fail(f"--env-id {args.env_id!r} cannot be checkpointed ({type(error).__name__}: {error})")
    video_env = None
    if args.capture_video:  # render one frame now rather than fail at the first evaluation
        try:
            import moviepy  # noqa: F401

            with warnings.catch_warnings(action="ignore"):  # GLFW warns before it fails without a display
                video_env, _ = make_env(args.env_id, args.seed + 20_000, render_mode="rgb_array")
                video_env.reset()
                video_env.render()
        except Exception as error:
            print(f"error: --capture-video cannot render ({type(error).__name__}: {(str(error) or '-').splitlines()[0]}); it "
                  "needs moviepy and, without a display, MUJOCO_GL=egl (GPU) or MUJOCO_GL=osmesa (CPU)", file=sys.stderr, flush=True)
            os._exit(2)  # not sys.exit: the half-made GL context's finalizer would print a traceback
    run_name = f"{args.env_id}__{args.exp_name}__{args.teacher}__{args.seed}__{int(time.time())}"
    output_dir = args.output_dir or os.path.join("runs", run_name)
    if not args.resume and os.path.isdir(output_dir) and os.listdir(output_dir):
        fail(f"--output-dir {output_dir!r} already holds a run; continue it with --resume {output_dir} or choose another directory")
    config = asdict(args)
    try:
        os.makedirs(os.path.join(output_dir, "labels"), exist_ok=True)
        if not args.resume:
            with open(os.path.join(output_dir, "config.json"), "w") as f:
                json.dump(config, f, indent=2)
    except OSError as error:
        fail(f"cannot write to --output-dir {output_dir!r}: {error.strerror}")
    print("configuration:", json.dumps(config))

    from torch.utils.tensorboard import SummaryWriter

    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, sync_tensorboard=True, config=config, name=run_name, save_code=True)
    checkpoint = None
    if args.resume:
        checkpoint = torch.load(os.path.join(output_dir, "checkpoint.pt"), map_location="cpu", weights_only=False)
        print(f"resuming from the checkpoint at step {checkpoint['progress']['global_step']}")
    writer = SummaryWriter(output_dir, purge_step=checkpoint["progress"]["global_step"] + 1 if checkpoint else None)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in config.items()))

    # Seeding: numpy (pairs and teacher, independent streams), torch (networks, batches), environments
    sampler_seed, teacher_seed = numpy_seeds(args.seed)
    rng = np.random.default_rng(sampler_seed)
    torch.manual_seed(args.seed)
    # MuJoCo's float64 states cast to float32 give denormal numbers (tiny velocities), which make
    # CPU matrix products ~10x slower; flushing them to zero changes nothing measurable
    torch.set_flush_denormal(True)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if args.cuda else "cpu")
    eval_env, _ = make_env(args.env_id, args.seed + 10_000)
    if video_env is not None:  # recorded on demand by record_video
        video_env = gym.wrappers.RecordVideo(video_env, os.path.join(output_dir, "videos"), episode_trigger=lambda _: False)

    actor = Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic = TwinCritic(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic_target = TwinCritic(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic_target.load_state_dict(critic.state_dict())
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=args.learning_rate)
    critic_optimizer = torch.optim.Adam(critic.parameters(), lr=args.learning_rate)
    log_alpha = torch.tensor(math.log(args.init_temperature), device=device, requires_grad=True)
    alpha_optimizer = torch.optim.Adam([log_alpha], lr=args.alpha_lr)
    target_entropy = -float(action_dim)
    buffer = ReplayBuffer(args.buffer_size, obs_dim, action_dim, device)
    intrinsic_stats = RunningMeanStd()

    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = torch.optim.Adam(reward_model.parameters(), lr=args.reward_lr)
    teacher = make_teacher(args.teacher, seed=teacher_seed,
                           **{name: getattr(args, f"teacher_{name}") for name in TEACHER_FIELDS})
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session)
    spent = labels_spent(args.total_timesteps, args.seed_steps + args.unsup_steps, args.feedback_every, session_sizes)
    if spent < args.max_feedback and not args.ground_truth_reward:
        print(f"note: only {spent} of the {args.max_feedback} labels of --max-feedback fit in {args.total_timesteps} "
              f"steps (sessions from step {args.seed_steps + args.unsup_steps + 1}, every {args.feedback_every} steps)")
    preference_inputs0, preference_inputs1, preference_y, labelled_features = [], [], [], []
    feedback_used = sessions_done = 0
    if args.labels_from and not args.resume:  # earlier labels: free, not counted in this run's budget
        preference_inputs0.append(torch.as_tensor(imported_labels["inputs0"], device=device))
        preference_inputs1.append(torch.as_tensor(imported_labels["inputs1"], device=device))
        preference_y.append(torch.as_tensor(imported_labels["y"], device=device))
        labelled_features.append(imported_labels["features"])
        print(f"--labels-from: {len(imported_labels['y'])} labels from {args.labels_from}")

    def sac_update(reward_source: str) -> dict:
        """One SAC step (appendix Eqs. (6)-(7), learned temperature) on a batch whose reward is the learned r_hat, the
        true reward (--ground-truth-reward) or the kNN state entropy (pre-training, Algorithm 2)."""
        batch = buffer.sample(args.batch_size)
        obs, actions, rewards, next_obs, terminated = batch
        if reward_source == "intrinsic":
            global overhead_seconds
            knn_start = time.perf_counter()
            rewards = intrinsic_reward(batch, buffer, args.knn_k)
            intrinsic_stats.update(rewards)
            rewards = rewards / max(intrinsic_stats.std, 1e-8)
            overhead_seconds += time.perf_counter() - knn_start
        alpha = log_alpha.exp().detach()
        with torch.no_grad():
            next_actions, next_log_probs = actor.sample(next_obs)
            target_q = torch.min(*critic_target(next_obs, next_actions)) - alpha * next_log_probs
            # bootstrap through truncation (time limit), not through termination
            target = rewards + args.gamma * (1 - terminated) * target_q
        q1, q2 = critic(obs, actions)
        critic_loss = F.mse_loss(q1, target) + F.mse_loss(q2, target)
        check_finite("critic loss", critic_loss)  # before the step: the networks stay finite
        critic_optimizer.zero_grad()
        critic_loss.backward()
        critic_optimizer.step()

        new_actions, log_probs = actor.sample(obs)
        actor_loss = (alpha * log_probs - torch.min(*critic(obs, new_actions))).mean()
        check_finite("actor loss", actor_loss)
        actor_optimizer.zero_grad()
        actor_loss.backward()
        actor_optimizer.step()
        alpha_loss = (log_alpha.exp() * (-log_probs.detach() - target_entropy)).mean()
        check_finite("temperature loss", alpha_loss)
        alpha_optimizer.zero_grad()
        alpha_loss.backward()
        alpha_optimizer.step()
        return {"critic_loss": critic_loss, "actor_loss": actor_loss, "alpha_loss": alpha_loss,
                "entropy": -log_probs.mean(), "alpha": alpha, "batch_reward": rewards.mean()}

    def update_target():
        with torch.no_grad():
            for param, target_param in zip(critic.parameters(), critic_target.parameters()):
                target_param.lerp_(param, args.tau)

    def usable_episodes() -> list[tuple[int, int]]:
        """(first transition number, length) of complete episodes still whole in the buffer, long enough
        for a segment, the last query_recent_episodes of them."""
        usable = [(s, n) for s, n in completed_episodes if n >= args.segment_len and buffer.added - s <= buffer.capacity]
        return usable[-args.query_recent_episodes:] if args.query_recent_episodes else usable

    def segments(episode_starts, starts):
        """Buffer indices (n, H) of segments, from episodes' first transition numbers and offsets."""
        offsets = torch.arange(args.segment_len, device=device)
        return (torch.as_tensor(episode_starts + starts, device=device)[:, None] + offsets) % buffer.capacity

    def feedback_session(size: int, first: bool) -> int:
        """Algorithm 3, reward learning: SAMPLE() queries, ask SimTeacher, save the labels, learn r_hat."""
        global feedback_used, sessions_done
        usable = usable_episodes()
        episode_starts = np.array([s for s, _ in usable], dtype=np.int64)
        sampler = "uniform" if first else args.sampler  # the first session is always uniform (reference code)
        n_candidates = size if sampler == "uniform" else size * args.candidate_multiplier
        e0, s0, e1, s1 = random_pairs([n for _, n in usable], args.segment_len, n_candidates, rng)
        idx0, idx1 = segments(episode_starts[e0], s0), segments(episode_starts[e1], s1)
        inputs0 = torch.cat([buffer.obs[idx0], buffer.actions[idx0]], dim=-1)
        inputs1 = torch.cat([buffer.obs[idx1], buffer.actions[idx1]], dim=-1)
        features = None  # appendix: the states of both segments concatenated
        if args.sampler.endswith("coverage"):
            features = torch.cat([buffer.obs[idx0].flatten(1), buffer.obs[idx1].flatten(1)], dim=1).cpu().numpy()
        probs = None
        if sampler != "uniform":
            with torch.no_grad():
                probs = torch.sigmoid(reward_model(inputs1).sum(2) - reward_model(inputs0).sum(2))[..., 0].cpu().numpy()
        labelled = np.concatenate(labelled_features) if labelled_features else None
        if sampler == "uniform":  # random_pairs already drew `size` uniform pairs
            chosen = np.arange(size)
        else:
            chosen = select(sampler, size, probs=probs, features=features, labeled_features=labelled, rng=rng)
        idx0, idx1, inputs0, inputs1 = idx0[chosen], idx1[chosen], inputs0[chosen], inputs1[chosen]
        true0, true1 = buffer.true_rewards[idx0][..., 0].cpu().numpy(), buffer.true_rewards[idx1][..., 0].cpu().numpy()

        # Appendix, adaptive thresholds: from the mean true return of the last 10 training episodes
        teacher.set_thresholds(float(np.mean(recent_returns[-10:])), args.segment_len, episode_len)
        y, keep = teacher.label(true0, true1)
        write_atomic_npz(os.path.join(output_dir, "labels", f"session_{sessions_done:04d}.npz"), step=global_step,
                         obs0=buffer.obs[idx0].cpu().numpy(), actions0=buffer.actions[idx0].cpu().numpy(),
                         obs1=buffer.obs[idx1].cpu().numpy(), actions1=buffer.actions[idx1].cpu().numpy(),
                         rewards0=true0, rewards1=true1, y=y, keep=keep)
        feedback_used += size
        sessions_done += 1
        kept = torch.as_tensor(keep, device=device)
        preference_inputs0.append(inputs0[kept])
        preference_inputs1.append(inputs1[kept])
        preference_y.append(torch.as_tensor(y[keep], dtype=torch.float32, device=device))
        if features is not None:
            labelled_features.append(features[chosen][keep])
        writer.add_scalar("feedback/labels", feedback_used, global_step)
        writer.add_scalar("feedback/skipped", int((~keep).sum()), global_step)
        writer.add_scalar("feedback/equal", int((y[keep] == 0.5).sum()), global_step)
        n_labels = sum(len(p) for p in preference_y)
        if n_labels == 0:  # every query so far was skipped: nothing to learn from yet
            print(f"step {global_step}: all {size} queries skipped, the reward model stays as it is")
            return 0
        loss, accuracy = train_reward(reward_model, reward_optimizer, torch.cat(preference_inputs0),
                                      torch.cat(preference_inputs1), torch.cat(preference_y), args, args.reward_epochs)
        writer.add_scalar("reward/loss", loss, global_step)
        writer.add_scalar("reward/accuracy", accuracy, global_step)
        print(f"step {global_step}: feedback session {sessions_done}: {size} queries ({int((~keep).sum())} skipped, "
              f"{int((y[keep] == 0.5).sum())} equal), reward model trained on {n_labels} labels, accuracy {accuracy:.3f}")
        return n_labels

    def reset_critic():
        """PEBBLE, after the first reward update: fresh critics (not actor or temperature), then
        critic_reset_updates SAC steps on the relabelled buffer (reference code)."""
        global critic, critic_optimizer
        counts["critic_resets"] += 1
        critic = TwinCritic(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
        critic_target.load_state_dict(critic.state_dict())
        critic_optimizer = torch.optim.Adam(critic.parameters(), lr=args.learning_rate)
        for i in range(args.critic_reset_updates):
            sac_update("learned")
            if (i + 1) % args.target_update_every == 0:
                update_target()

    # Main loop: Algorithm 3 (PEBBLE) with Algorithm 2 (pre-training) for the first steps
    eval_path = os.path.join(output_dir, "eval.csv")
    eval_fields = ["step", "episode_return", "episode_return_std", "success_rate", "feedback", "reward_correlation",
                   "wall_time", "overhead_seconds"]
    pretrain_end = args.seed_steps + args.unsup_steps
    # The loop's progress: a checkpoint saves these names (and every object above), a resume restores them
    progress_names = ["global_step", "wall_time", "obs", "episode_start", "episode_steps", "episode_return",
                      "completed_episodes", "recent_returns", "next_feedback_step", "feedback_used", "sessions_done",
                      "reward_ready", "sac_steps", "last_eval", "counts", "overhead_seconds", "eval_log"]
    global_step, wall_time, next_feedback_step = 0, 0.0, pretrain_end + 1
    completed_episodes, recent_returns = [], []  # (first transition number, length) of finished episodes; true returns
    obs, _ = env.reset()
    episode_start, episode_steps, episode_return = 0, 0, 0.0
    reward_ready, last_eval, sac_steps = False, float("nan"), 0  # reward_ready: SAC uses buffer.rewards
    counts = dict(updates_on_knn_reward=0, updates_on_learned_reward=0, relabels=0, critic_resets=0)
    overhead_seconds = 0.0  # time in PEBBLE's own parts: kNN reward, queries, reward learning, relabelling, r_hat
    eval_log = []  # the rows of eval.csv

    def learner_state() -> dict:
        """Every network and optimizer by name (reset_critic replaces the critic and its optimizer)."""
        return {"actor": actor, "critic": critic, "critic_target": critic_target, "reward_model": reward_model,
                "actor_optimizer": actor_optimizer, "critic_optimizer": critic_optimizer,
                "alpha_optimizer": alpha_optimizer, "reward_optimizer": reward_optimizer}

    def save_checkpoint():
        """Everything the run needs to go on exactly: networks, optimizers, temperature, replay buffer, kNN
        statistics, preferences, teacher, random generators, environments, counters and logs."""
        save_start, path = time.perf_counter(), os.path.join(output_dir, "checkpoint.pt")
        buffer_part = {name: getattr(buffer, name)[: buffer.size].clone() for name in ReplayBuffer.fields}  # not the empty rest
        atomic_torch_save({
            "progress": {name: globals()[name] for name in progress_names} | {"wall_time": time.time() - start_time},
            **{name: part.state_dict() for name, part in learner_state().items()},
            "log_alpha": log_alpha.detach(), "intrinsic_stats": vars(intrinsic_stats),
            "buffer": buffer_part | {"pos": buffer.pos, "size": buffer.size, "added": buffer.added},
            "preferences": [preference_inputs0, preference_inputs1, preference_y, labelled_features],
            "teacher": teacher, "rng": rng, "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if args.cuda else None,
            "env": env_state(env), "eval_env": env_state(eval_env),
        }, path)
        print(f"step {global_step}: checkpoint saved ({os.path.getsize(path) / 2**20:.1f} MiB in "
              f"{time.perf_counter() - save_start:.1f} s)", flush=True)

    if checkpoint:  # --resume: put every saved part back
        for name, part in learner_state().items():
            part.load_state_dict(checkpoint[name])
        with torch.no_grad():
            log_alpha.copy_(checkpoint["log_alpha"])
        vars(intrinsic_stats).update(checkpoint["intrinsic_stats"])
        for name in ReplayBuffer.fields:
            getattr(buffer, name)[: checkpoint["buffer"]["size"]] = checkpoint["buffer"][name]
        buffer.pos, buffer.size, buffer.added = (checkpoint["buffer"][k] for k in ("pos", "size", "added"))
        preference_inputs0, preference_inputs1, preference_y = ([t.to(device) for t in part] for part in checkpoint["preferences"][:3])
        labelled_features, teacher, rng = checkpoint["preferences"][3], checkpoint["teacher"], checkpoint["rng"]
        torch.set_rng_state(checkpoint["torch_rng"])
        if args.cuda:
            torch.cuda.set_rng_state_all(checkpoint["cuda_rng"])
        load_env_state(env, checkpoint["env"])
        load_env_state(eval_env, checkpoint["eval_env"])
        globals().update(checkpoint["progress"])
        if global_step >= args.total_timesteps:
            fail(f"the run in {output_dir!r} has already finished ({global_step} steps)")
        later_sessions = sorted(glob.glob(os.path.join(output_dir, "labels", "session_*.npz")))[sessions_done:]
        if later_sessions:  # asked after the checkpoint: kept aside, the resumed run asks these sessions again
            aside = os.path.join(output_dir, "labels", f"before_resume_at_step_{global_step}")
            os.makedirs(aside, exist_ok=True)
            for path in later_sessions:
                shutil.move(path, aside)
    with open(f"{eval_path}.tmp", "w", newline="") as f:  # rows logged after the checkpoint are dropped
        csv.DictWriter(f, eval_fields).writeheader()
        csv.DictWriter(f, eval_fields).writerows(eval_log)
    os.replace(f"{eval_path}.tmp", eval_path)

    stop_signal = None

    def request_stop(signum, frame):
        """SIGTERM (a cluster's time limit) or SIGINT (Ctrl-C): checkpoint at the end of this step, then exit."""
        global stop_signal
        stop_signal = signum

    signal.signal(signal.SIGTERM, request_stop)
    signal.signal(signal.SIGINT, request_stop)
    start_time = last_print = time.time() - wall_time
    try:
        for global_step in range(global_step + 1, args.total_timesteps + 1):
            if args.ground_truth_reward and global_step == pretrain_end + 1:
                reset_critic()  # the same schedule as PEBBLE, with the true reward in place of r_hat
                reward_ready = True
            # Feedback sessions: the first at the end of pre-training, then every feedback_every steps
            if (not args.ground_truth_reward and global_step >= next_feedback_step
                    and sessions_done < len(session_sizes) and usable_episodes()):
                session_start = time.perf_counter()
                learned = feedback_session(int(session_sizes[sessions_done]), first=not reward_ready) > 0
                if learned:
                    relabel(buffer, reward_model)
                    counts["relabels"] += 1
                session_seconds = time.perf_counter() - session_start
                overhead_seconds += session_seconds
                writer.add_scalar("time/feedback_session_seconds", session_seconds, global_step)
                if learned and not reward_ready:
                    reset_critic()  # not timed: SAC updates, which the --ground-truth-reward run makes too
                reward_ready = reward_ready or learned
                next_feedback_step = global_step + args.feedback_every

            if global_step <= args.seed_steps:
                action = env.action_space.sample()
            else:
                with torch.no_grad():
                    action = actor.sample(torch.as_tensor(obs, device=device)[None])[0][0].cpu().numpy()
            next_obs, true_reward, terminated, truncated, info = env.step(action)
            if not (math.isfinite(true_reward) and np.isfinite(next_obs).all()):
                raise NonFiniteError(f"non-finite reward ({true_reward}) or observation from the environment")
            learned_reward = 0.0
            if reward_ready and not args.ground_truth_reward:  # Algorithm 3: store r_hat(s_t, a_t) with the transition
                inference_start = time.perf_counter()
                with torch.no_grad():
                    learned_reward = reward_model(torch.as_tensor(np.concatenate([obs, action]), device=device)).mean().item()
                overhead_seconds += time.perf_counter() - inference_start
            buffer.add(obs, action, true_reward if args.ground_truth_reward else learned_reward, true_reward, next_obs, terminated)
            obs, episode_steps, episode_return = next_obs, episode_steps + 1, episode_return + true_reward
            if terminated or truncated:
                completed_episodes.append((episode_start, episode_steps))
                recent_returns = (recent_returns + [episode_return])[-100:]
                writer.add_scalar("charts/episodic_return", episode_return, global_step)
                obs, _ = env.reset()
                episode_start, episode_steps, episode_return = buffer.added, 0, 0.0

            # Policy learning: SAC on the kNN state entropy during pre-training (and while every query was
            # skipped), then on the learned reward (or the true reward with --ground-truth-reward)
            if global_step > args.seed_steps:
                losses = sac_update("learned" if reward_ready else "intrinsic")
                sac_steps += 1
                counts["updates_on_" + ("learned_reward" if reward_ready else "knn_reward")] += 1
                if sac_steps % args.target_update_every == 0:
                    update_target()
                if global_step % 1000 == 0:
                    for name, value in losses.items():
                        writer.add_scalar(f"losses/{name}", float(value), global_step)
                    writer.add_scalar("charts/SPS", int(global_step / (time.time() - start_time)), global_step)

            if global_step % args.eval_every == 0 or global_step == args.total_timesteps:
                result = evaluate(actor, reward_model if reward_ready and not args.ground_truth_reward else None, eval_env, args.eval_episodes, device)
                last_eval = result["episode_return"]
                row = {"step": global_step, **result, "feedback": feedback_used, "wall_time": round(time.time() - start_time, 1),
                       "overhead_seconds": round(overhead_seconds, 1)}
                with open(eval_path, "a", newline="") as f:
                    csv.DictWriter(f, eval_fields).writerow(row)
                eval_log.append(row)
                for name in ("episode_return", "success_rate", "reward_correlation"):
                    writer.add_scalar(f"eval/{name}", result[name], global_step)
                if video_env is not None:
                    record_video(actor, video_env, device, f"step_{global_step}")
            if time.time() - last_print > 10 or global_step == args.total_timesteps:
                last_print = time.time()
                sps = global_step / (last_print - start_time)
                print(f"step {global_step}/{args.total_timesteps} | {sps:.0f} SPS | ETA {(args.total_timesteps - global_step) / sps / 60:.1f} min"
                      f" | last eval return {last_eval:.1f} | labels {feedback_used}/{args.max_feedback}", flush=True)

            if (args.checkpoint_every and global_step % args.checkpoint_every == 0) or stop_signal:
                save_checkpoint()
            if stop_signal:
                print(f"{signal.Signals(stop_signal).name}: checkpoint saved at step {global_step}; "
                      f"continue with --resume {output_dir}", flush=True)
                sys.exit(128 + stop_signal)
    except NonFiniteError as error:
        save_checkpoint()  # the check comes before the optimizer step, so the saved state is finite
        fail(f"{error} at step {global_step}; run stopped, its last finite state is in {output_dir}/checkpoint.pt "
             f"and its labels in {output_dir}/labels", code=3)
    except OSError as error:
        fail(f"writing to {output_dir!r} failed at step {global_step} ({error.strerror or error}); "
             "the last checkpoint there is intact", code=1)

    print(f"done: {counts} (updates_on_learned_reward: the true reward with --ground-truth-reward), "
          f"{sessions_done} feedback sessions, {feedback_used} queries; outputs in {output_dir}")
    torch.save({"actor": actor.state_dict(), "critic": critic.state_dict(), "reward_model": reward_model.state_dict()},
               os.path.join(output_dir, "final_model.pt"))
    for each_env in (env, eval_env, video_env):
        if each_env is not None:
            each_env.close()
    writer.close()
