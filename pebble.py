# PEBBLE (Lee, Smith, Abbeel 2021) as benchmarked by B-Pref (Lee et al. 2021); docs/pebble.md
import contextlib
import csv
import glob
import importlib
import io
import json
import math
import os
import shutil
import signal
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field, fields
from typing import Literal, NamedTuple

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro

from samplers import random_pairs, schedule_sizes, select
from sim_teacher import make_teacher


@dataclass
class Args:
    exp_name: str = "pebble"
    """the name of this experiment (part of the run name)"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """use the GPU when torch sees one (--no-cuda: the CPU)"""
    track: bool = False
    """if toggled, log to Weights & Biases (needs `pip install wandb`)"""
    wandb_project_name: str = "bpref"
    """the Weights & Biases project"""
    capture_video: bool = False
    """if toggled, record each evaluation's first episode to videos/ (headless: MUJOCO_GL=egl)"""
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
    teacher: Literal["oracle", "stoc", "mistake", "skip", "equal", "myopic"] = "oracle"
    """simulated teacher (paper Section 3.3)"""
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
    sampler: Literal[
        "uniform", "disagreement", "entropy", "coverage", "disagreement-coverage", "entropy-coverage"
    ] = "disagreement"
    """query selection (paper Section 4.2)"""
    schedule: Literal["uniform", "decay", "increase"] = "uniform"
    """feedback schedule (paper Section 4.2)"""
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
    """environment steps between evaluations (reference code: 10000)"""
    eval_episodes: int = 10
    """episodes per evaluation (reference code: 10)"""
    ground_truth_reward: bool = False
    """if toggled, train SAC on the true reward with no teacher (the normalisation denominator)"""
    buffer_size: int | None = None
    """replay buffer capacity (default: total_timesteps, as the reference code)"""
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
    """segments are drawn from the last N complete episodes (reference code: 100; 0 = all in the buffer)"""
    critic_reset_updates: int = 100
    """SAC updates on relabelled data right after the critic reset of the first reward update"""


# Paper appendix, Table of PEBBLE hyperparameters (sources of the others: docs/differences.md). Meta-World: feedback
# every 4950 steps, not the paper's 5000, so that all 200 sessions (10,000 labels) fit in 1M steps (planned_labels)
DMC_PRESET = dict(total_timesteps=500_000, max_feedback=1000, feedback_per_session=100, feedback_every=20_000,
                  segment_len=50, hidden_dim=1024, num_layers=2, batch_size=1024, learning_rate=5e-4, reward_epochs=50)
METAWORLD_PRESET = dict(total_timesteps=1_000_000, max_feedback=10_000, feedback_per_session=50, feedback_every=4950,
                        segment_len=25, hidden_dim=256, num_layers=3, batch_size=512, learning_rate=3e-4,
                        reward_epochs=10)
GYM_PRESET = dict(DMC_PRESET, hidden_dim=256, num_layers=2, batch_size=256, learning_rate=3e-4)
PRESETS = {
    "walker-walk": DMC_PRESET,
    "quadruped-walk": dict(DMC_PRESET, total_timesteps=1_000_000, feedback_every=30_000, learning_rate=1e-4),
    "button-press": METAWORLD_PRESET,
    "sweep-into": METAWORLD_PRESET,
}
CPU_SCALE = ("python pebble.py --env-id walker-walk --total-timesteps 100000 --hidden-dim 256 --num-layers 2 "
             "--batch-size 256 --max-feedback 1000 --feedback-per-session 100 --feedback-every 9000")  # README


# Environments
class DMCEnv(gym.Env):
    """A dm_control suite task as a Gymnasium env: flat float32 observations, actions in [-1, 1] (quadruped's bounds
    are not), episodes end by truncation; reset(seed=s) re-seeds the task's random state (the initial pose)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, domain: str, task: str, render_mode: str | None = None):
        from dm_control import suite

        self.dmc, self.render_mode = suite.load(domain, task), render_mode
        obs_dim = sum(int(np.prod(v.shape)) for v in self.dmc.observation_spec().values())
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        spec = self.dmc.action_spec()
        self.low, self.high = spec.minimum, spec.maximum
        self.action_space = gym.spaces.Box(-1.0, 1.0, spec.shape, np.float32)

    def _flat(self, observation):
        return np.concatenate([np.asarray(v, dtype=np.float32).ravel() for v in observation.values()])

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.dmc.task.random.seed(seed)
        return self._flat(self.dmc.reset().observation), {}

    def step(self, action):
        step = self.dmc.step(self.low + (np.asarray(action, np.float64) + 1) / 2 * (self.high - self.low))
        terminated = step.last() and step.discount == 0
        return self._flat(step.observation), step.reward, terminated, step.last() and not terminated, {}

    def render(self):
        return self.dmc.physics.render(height=240, width=320, camera_id=0)


class MetaWorldSeeding(gym.Wrapper):
    """Meta-World's reset ignores its seed argument; its seed() re-seeds the random vector (object and goal)."""

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.unwrapped.seed(seed)
        return self.env.reset(options=options)


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
    try:
        importlib.import_module(module) if module else None
    except ImportError as error:
        raise ValueError(f"--env-id {env_id!r}: cannot import {module!r} ({error})") from None
    if gym_id in gym.registry:
        return "gym"
    raise ValueError(f"--env-id {env_id!r} is not a DMC task (domain-task, e.g. walker-walk), a Meta-World v3 task "
                     "(e.g. button-press) or a registered Gymnasium id (optionally module:id)")


def make_env(env_id: str, render_mode: str | None = None) -> tuple[gym.Env, int]:
    """Returns (env, episode length T); actions in [-1, 1], observations flat float32; seed every reset."""
    kind = env_kind(env_id)
    if kind == "dmc":
        env = DMCEnv(*env_id.split("-", 1), render_mode)
        episode_len = int(env.dmc._step_limit)
    elif kind == "metaworld":
        env = gym.make("Meta-World/MT1", env_name=f"{env_id.removesuffix('-v3')}-v3", render_mode=render_mode,
                       disable_env_checker=True)  # its checker warns about the hidden goal's zero bounds
        env.get_wrapper_attr("toggle_terminate_on_success")(False)  # B-Pref: fixed 500-step episodes
        # Reference code (utils.make_metaworld_env): a fresh goal from the task's whole range at every reset, not
        # one of MT1's 50 fixed goals. One task is set for its settings; then the random vector (object and goal
        # positions) is unfrozen and drawn from the env's own generator, seeded at each reset. The goal is hidden
        # (its 3 entries are zeros), as in the reference's v2 envs, which were partially observable by default
        env.unwrapped.set_task(env.get_wrapper_attr("tasks")[0])
        env.unwrapped._partially_observable = True
        env.get_wrapper_attr("toggle_sample_tasks_on_reset")(False)
        env.unwrapped._freeze_rand_vec, env.unwrapped.seeded_rand_vec = False, True
        env, episode_len = MetaWorldSeeding(env), env.spec.max_episode_steps or 500
    else:
        env = gym.make(env_id, **({"render_mode": render_mode} if render_mode else {}))
        episode_len = env.spec.max_episode_steps
        if not isinstance(env.action_space, gym.spaces.Box) or not isinstance(env.observation_space, gym.spaces.Box):
            raise ValueError(f"--env-id {env_id!r} must have Box observation and action spaces")
        if episode_len is None:
            raise ValueError(f"--env-id {env_id!r} has no time limit (max_episode_steps), needed for the thresholds")
    bounds = (np.full(env.action_space.shape, bound, np.float32) for bound in (-1, 1))  # float32: no casting warning
    env = gym.wrappers.RescaleAction(env, *bounds)
    space = gym.spaces.Box(-np.inf, np.inf, env.observation_space.shape, np.float32)
    return gym.wrappers.TransformObservation(env, lambda obs: np.asarray(obs, dtype=np.float32), space), episode_len


TRAIN_STREAM, EVAL_STREAM = 0, 1


def episode_seed(run_seed: int, stream: int, episode: int) -> int:
    """The reset seed of one episode of the training or evaluation env: any episode can be played again alone (a
    checkpoint needs no environment state), and runs with different seeds share no episode seed."""
    return int(np.random.SeedSequence([run_seed, stream, episode]).generate_state(1)[0])


def numpy_seeds(seed: int) -> tuple[np.random.SeedSequence, ...]:
    """Independent streams for the query sampler, the teacher and the seed steps' random actions."""
    return tuple(np.random.SeedSequence(seed).spawn(3))


# Networks
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
        return torch.tanh(pre_tanh), tanh_gaussian_log_prob(mean, log_std, pre_tanh)


class TwinCritic(nn.Module):
    """Two Q-networks, Q(s, a) -> (q1, q2)."""

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


# Algorithm: the math a reader must trust (each unit-tested), the replay buffer, reward learning
def tanh_gaussian_log_prob(mean, log_std, pre_tanh) -> torch.Tensor:
    """log pi(a|s) of a = tanh(u), u ~ N(mean, exp(log_std)^2), summed over the action (batch, 1): the Gaussian's
    log-density minus log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)) (SAC paper, appendix C; stable form)."""
    gaussian = -0.5 * ((pre_tanh - mean) / log_std.exp()) ** 2 - log_std - 0.5 * math.log(2 * math.pi)
    return (gaussian - 2 * (math.log(2) - pre_tanh - F.softplus(-2 * pre_tanh))).sum(-1, keepdim=True)


def sac_critic_loss(q1, q2, rewards, terminated, next_q, next_log_prob, alpha, gamma) -> torch.Tensor:
    """Appendix Eq. (6), both critics: target r + gamma (1 - terminated) (min target Q(s', a') - alpha log pi(a'|s')),
    a' ~ pi(s'); it bootstraps through a time limit, not through a termination."""
    target = (rewards + gamma * (1 - terminated) * (next_q - alpha * next_log_prob)).detach()
    return F.mse_loss(q1, target) + F.mse_loss(q2, target)


def sac_actor_loss(log_prob, q1, q2, alpha) -> torch.Tensor:
    """Appendix Eq. (7): E[alpha log pi(a|s) - Q(s, a)], a ~ pi(s), with the smaller of the two critics."""
    return (alpha * log_prob - torch.min(q1, q2)).mean()


def temperature_loss(log_alpha, log_prob, target_entropy: float) -> torch.Tensor:
    """SAC's learned temperature (reference code: agent/sac.py): alpha grows while the policy's entropy -log pi is
    below the target entropy (-action dim), and shrinks while above."""
    return (log_alpha.exp() * (-log_prob.detach() - target_entropy)).mean()


def optimize(optimizer, loss: torch.Tensor, name: str):
    """One gradient step; a non-finite loss stops the run before it, so the networks stay finite."""
    if not torch.isfinite(loss).all():
        raise FloatingPointError(f"non-finite {name} ({loss.detach().flatten()[0].item()})")
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()


class Batch(NamedTuple):  # transitions sampled from the replay buffer, one row each
    obs: torch.Tensor
    actions: torch.Tensor
    rewards: torch.Tensor
    next_obs: torch.Tensor
    terminated: torch.Tensor


def sac_update(batch, rewards, actor, critic, critic_target, log_alpha, actor_opt, critic_opt, alpha_opt, gamma):
    """One SAC step on a batch whose rewards are r_hat, the true reward or the kNN state entropy."""
    alpha = log_alpha.exp().detach()
    with torch.no_grad():
        next_actions, next_log_prob = actor.sample(batch.next_obs)
        next_q = torch.min(*critic_target(batch.next_obs, next_actions))
    q1, q2 = critic(batch.obs, batch.actions)
    critic_loss = sac_critic_loss(q1, q2, rewards, batch.terminated, next_q, next_log_prob, alpha, gamma)
    optimize(critic_opt, critic_loss, "critic loss")
    actions, log_prob = actor.sample(batch.obs)
    actor_loss = sac_actor_loss(log_prob, *critic(batch.obs, actions), alpha)
    optimize(actor_opt, actor_loss, "actor loss")
    alpha_loss = temperature_loss(log_alpha, log_prob, -batch.actions.shape[-1])
    optimize(alpha_opt, alpha_loss, "temperature loss")
    losses = {"critic_loss": critic_loss, "actor_loss": actor_loss, "alpha_loss": alpha_loss,
              "entropy": -log_prob.mean(), "alpha": alpha, "batch_reward": rewards.mean()}
    return {name: value.detach() for name, value in losses.items()}


def soft_update(critic: nn.Module, critic_target: nn.Module, tau: float):
    with torch.no_grad():
        for param, target_param in zip(critic.parameters(), critic_target.parameters()):
            target_param.lerp_(param, tau)


class ReplayBuffer:
    """On the training device; `rewards` is r_hat (relabelled), `added` counts every transition ever stored."""
    fields = ("obs", "actions", "rewards", "true_rewards", "next_obs", "terminated")

    def __init__(self, capacity, obs_dim, action_dim, device):
        self.capacity, self.size, self.pos, self.added, self.device = capacity, 0, 0, 0, device
        self.obs, self.next_obs = (torch.zeros(capacity, obs_dim, device=device) for _ in range(2))
        self.actions = torch.zeros(capacity, action_dim, device=device)
        self.rewards, self.true_rewards, self.terminated = (torch.zeros(capacity, 1, device=device) for _ in range(3))

    def add(self, obs, action, reward, true_reward, next_obs, terminated):
        i = self.pos
        self.obs[i], self.actions[i], self.next_obs[i] = (torch.as_tensor(x) for x in (obs, action, next_obs))
        self.rewards[i], self.true_rewards[i], self.terminated[i] = reward, true_reward, float(terminated)
        self.pos, self.size, self.added = (i + 1) % self.capacity, min(self.size + 1, self.capacity), self.added + 1

    def sample(self, batch_size):
        idx = torch.randint(self.size, (batch_size,), device=self.device)
        return Batch(self.obs[idx], self.actions[idx], self.rewards[idx], self.next_obs[idx], self.terminated[idx])


def knn_distance(states: torch.Tensor, reference: torch.Tensor, k: int, chunk: int = 4096) -> torch.Tensor:
    """Eq. (8) without the log (docs): distance to the k-th nearest neighbour in `reference`, not counting the
    state itself (the (k+1)-th smallest); chunk x chunk blocks bound the memory, the k+1 nearest merged per block."""
    kth = []
    for i in range(0, len(states), chunk):
        nearest = torch.empty(len(states[i : i + chunk]), 0, device=states.device)
        for j in range(0, len(reference), chunk):
            candidates = torch.cat([nearest, torch.cdist(states[i : i + chunk], reference[j : j + chunk])], dim=1)
            nearest = candidates.topk(min(k + 1, candidates.shape[1]), dim=1, largest=False).values
        kth.append(nearest[:, -1:])
    return torch.cat(kth)


def intrinsic_reward(batch: Batch, buffer: ReplayBuffer, k: int) -> torch.Tensor:
    """Algorithm 2's r_int(s_t) before normalisation: kNN distance of the batch's s_t (obs, not next_obs; reference
    code: agent/sac.py) among all states in the buffer (s_t is one of them: knn_distance skips its zero distance)."""
    return knn_distance(batch.obs, buffer.obs[: buffer.size], k)


class RunningMeanStd:  # Chan et al.'s parallel update (the reference code's was wrong)
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


def relabel(buffer: ReplayBuffer, reward_model: RewardEnsemble, chunk: int = 16384):
    """PEBBLE's relabelling: r_hat = ensemble mean for every stored transition, the wrapped buffer's too."""
    with torch.no_grad():
        for i in range(0, buffer.size, chunk):
            obs_action = torch.cat([buffer.obs[i : i + chunk], buffer.actions[i : i + chunk]], dim=-1)
            buffer.rewards[i : i + chunk] = reward_model(obs_action).mean(0)


def usable_episodes(completed: list, buffer: ReplayBuffer, segment_len: int, recent: int) -> list:
    """The query pool: the last `recent` (0 = all) complete episodes still whole in the buffer, long enough."""
    usable = [(s, n) for s, n in completed if n >= segment_len and buffer.added - s <= buffer.capacity]
    return usable[-recent:] if recent else usable


def preference_loss(segment_returns: torch.Tensor, y: torch.Tensor, label_smoothing: float = 0.0) -> torch.Tensor:
    """Eq. (3): cross-entropy of P[sigma1 > sigma0] = softmax(sum r_hat) (Eq. (2)) against (1 - y, y), (batch, 2)."""
    target = (1 - label_smoothing) * y + label_smoothing / 2
    log_probs = F.log_softmax(segment_returns, dim=-1)
    return -((1 - target) * log_probs[:, 0] + target * log_probs[:, 1]).mean()


def preference_accuracy(segment_returns: torch.Tensor, y: torch.Tensor) -> tuple[int, int]:
    """(correct, counted) over strict labels: an equal label has no right side (the reference code counted it)."""
    strict = y != 0.5
    predicted_second = segment_returns[:, 1] > segment_returns[:, 0]
    return int((predicted_second == (y > 0.5))[strict].sum()), int(strict.sum())


def train_reward(reward_model, optimizer, inputs0, inputs1, y, args, max_epochs) -> tuple[float, float]:
    """Algorithm 3, reward learning: up to max_epochs passes over D, one shuffle per member, until 97% accuracy."""
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
            optimize(optimizer, loss, "reward-model loss")
            losses.append(loss.item() / len(reward_model.members))
        loss_value = float(np.mean(losses))
        accuracy = correct / counted if counted else float("nan")
        if accuracy > 0.97:
            break
    return loss_value, accuracy


def planned_labels(total_timesteps: int, pretrain_steps: int, feedback_every: int, session_sizes) -> int:
    """Labels asked: session i at step pretrain_steps + 1 + i * feedback_every while <= total_timesteps (assumes a
    complete episode by the end of pre-training, as on DMC and Meta-World; a later first session asks fewer)."""
    n_sessions = max(0, (total_timesteps - pretrain_steps - 1) // feedback_every + 1)
    return int(np.sum(session_sizes[:n_sessions]))


# Plumbing
def parse_args() -> Args:
    """tyro's command line; its error box (an unknown choice, a word for a number) becomes one `error:` line."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            args = tyro.cli(Args)
    except SystemExit as error:
        if not error.code:  # --help
            raise
        text = []
        for line in captured.getvalue().splitlines()[1:]:  # the box's lines after its title
            if line.strip("│ ").startswith("──"):  # the rule before "For full helptext"
                break
            text.append(line.strip("│╭╰╮╯ "))
        fail(" ".join(line for line in text if line) or captured.getvalue().strip())
    sys.stderr.write(captured.getvalue())  # tyro's warnings, if any
    return args


TEACHER_FIELDS = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal")  # SimTeacher's, --teacher-* here
RESUME_MAY_CHANGE = ("resume", "checkpoint_every", "cuda", "track", "wandb_project_name", "capture_video")


def resolve(args: Args) -> Args:
    """The run's configuration. --resume DIR: the one saved in DIR, refusing a flag that would change the
    experiment. Otherwise every field left None from the task's preset and the teacher's; a flag the user gave wins."""
    if args.resume:
        if not os.path.isfile(os.path.join(args.resume, "checkpoint.pt")):
            raise ValueError(f"--resume {args.resume!r}: no checkpoint.pt there (a run stopped before its first "
                             "checkpoint has to start again)")
        with open(os.path.join(args.resume, "config.json")) as f:
            saved = json.load(f)
        missing = [field.name for field in fields(Args) if field.name not in saved]
        if missing:
            raise ValueError(f"--resume {args.resume!r}: its config.json has no {', '.join(missing)} (written by an "
                             "older pebble.py, whose run this one cannot continue); start a new run")
        for name, default in ((field.name, field.default) for field in fields(Args)):
            if name not in RESUME_MAY_CHANGE and getattr(args, name) not in (default, saved[name]):
                raise ValueError(f"--{name.replace('_', '-')} cannot change when resuming (the run has "
                                 f"{saved[name]!r}, got {getattr(args, name)!r}); start a new run for another "
                                 "configuration")
        return Args(**{**saved, **{name: getattr(args, name) for name in RESUME_MAY_CHANGE}, "output_dir": args.resume})
    family = {"dmc": DMC_PRESET, "metaworld": METAWORLD_PRESET, "gym": GYM_PRESET}[env_kind(args.env_id)]
    teacher = make_teacher(args.teacher)
    defaults = PRESETS.get(args.env_id.removesuffix("-v3"), family) | {
        f"teacher_{name}": getattr(teacher, name) for name in TEACHER_FIELDS}
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    args.buffer_size = args.buffer_size or args.total_timesteps
    return args


def check_args(args: Args, episode_len: int) -> str | None:
    """The first problem with the configuration as one line, or None."""
    a, pretrain = args, args.seed_steps + args.unsup_steps
    checks = [  # (field, ok, the rule)
        ("seed", a.seed >= 0, ">= 0"), ("teacher_beta", a.teacher_beta >= 0, ">= 0 (inf = rational)"),
        ("teacher_gamma", 0 < a.teacher_gamma <= 1, "in (0, 1]"),
        *[(n, 0 <= getattr(a, n) <= 1, "in [0, 1]") for n in ("teacher_eps_mistake", "teacher_eps_skip",
                                                              "teacher_eps_equal")],
        *[(n, getattr(a, n) >= 1, ">= 1") for n in (
            "max_feedback", "feedback_every", "hidden_dim", "num_layers", "batch_size", "reward_batch_size",
            "reward_ensemble_size", "eval_every", "eval_episodes", "knn_k", "candidate_multiplier", "reward_epochs",
            "target_update_every")],
        *[(n, getattr(a, n) >= 0, ">= 0") for n in ("seed_steps", "unsup_steps", "critic_reset_updates",
                                                    "query_recent_episodes", "checkpoint_every")],
        *[(n, getattr(a, n) > 0, "> 0") for n in ("learning_rate", "alpha_lr", "reward_lr", "init_temperature")],
        *[(n, 0 < getattr(a, n) <= 1, "in (0, 1]") for n in ("gamma", "tau")],
        ("label_smoothing", 0 <= a.label_smoothing < 1, "in [0, 1)"),
        ("feedback_per_session", 1 <= a.feedback_per_session <= a.max_feedback,
         f"in [1, --max-feedback={a.max_feedback}]"),
        ("segment_len", 1 <= a.segment_len <= episode_len, f"in [1, {episode_len}] (the episode length of {a.env_id})"),
        ("total_timesteps", a.total_timesteps > pretrain, f"> --seed-steps + --unsup-steps ({pretrain})"),
        ("buffer_size", a.buffer_size >= max(a.batch_size, episode_len), ">= max(batch size, episode length)"),
    ]
    return next((f"--{name.replace('_', '-')} must be {rule}, got {getattr(a, name)}" for name, ok, rule in checks
                 if not ok), None)


def fail(message: str, code: int = 2):
    print(f"error: {message}", file=sys.stderr)
    sys.exit(code)


def save_labels(path: str, **arrays):
    """labels/session_NNNN.npz: written, then renamed, so that a kill never leaves a half-written file."""
    np.savez(f"{path}.tmp.npz", **arrays)
    os.replace(f"{path}.tmp.npz", path)


def load_labels(path: str, obs_dim: int, action_dim: int, segment_len: int) -> dict:
    """--labels-from: the kept labels of saved sessions (a run directory, its labels/ or one .npz), as
    inputs0, inputs1 (obs and action per step), y and the coverage features."""
    files = [path] if os.path.isfile(path) else sorted(glob.glob(os.path.join(path, "labels", "session_*.npz"))
                                                      or glob.glob(os.path.join(path, "session_*.npz")))
    if not files:
        raise ValueError(f"--labels-from {path!r}: no labels found (expected session_*.npz files)")
    sessions = [dict(np.load(file)) for file in files]
    for file, s in zip(files, sessions):
        if s["obs0"].shape[1:] != (segment_len, obs_dim) or s["actions0"].shape[1:] != (segment_len, action_dim):
            raise ValueError(f"--labels-from {file!r}: segments of shape {s['obs0'].shape[1:]} and actions "
                             f"{s['actions0'].shape[1:]} do not fit this run ({segment_len}, {obs_dim}) and "
                             f"({segment_len}, {action_dim})")
    kept = {key: np.concatenate([s[key][s["keep"]] for s in sessions])
            for key in ("obs0", "actions0", "obs1", "actions1", "y")}
    n = len(kept["y"])
    return {"inputs0": np.concatenate([kept["obs0"], kept["actions0"]], -1), "y": kept["y"].astype(np.float32),
            "inputs1": np.concatenate([kept["obs1"], kept["actions1"]], -1),
            "features": np.concatenate([kept["obs0"].reshape(n, -1), kept["obs1"].reshape(n, -1)], axis=1)}


def save_checkpoint(path: str, state: dict):
    """Serialised in memory (a full disk is then a plain OSError), written to a temporary file, flushed to disk and
    renamed: a kill during the write leaves the previous checkpoint intact."""
    tmp, serialised = f"{path}.tmp", io.BytesIO()
    torch.save(state, serialised)
    try:
        with open(tmp, "wb") as f:
            f.write(serialised.getbuffer())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def evaluate(actor, reward_model, env, seeds: list[int], device) -> dict:
    """Mean-action episodes (one per reset seed) with the true reward (B-Pref's metric), Meta-World success (at any
    step), and the Pearson correlation of learned and true per-step rewards (the paper's reward analysis)."""
    returns, successes, true_rewards, learned_rewards = [], [], [], []
    for seed in seeds:
        (obs, _), done = env.reset(seed=seed), False
        returns.append(0.0)
        successes.append(False)
        while not done:
            with torch.no_grad():
                obs_t = torch.as_tensor(obs, device=device)
                action = torch.tanh(actor(obs_t)[0])  # the mean action
                if reward_model is not None:
                    learned_rewards.append(reward_model(torch.cat([obs_t, action])).mean().item())
            obs, reward, terminated, truncated, info = env.step(action.cpu().numpy())
            done, returns[-1] = terminated or truncated, returns[-1] + reward
            true_rewards.append(reward)
            successes[-1] = successes[-1] or bool(info.get("success", False))
    correlation = float("nan")
    if learned_rewards and np.std(learned_rewards) > 0 and np.std(true_rewards) > 0:
        correlation = float(np.corrcoef(learned_rewards, true_rewards)[0, 1])
    return {"episode_return": float(np.mean(returns)), "episode_return_std": float(np.std(returns)),
            "success_rate": float(np.mean(successes)), "reward_correlation": correlation}


def seconds_per_update(args: Args, obs_dim: int, action_dim: int, repeats: int = 3) -> float:
    """One SAC update's time at the run's sizes, on throwaway networks and data, timed before the run seeds torch."""
    nets = [cls(obs_dim, action_dim, args.hidden_dim, args.num_layers) for cls in (Actor, TwinCritic, TwinCritic)]
    log_alpha = torch.zeros((), requires_grad=True)
    optimizers = [torch.optim.Adam(p) for p in (nets[0].parameters(), nets[1].parameters(), [log_alpha])]
    batch = Batch(*(torch.rand(args.batch_size, dim) for dim in (obs_dim, action_dim, 1, obs_dim, 1)))
    sac_update(batch, batch.rewards, *nets, log_alpha, *optimizers, args.gamma)  # warm-up
    start = time.perf_counter()
    for _ in range(repeats):
        sac_update(batch, batch.rewards, *nets, log_alpha, *optimizers, args.gamma)
    return (time.perf_counter() - start) / repeats


@dataclass
class Progress:
    """Every counter and log the main loop carries. The checkpoint saves it with asdict() and a resume restores it
    with Progress(**saved), so a new field is checkpointed by construction."""

    global_step: int = 0
    next_feedback_step: int = 0
    episode_start: int = 0  # buffer.added at the current episode's first transition
    episode_steps: int = 0
    episode_return: float = 0.0
    completed_episodes: list = field(default_factory=list)  # (first transition number, length) of each
    recent_returns: list = field(default_factory=list)  # true returns of the last 10 complete episodes
    reward_ready: bool = False  # SAC trains on buffer.rewards: r_hat (or the true reward, --ground-truth-reward)
    sessions_done: int = 0
    feedback_used: int = 0
    eval_rows: list = field(default_factory=list)  # eval.csv
    last_eval: float = math.nan
    updates_on_knn_reward: int = 0
    updates_on_learned_reward: int = 0  # the true reward with --ground-truth-reward
    relabels: int = 0
    critic_resets: int = 0
    overhead_seconds: float = 0.0  # PEBBLE's own parts: kNN reward, queries, reward learning, relabelling, r_hat
    wall_time: float = 0.0

    @contextlib.contextmanager
    def overhead(self):
        start = time.perf_counter()
        yield
        self.overhead_seconds += time.perf_counter() - start


if __name__ == "__main__":
    args = parse_args()
    try:
        args = resolve(args)
        env, episode_len = make_env(args.env_id)
        obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
        problem, imported = check_args(args, episode_len), None
        if not problem and args.labels_from and not args.resume:
            imported = load_labels(args.labels_from, obs_dim, action_dim, args.segment_len)
    except (ValueError, OSError, KeyError) as error:
        fail(str(error))
    if problem:
        fail(problem)
    eval_env, _ = make_env(args.env_id, render_mode="rgb_array" if args.capture_video else None)
    if args.capture_video:  # render one frame now rather than fail at the first evaluation
        try:
            import moviepy  # noqa: F401

            with warnings.catch_warnings(action="ignore"):  # GLFW warns before it fails without a display
                eval_env.reset(seed=0)
                eval_env.render()
        except Exception as error:
            print(f"error: --capture-video cannot render ({type(error).__name__}: "
                  f"{(str(error) or '-').splitlines()[0]}); it needs moviepy and, without a display, MUJOCO_GL=egl "
                  "(GPU) or MUJOCO_GL=osmesa (CPU)", file=sys.stderr, flush=True)
            os._exit(2)  # not sys.exit: the half-made GL context's finalizer would print a traceback
    run_name = f"{args.env_id}__{args.exp_name}__{args.teacher}__{args.seed}__{int(time.time())}"
    output_dir = args.output_dir or os.path.join("runs", run_name)
    if not args.resume and os.path.isdir(output_dir) and os.listdir(output_dir):
        fail(f"--output-dir {output_dir!r} already holds a run; continue it with --resume {output_dir} or choose "
             "another directory")
    config = asdict(args)
    try:
        os.makedirs(os.path.join(output_dir, "labels"), exist_ok=True)
        if not args.resume:
            with open(os.path.join(output_dir, "config.json"), "w") as f:
                json.dump(config, f, indent=2)
    except OSError as error:
        fail(f"cannot write to --output-dir {output_dir!r}: {error.strerror}")
    print("configuration:\n" + "\n".join(f"  {key}: {value}" for key, value in config.items()))

    from torch.utils.tensorboard import SummaryWriter

    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, sync_tensorboard=True, config=config, name=run_name, save_code=True)
    checkpoint_path = os.path.join(output_dir, "checkpoint.pt")
    checkpoint = torch.load(checkpoint_path, map_location="cpu", weights_only=False) if args.resume else None
    writer = SummaryWriter(output_dir, purge_step=checkpoint["progress"]["global_step"] + 1 if checkpoint else None)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in config.items()))
    device = torch.device("cuda" if args.cuda and torch.cuda.is_available() else "cpu")
    print(f"device: {device} (" + (torch.cuda.get_device_name(device) if device.type == "cuda"
                                   else "torch sees no GPU" if args.cuda else "--no-cuda") + ")", flush=True)
    if device.type == "cpu" and args.hidden_dim * args.batch_size > 256 * 256:  # above the README's CPU scale
        seconds = seconds_per_update(args, obs_dim, action_dim)
        print(f"note: one SAC update of this size takes {1000 * seconds:.0f} ms on this CPU, so this run needs about "
              f"{seconds * (args.total_timesteps - args.seed_steps) / 3600:.0f} hours; use a GPU, or the README's CPU "
              f"scale: {CPU_SCALE}", flush=True)

    # Seeding: numpy (pairs, teacher, seed steps' actions: independent streams), torch (networks, batches);
    # each environment reset has its own seed (episode_seed)
    sampler_seed, teacher_seed, action_seed = numpy_seeds(args.seed)
    rng, action_rng = np.random.default_rng(sampler_seed), np.random.default_rng(action_seed)
    torch.manual_seed(args.seed)
    # MuJoCo's float64 states cast to float32 give denormal numbers (tiny velocities), which make
    # CPU matrix products ~10x slower; flushing them to zero changes nothing measurable
    torch.set_flush_denormal(True)
    torch.backends.cudnn.deterministic = args.torch_deterministic

    actor = Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic = TwinCritic(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic_target = TwinCritic(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic_target.load_state_dict(critic.state_dict())
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=args.learning_rate)
    critic_optimizer = torch.optim.Adam(critic.parameters(), lr=args.learning_rate)
    log_alpha = torch.tensor(math.log(args.init_temperature), device=device, requires_grad=True)
    alpha_optimizer = torch.optim.Adam([log_alpha], lr=args.alpha_lr)
    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = torch.optim.Adam(reward_model.parameters(), lr=args.reward_lr)
    learner = {"actor": actor, "critic": critic, "critic_target": critic_target, "reward_model": reward_model,
               "actor_optimizer": actor_optimizer, "critic_optimizer": critic_optimizer,
               "alpha_optimizer": alpha_optimizer, "reward_optimizer": reward_optimizer}  # checkpointed by state_dict
    buffer = ReplayBuffer(args.buffer_size, obs_dim, action_dim, device)
    intrinsic_stats = RunningMeanStd()
    teacher = make_teacher(args.teacher, seed=teacher_seed,
                           **{name: getattr(args, f"teacher_{name}") for name in TEACHER_FIELDS})
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session)
    pretrain_end = args.seed_steps + args.unsup_steps
    planned = planned_labels(args.total_timesteps, pretrain_end, args.feedback_every, session_sizes)
    if planned < args.max_feedback and not args.ground_truth_reward:
        print(f"note: only {planned} of the {args.max_feedback} labels of --max-feedback fit in {args.total_timesteps} "
              f"steps (sessions from step {pretrain_end + 1}, every {args.feedback_every} steps)")
    preferences = {"inputs0": [], "inputs1": [], "y": [], "features": []}  # the labelled dataset D of Algorithm 3
    if imported is not None:  # earlier labels: free, not counted in this run's budget
        for key, part in imported.items():
            preferences[key].append(part if key == "features" else torch.as_tensor(part, device=device))
        print(f"--labels-from: {len(imported['y'])} labels from {args.labels_from}")
    progress = Progress(next_feedback_step=pretrain_end + 1)

    if checkpoint:  # --resume: every part back, key by key (the keys that checkpoint_state below writes)
        print(f"resuming from the checkpoint at step {checkpoint['progress']['global_step']}")
        for name, part in learner.items():
            part.load_state_dict(checkpoint[name])
        with torch.no_grad():
            log_alpha.copy_(checkpoint["log_alpha"])
        vars(intrinsic_stats).update(checkpoint["intrinsic_stats"])
        for name in ReplayBuffer.fields:
            getattr(buffer, name)[: checkpoint["buffer"]["size"]] = checkpoint["buffer"][name]
        buffer.pos, buffer.size, buffer.added = (checkpoint["buffer"][k] for k in ("pos", "size", "added"))
        preferences = {key: [part.to(device) if torch.is_tensor(part) else part for part in parts]
                       for key, parts in checkpoint["preferences"].items()}
        teacher = checkpoint["teacher"]
        rng.bit_generator.state, action_rng.bit_generator.state = checkpoint["rng"], checkpoint["action_rng"]
        torch.set_rng_state(checkpoint["torch_rng"])
        if device.type == "cuda" and checkpoint["cuda_rng"] is not None:
            torch.cuda.set_rng_state_all(checkpoint["cuda_rng"])
        progress = Progress(**checkpoint["progress"])
        if progress.global_step >= args.total_timesteps:
            fail(f"the run in {output_dir!r} has already finished ({progress.global_step} steps)")
        later_sessions = sorted(glob.glob(os.path.join(output_dir, "labels", "session_*.npz")))[progress.sessions_done:]
        if later_sessions:  # asked after the checkpoint: kept aside, the resumed run asks these sessions again
            aside = os.path.join(output_dir, "labels", f"before_resume_at_step_{progress.global_step}")
            os.makedirs(aside, exist_ok=True)
            for path in later_sessions:
                shutil.move(path, aside)
    eval_path = os.path.join(output_dir, "eval.csv")
    eval_fields = ["step", "episode_return", "episode_return_std", "success_rate", "feedback", "reward_correlation",
                   "wall_time", "overhead_seconds"]
    with open(f"{eval_path}.tmp", "w", newline="") as f:  # rows logged after the checkpoint are dropped
        csv.DictWriter(f, eval_fields).writeheader()
        csv.DictWriter(f, eval_fields).writerows(progress.eval_rows)
    os.replace(f"{eval_path}.tmp", eval_path)
    # The training env as at the checkpoint: the current episode's seeded reset, then its actions replayed from the
    # buffer (MuJoCo is deterministic, so the env is exactly where it was; a new run has none to replay)
    obs, _ = env.reset(seed=episode_seed(args.seed, TRAIN_STREAM, len(progress.completed_episodes)))
    for i in range(progress.episode_steps):
        obs = env.step(buffer.actions[(progress.episode_start + i) % buffer.capacity].cpu().numpy())[0]
    if args.capture_video:  # the first episode of each evaluation, as videos/step_N-episode-M.mp4
        eval_env = gym.wrappers.RecordVideo(eval_env, os.path.join(output_dir, "videos"),
                                            episode_trigger=lambda episode: episode % args.eval_episodes == 0)

    def checkpoint_state() -> dict:
        """Everything the run needs to go on exactly; the environments need nothing (seeded resets, replay)."""
        return {"progress": asdict(progress) | {"wall_time": time.time() - start_time},
                **{name: part.state_dict() for name, part in learner.items()}, "log_alpha": log_alpha.detach(),
                "intrinsic_stats": vars(intrinsic_stats), "preferences": preferences, "teacher": teacher,
                "buffer": {name: getattr(buffer, name)[: buffer.size].clone() for name in ReplayBuffer.fields}
                | {"pos": buffer.pos, "size": buffer.size, "added": buffer.added},
                "rng": rng.bit_generator.state, "action_rng": action_rng.bit_generator.state,
                "torch_rng": torch.get_rng_state(),
                "cuda_rng": torch.cuda.get_rng_state_all() if device.type == "cuda" else None}

    stop = []  # SIGTERM (a cluster's time limit) or SIGINT (Ctrl-C): checkpoint at the end of this step, then exit
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    signal.signal(signal.SIGINT, lambda signum, frame: stop.append(signum))
    start_time = last_print = time.time() - progress.wall_time
    # Main loop: Algorithm 3 (PEBBLE) with Algorithm 2 (unsupervised pre-training) for the first steps
    try:
        for global_step in range(progress.global_step + 1, args.total_timesteps + 1):
            progress.global_step = global_step
            reset_critic = args.ground_truth_reward and global_step == pretrain_end + 1  # as PEBBLE, on the true reward
            # Feedback session (Algorithm 3, reward learning): the first at the end of pre-training, then every
            # feedback_every steps: SAMPLE() queries, ask the teacher, save the labels, learn r_hat, relabel
            if (not args.ground_truth_reward and global_step >= progress.next_feedback_step
                    and progress.sessions_done < len(session_sizes) and (usable := usable_episodes(
                        progress.completed_episodes, buffer, args.segment_len, args.query_recent_episodes))):
                size = int(session_sizes[progress.sessions_done])
                with progress.overhead():
                    sampler = args.sampler if progress.reward_ready else "uniform"  # reference code: the first uniform
                    n_candidates = size if sampler == "uniform" else size * args.candidate_multiplier
                    e0, s0, e1, s1 = random_pairs([n for _, n in usable], args.segment_len, n_candidates, rng)
                    starts = np.array([s for s, _ in usable], dtype=np.int64)
                    idx0, idx1 = (torch.as_tensor((starts[e] + s)[:, None] + np.arange(args.segment_len), device=device)
                                  % buffer.capacity for e, s in ((e0, s0), (e1, s1)))
                    features = None  # coverage (appendix): the states of both segments, concatenated
                    if args.sampler.endswith("coverage"):
                        features = torch.cat([buffer.obs[i].flatten(1) for i in (idx0, idx1)], 1).cpu().numpy()
                    chosen = np.arange(size)  # uniform: random_pairs drew `size` pairs
                    if sampler != "uniform":
                        with torch.no_grad():
                            r0, r1 = (reward_model(torch.cat([buffer.obs[i], buffer.actions[i]], -1)).sum(2)
                                      for i in (idx0, idx1))
                        labelled = np.concatenate(preferences["features"]) if preferences["features"] else None
                        chosen = select(sampler, size, probs=torch.sigmoid(r1 - r0)[..., 0].cpu().numpy(),
                                        features=features, labeled_features=labelled, rng=rng)
                    idx0, idx1 = idx0[chosen], idx1[chosen]
                    parts = (("obs", buffer.obs), ("actions", buffer.actions), ("rewards", buffer.true_rewards[:, 0]))
                    segments = {f"{key}{i}": part[idx].cpu().numpy() for i, idx in enumerate((idx0, idx1))
                                for key, part in parts}
                    # Appendix, adaptive thresholds: mean true return of the last 10 training episodes (reference code)
                    teacher.set_thresholds(float(np.mean(progress.recent_returns)), args.segment_len, episode_len)
                    y, keep = teacher.label(segments["rewards0"], segments["rewards1"])
                    save_labels(os.path.join(output_dir, "labels", f"session_{progress.sessions_done:04d}.npz"),
                                step=global_step, y=y, keep=keep, **segments)
                    progress.feedback_used += size
                    progress.sessions_done += 1
                    kept = torch.as_tensor(keep, device=device)
                    for key, idx in (("inputs0", idx0), ("inputs1", idx1)):
                        preferences[key].append(torch.cat([buffer.obs[idx], buffer.actions[idx]], -1)[kept])
                    preferences["y"].append(torch.as_tensor(y[keep], dtype=torch.float32, device=device))
                    if features is not None:
                        preferences["features"].append(features[chosen][keep])
                    n_labels = sum(len(part) for part in preferences["y"])
                    skipped, equal = int((~keep).sum()), int((y[keep] == 0.5).sum())
                    for name, value in (("labels", progress.feedback_used), ("skipped", skipped), ("equal", equal)):
                        writer.add_scalar(f"feedback/{name}", value, global_step)
                    if n_labels:
                        loss, accuracy = train_reward(reward_model, reward_optimizer, *(torch.cat(preferences[key])
                                                      for key in ("inputs0", "inputs1", "y")), args, args.reward_epochs)
                        relabel(buffer, reward_model)
                        progress.relabels += 1
                        writer.add_scalar("reward/loss", loss, global_step)
                        writer.add_scalar("reward/accuracy", accuracy, global_step)
                        print(f"step {global_step}: feedback session {progress.sessions_done}: {size} queries "
                              f"({skipped} skipped, {equal} equal), reward model trained on {n_labels} labels, "
                              f"accuracy {accuracy:.3f}")
                    else:  # every query so far was skipped: nothing to learn from yet
                        print(f"step {global_step}: all {size} queries skipped, the reward model stays as it is")
                reset_critic = n_labels > 0 and not progress.reward_ready
                progress.next_feedback_step = global_step + args.feedback_every
            if reset_critic:  # PEBBLE, after the first reward update: fresh critics (not actor or temperature), then
                # critic_reset_updates SAC updates on the relabelled buffer (reference code); not counted as overhead
                progress.reward_ready, progress.critic_resets = True, progress.critic_resets + 1
                critic.load_state_dict(TwinCritic(obs_dim, action_dim, args.hidden_dim, args.num_layers).state_dict())
                critic_target.load_state_dict(critic.state_dict())
                critic_optimizer.state.clear()  # and fresh Adam moments
                for i in range(args.critic_reset_updates):
                    batch = buffer.sample(args.batch_size)
                    sac_update(batch, batch.rewards, actor, critic, critic_target, log_alpha, actor_optimizer,
                               critic_optimizer, alpha_optimizer, args.gamma)
                    if (i + 1) % args.target_update_every == 0:
                        soft_update(critic, critic_target, args.tau)

            if global_step <= args.seed_steps:  # Algorithm 2: random actions, from the run's own generator
                action = action_rng.uniform(-1, 1, action_dim).astype(np.float32)
            else:
                with torch.no_grad():
                    action = actor.sample(torch.as_tensor(obs, device=device)[None])[0][0].cpu().numpy()
            next_obs, true_reward, terminated, truncated, info = env.step(action)
            if not (math.isfinite(true_reward) and np.isfinite(next_obs).all()):
                raise FloatingPointError(f"non-finite reward ({true_reward}) or observation from the environment")
            reward = float(true_reward) if args.ground_truth_reward else 0.0
            if progress.reward_ready and not args.ground_truth_reward:  # Algorithm 3: store r_hat(s_t, a_t)
                with progress.overhead(), torch.no_grad():
                    reward = reward_model(torch.as_tensor(np.concatenate([obs, action]), device=device)).mean().item()
            buffer.add(obs, action, reward, true_reward, next_obs, terminated)
            obs, progress.episode_steps = next_obs, progress.episode_steps + 1
            progress.episode_return += float(true_reward)
            if terminated or truncated:
                progress.completed_episodes.append((progress.episode_start, progress.episode_steps))
                progress.recent_returns = (progress.recent_returns + [progress.episode_return])[-10:]
                writer.add_scalar("charts/episodic_return", progress.episode_return, global_step)
                obs, _ = env.reset(seed=episode_seed(args.seed, TRAIN_STREAM, len(progress.completed_episodes)))
                progress.episode_start, progress.episode_steps, progress.episode_return = buffer.added, 0, 0.0

            # Policy learning: SAC on the kNN state entropy during pre-training (and while every query was
            # skipped), then on the learned reward (or the true reward with --ground-truth-reward)
            if global_step > args.seed_steps:
                batch = buffer.sample(args.batch_size)
                rewards = batch.rewards
                if not progress.reward_ready:  # Algorithm 2: r_int(s_t) over its running standard deviation
                    with progress.overhead():
                        rewards = intrinsic_reward(batch, buffer, args.knn_k)
                        intrinsic_stats.update(rewards)
                        rewards = rewards / max(intrinsic_stats.std, 1e-8)
                losses = sac_update(batch, rewards, actor, critic, critic_target, log_alpha, actor_optimizer,
                                    critic_optimizer, alpha_optimizer, args.gamma)
                if progress.reward_ready:
                    progress.updates_on_learned_reward += 1
                else:
                    progress.updates_on_knn_reward += 1
                if (global_step - args.seed_steps) % args.target_update_every == 0:
                    soft_update(critic, critic_target, args.tau)
                if global_step % 1000 == 0:
                    for name, value in losses.items():
                        writer.add_scalar(f"losses/{name}", float(value), global_step)
                    writer.add_scalar("charts/SPS", int(global_step / (time.time() - start_time)), global_step)

            if global_step % args.eval_every == 0 or global_step == args.total_timesteps:
                first = len(progress.eval_rows) * args.eval_episodes  # evaluation episodes are numbered over the run
                seeds = [episode_seed(args.seed, EVAL_STREAM, first + n) for n in range(args.eval_episodes)]
                if args.capture_video:
                    eval_env.name_prefix = f"step_{global_step}"
                learned = reward_model if progress.reward_ready and not args.ground_truth_reward else None
                result = evaluate(actor, learned, eval_env, seeds, device)
                if args.capture_video and eval_env.recording:  # write the video now, not at the next reset
                    eval_env.stop_recording()
                progress.last_eval = result["episode_return"]
                row = {"step": global_step, **result, "feedback": progress.feedback_used,
                       "wall_time": round(time.time() - start_time, 1),
                       "overhead_seconds": round(progress.overhead_seconds, 1)}
                with open(eval_path, "a", newline="") as f:
                    csv.DictWriter(f, eval_fields).writerow(row)
                progress.eval_rows.append(row)
                for name in ("episode_return", "success_rate", "reward_correlation"):
                    writer.add_scalar(f"eval/{name}", result[name], global_step)
            if time.time() - last_print > 10 or global_step == args.total_timesteps:
                last_print = time.time()
                sps = global_step / (last_print - start_time)
                print(f"step {global_step}/{args.total_timesteps} | {sps:.0f} SPS | ETA "
                      f"{(args.total_timesteps - global_step) / sps / 60:.1f} min | last eval return "
                      f"{progress.last_eval:.1f} | labels {progress.feedback_used}/{args.max_feedback}", flush=True)

            if (args.checkpoint_every and global_step % args.checkpoint_every == 0) or stop:
                save_start = time.perf_counter()
                save_checkpoint(checkpoint_path, checkpoint_state())
                print(f"step {global_step}: checkpoint saved ({os.path.getsize(checkpoint_path) / 2**20:.1f} MiB "
                      f"in {time.perf_counter() - save_start:.1f} s)", flush=True)
            if stop:
                print(f"{signal.Signals(stop[0]).name}: checkpoint saved at step {global_step}; "
                      f"continue with --resume {output_dir}", flush=True)
                writer.close()
                sys.exit(128 + stop[0])
    except FloatingPointError as error:  # a NaN or infinity in a loss or from the environment
        # Mid-step the env and the buffer have moved past the last checkpoint, which stays as it is. The state at the
        # failure (finite: the checks come before the optimizer steps) goes to a file of its own, to inspect
        save_checkpoint(os.path.join(output_dir, "checkpoint_nonfinite.pt"), checkpoint_state())
        last = f"its last checkpoint is intact in {checkpoint_path}" if os.path.exists(checkpoint_path) else \
            "no checkpoint was due yet"
        fail(f"{error} at step {progress.global_step}; run stopped, {last}, "
             f"the state at the failure is in {output_dir}/checkpoint_nonfinite.pt and the labels in "
             f"{output_dir}/labels", code=3)
    except OSError as error:
        fail(f"writing to {output_dir!r} failed at step {progress.global_step} ({error.strerror or error}); "
             "the last checkpoint there is intact", code=1)

    counts = {name: getattr(progress, name)
              for name in ("updates_on_knn_reward", "updates_on_learned_reward", "relabels", "critic_resets")}
    print(f"done: {counts} (updates_on_learned_reward: the true reward with --ground-truth-reward), "
          f"{progress.sessions_done} feedback sessions, {progress.feedback_used} queries; outputs in {output_dir}")
    torch.save({"actor": actor.state_dict(), "critic": critic.state_dict(), "reward_model": reward_model.state_dict()},
               os.path.join(output_dir, "final_model.pt"))
    env.close()
    eval_env.close()
    writer.close()
