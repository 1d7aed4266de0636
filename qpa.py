# QPA (Hu et al. 2024): PEBBLE that asks about what the policy does now; docs/qpa.md
import argparse
import csv
import io
import json
import math
import os
import signal
import sys
import time
import warnings
from collections import deque, namedtuple
from dataclasses import asdict, dataclass, field, is_dataclass
from typing import Annotated, Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro

from samplers import draw_segments, planned_labels, schedule_sizes, select, session_steps
from sim_teacher import (TEACHERS, load_pairs, make_teacher, save_file, save_labels,
                         set_labels_aside)


@dataclass
class Args:
    exp_name: str = "qpa"
    """the name of this experiment"""
    seed: int = 1
    """seed of the experiment"""
    cuda: bool = True
    """use the GPU when torch sees one"""
    track: bool = False
    """if toggled, log to Weights & Biases"""
    wandb_project_name: str = "bpref"
    """the Weights & Biases project"""
    capture_video: bool = False
    """if toggled, record each evaluation's first episode to videos/"""
    compile: bool = False
    """if toggled, compile the SAC update and r_hat; on a GPU, replay whole steps as CUDA graphs"""
    output_dir: Annotated[str, tyro.conf.arg(help_behavior_hint="(default: runs/<run name>)")] = ""
    """where the run's files go"""
    checkpoint_every: int = 50000
    """steps between checkpoints (0: at the end and on SIGTERM/SIGINT)"""
    resume: str = ""
    """continue the run in this directory"""
    labels_from: str = ""
    """start D with an earlier run's labels (run directory or .npz)"""

    # Algorithm specific arguments (walker-walk's; PRESETS: the others')
    env_id: str = "walker-walk"
    """DMC domain-task, Meta-World task or Gymnasium id"""
    total_timesteps: int = 500_000
    """total environment steps"""
    teacher: Literal["oracle", "stoc", "mistake", "skip", "equal", "myopic", "human"] = "oracle"
    """simulated teacher (Section 3.3), or human (label_server.py)"""
    teacher_beta: float = math.inf
    """the teacher's rationality beta (inf: rational)"""
    teacher_gamma: float = 1.0
    """the teacher's myopic discount gamma"""
    teacher_eps_mistake: float = 0.0
    """the teacher's mistake probability"""
    teacher_eps_skip: float = 0.0
    """the teacher's adaptive skip fraction"""
    teacher_eps_equal: float = 0.0
    """the teacher's adaptive equal fraction"""
    teacher_bias: float = 0.0
    """the teacher's side bias (> 0: right, < 0: left; not in the paper)"""
    sampler: Literal["uniform", "disagreement", "entropy", "coverage", "disagreement-coverage",
                     "entropy-coverage"] = "uniform"
    """query selection in the pool (QPA: uniform, policy-aligned by the pool)"""
    schedule: Literal["uniform", "decay", "increase"] = "uniform"
    """feedback schedule (paper Section 4.2)"""
    max_feedback: int = 1000
    """total number of queries (the budget)"""
    feedback_per_session: int = 100
    """queries per feedback session (uniform schedule)"""
    feedback_every: int = 20_000
    """environment steps between feedback sessions"""
    segment_len: int = 50
    """length H of a queried segment"""
    seed_steps: int = 1000
    """random-action steps at the start"""
    unsup_steps: int = 9000
    """unsupervised pre-training steps after the seed steps"""
    hidden_dim: int = 1024
    """hidden units of the actor and critic"""
    num_layers: int = 2
    """hidden layers of the actor and critic"""
    batch_size: int = 1024
    """SAC batch size"""
    learning_rate: float = 5e-4
    """learning rate of actor and critics"""
    alpha_lr: float = 1e-4
    """learning rate of the SAC temperature"""
    eval_every: int = 10000
    """environment steps between evaluations"""
    eval_episodes: int = 10
    """episodes per evaluation"""
    ground_truth_reward: bool = False
    """if toggled, SAC learns from the true reward, with no teacher"""
    buffer_size: int = 0
    """replay buffer capacity (0: total_timesteps)"""
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
    reward_ensemble_size: int = 1
    """reward models in the ensemble"""
    reward_lr: float = 3e-4
    """learning rate of the reward models"""
    reward_batch_size: int = 128
    """preference batch size of reward learning"""
    reward_epochs: int = 50
    """most epochs of reward learning per session (it stops at 97% accuracy)"""
    label_smoothing: float = 0.0
    """soft labels (1 - s) y + s / 2"""
    candidate_multiplier: int = 10
    """candidate pairs per query for the uncertainty and coverage samplers"""
    query_recent_episodes: int = 10
    """segments come from the last N complete episodes (0: all; QPA's max_reward_buffer_size)"""
    critic_reset_updates: int = 100
    """SAC updates right after the critic reset"""
    her_ratio: float = 0.5
    """share of each SAC batch from the query pool's episodes while labels remain (hybrid replay)"""
    data_aug_ratio: int = 20
    """random crops of each labelled pair per reward-learning step (0: whole segments)"""
    reward_updates: int = 2000
    """reward-learning steps per session: ceil(this x |D| / batch) (0: --reward-epochs epochs)"""


# PEBBLE's presets (budgets, networks) with QPA's settings: run_QPA.sh's walker_walk (Args); on
# Meta-World its learning rate, reward epochs on whole segments, a pool of 30 (differences.md)
PRESETS = {
    "quadruped-walk": dict(total_timesteps=1_000_000, feedback_every=30_000, learning_rate=1e-4),
    "metaworld": dict(total_timesteps=1_000_000, max_feedback=10_000, feedback_per_session=50,
                      feedback_every=4950, hidden_dim=256, num_layers=3, batch_size=512,
                      learning_rate=1e-4, reward_epochs=200, reward_updates=0, data_aug_ratio=0,
                      query_recent_episodes=30),
    "gym": dict(hidden_dim=256, batch_size=256, learning_rate=3e-4),
}


# Console's note: each task's CPU scale
CPU_SCALES = {
    "walker-walk": "walker-walk, experiments/grid.py qpa-walker-1000 (--total-timesteps 100000 "
    "--hidden-dim 256 --num-layers 2 --batch-size 256 --feedback-every 9000), took 22-29 min for "
    "pebble.py",
}


# Environments
class DMCEnv(gym.Env):
    """A dm_control task as a Gymnasium env with flat observations."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, domain, task, render_mode=None):
        from dm_control import suite

        self.dmc = suite.load(domain, task)
        self.render_mode = render_mode
        obs_dim = sum(int(np.prod(v.shape)) for v in self.dmc.observation_spec().values())
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,))
        spec = self.dmc.action_spec()
        self.action_space = gym.spaces.Box(spec.minimum.astype(np.float32),
                                           spec.maximum.astype(np.float32))

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.dmc.task.random.seed(seed)
        return self.flat(self.dmc.reset()), {}

    def step(self, action):
        time_step = self.dmc.step(action)
        terminated = time_step.last() and time_step.discount == 0
        truncated = time_step.last() and not terminated
        return self.flat(time_step), time_step.reward, terminated, truncated, {}

    def flat(self, time_step):
        return np.concatenate([np.ravel(v) for v in time_step.observation.values()])

    def render(self):
        return self.dmc.physics.render(height=240, width=320, camera_id=0)

    def close(self):
        self.dmc.physics.free()


class MetaWorldSeeding(gym.Wrapper):
    """reset(seed=s) seeds the object and goal positions."""

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.env.unwrapped.seed(seed)
        return self.env.reset(options=options)


def env_kind(env_id):
    if env_id in gym.registry:
        return "gym"
    with warnings.catch_warnings(action="ignore"):
        from dm_control import suite
    if tuple(env_id.split("-", 1)) in suite.ALL_TASKS:
        return "dmc"
    import metaworld

    if f"{env_id.removesuffix('-v3')}-v3" in metaworld.ALL_V3_ENVIRONMENTS:
        return "metaworld"
    return "gym"


def make_env(env_id, render_mode=None):
    """(env, episode length T), actions in [-1, 1]."""
    kind = env_kind(env_id)
    if kind == "dmc":
        env = DMCEnv(*env_id.split("-", 1), render_mode)
        episode_len = int(env.dmc._step_limit)
    elif kind == "metaworld":
        env = gym.make("Meta-World/MT1", env_name=f"{env_id.removesuffix('-v3')}-v3",
                       render_mode=render_mode, disable_env_checker=True)
        env.get_wrapper_attr("toggle_terminate_on_success")(False)
        # Reference code: a fresh hidden goal at each reset
        env.unwrapped.set_task(env.get_wrapper_attr("tasks")[0])
        env.get_wrapper_attr("toggle_sample_tasks_on_reset")(False)
        env.unwrapped._partially_observable = True
        env.unwrapped._freeze_rand_vec = False
        env.unwrapped.seeded_rand_vec = True
        episode_len = env.spec.max_episode_steps or 500
        env = MetaWorldSeeding(env)
    else:
        try:
            env = gym.make(env_id, **({"render_mode": render_mode} if render_mode else {}))
        except (gym.error.Error, ImportError) as error:
            raise ValueError(f"--env-id {env_id!r} is not a DMC task (walker-walk), a Meta-World "
                             f"task (button-press) or a Gymnasium id: {error}") from None
        episode_len = env.spec.max_episode_steps
        spaces = (env.action_space, env.observation_space)
        if not (all(isinstance(s, gym.spaces.Box) for s in spaces) and episode_len):
            raise ValueError(f"--env-id {env_id!r} needs Box spaces and a time limit")
    bound = np.ones(env.action_space.shape, np.float32)
    env = gym.wrappers.RescaleAction(env, -bound, bound)
    space = gym.spaces.Box(-np.inf, np.inf, env.observation_space.shape, np.float32)
    env = gym.wrappers.TransformObservation(env, lambda obs: np.asarray(obs, np.float32), space)
    return env, episode_len


TRAIN_STREAM = 0  # episode seeds of the training and evaluation envs
EVAL_STREAM = 1


def numpy_seeds(seed):
    """Streams of the sampler, the teacher and the seed steps' actions."""
    return np.random.SeedSequence(seed).spawn(3)


def episode_seed(run_seed, stream, episode):
    return int(np.random.SeedSequence([run_seed, stream, episode]).generate_state(1)[0])


# Networks
def mlp(in_dim, out_dim, hidden_dim, num_layers, activation=nn.ReLU):
    layers = []
    for i in range(num_layers):
        layers += [nn.Linear(hidden_dim if i else in_dim, hidden_dim), activation()]
    return nn.Sequential(*layers, nn.Linear(hidden_dim, out_dim))


def orthogonal_init(module):
    """Reference code (utils.weight_init): orthogonal weights, zero biases."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight)
            nn.init.zeros_(layer.bias)
    return module


LOG_STD_MIN = -5  # the reference SAC's
LOG_STD_MAX = 2


class Actor(nn.Module):
    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers):
        super().__init__()
        self.net = orthogonal_init(mlp(obs_dim, 2 * action_dim, hidden_dim, num_layers))

    def forward(self, obs):
        mean, log_std = self.net(obs).chunk(2, dim=-1)
        return mean, LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(log_std) + 1)

    def sample(self, obs):
        mean, log_std = self(obs)
        pre_tanh = mean + log_std.exp() * torch.randn_like(mean)
        return torch.tanh(pre_tanh), tanh_gaussian_log_prob(mean, log_std, pre_tanh)


def mean_policy(actor, device):
    """The policy evaluated: an observation -> the mean action."""
    return lambda obs: torch.tanh(actor(torch.as_tensor(obs, device=device))[0])


class TwinCritic(nn.Module):
    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers):
        super().__init__()
        self.q1 = mlp(obs_dim + action_dim, 1, hidden_dim, num_layers)
        self.q2 = mlp(obs_dim + action_dim, 1, hidden_dim, num_layers)
        orthogonal_init(self)

    def forward(self, obs, action):
        x = torch.cat([obs, action], -1)
        return self.q1(x), self.q2(x)


class RewardEnsemble(nn.Module):
    """Appendix, reward model: 3 x 256 LeakyReLU, tanh output; inputs standardised by D."""

    def __init__(self, obs_dim, action_dim, size):
        super().__init__()
        self.members = nn.ModuleList(
            nn.Sequential(mlp(obs_dim + action_dim, 1, 256, 3, nn.LeakyReLU), nn.Tanh())
            for _ in range(size))
        self.register_buffer("input_mean", torch.zeros(obs_dim + action_dim))
        self.register_buffer("input_std", torch.ones(obs_dim + action_dim))
        self.register_buffer("input_clip", torch.tensor(math.inf))

    def normalize(self, obs_action):
        centred = (obs_action - self.input_mean) / self.input_std
        return centred.clamp(-self.input_clip, self.input_clip)

    def set_input_stats(self, states):
        obs_dim = states.shape[-1]
        self.input_mean[:obs_dim] = states.mean(0)
        self.input_std[:obs_dim] = (states.var(0, unbiased=False) + 1e-8).sqrt()
        self.input_clip.fill_(10.0)

    def forward(self, obs_action):
        inputs = self.normalize(obs_action)
        return torch.stack([member(inputs) for member in self.members])


# Algorithm
def tanh_gaussian_log_prob(mean, log_std, pre_tanh):
    """log pi(a|s), a = tanh(u), u ~ N(mean, std^2) (SAC paper, appendix C)."""
    z = (pre_tanh - mean) / log_std.exp()
    gaussian = -0.5 * z**2 - log_std - 0.5 * math.log(2 * math.pi)
    squash = 2 * (math.log(2) - pre_tanh - F.softplus(-2 * pre_tanh))
    return (gaussian - squash).sum(-1, keepdim=True)


def sac_critic_loss(q1, q2, rewards, terminated, next_q, next_log_prob, alpha, gamma):
    """Appendix Eq. (6) for both critics; bootstraps through a time limit."""
    target = (rewards + gamma * (1 - terminated) * (next_q - alpha * next_log_prob)).detach()
    return F.mse_loss(q1, target) + F.mse_loss(q2, target)


def sac_actor_loss(log_prob, q1, q2, alpha):
    """Appendix Eq. (7), with the smaller critic."""
    return (alpha * log_prob - torch.min(q1, q2)).mean()


def temperature_loss(log_alpha, log_prob, target_entropy):
    """SAC's learned temperature (reference code: agent/sac.py)."""
    return (log_alpha.exp() * (-log_prob.detach() - target_entropy)).mean()


def optimize(optimizer, loss):
    """A gradient step of this optimizer's parameters only."""
    optimizer.zero_grad()
    # inputs: not the critic's gradients from the actor's loss
    loss.backward(inputs=[param for group in optimizer.param_groups for param in group["params"]])
    optimizer.step()


def adam(params, lr, capturable=False):
    # fused: one kernel per step; capturable: for CUDA graphs
    return torch.optim.Adam(params, lr=lr, fused=True, capturable=capturable)


Batch = namedtuple("Batch", "obs actions rewards next_obs terminated")


def sac_update(batch, rewards, actor, critic, critic_target, log_alpha, actor_opt, critic_opt,
               alpha_opt, gamma):
    alpha = log_alpha.exp().detach()
    with torch.no_grad():
        next_actions, next_log_prob = actor.sample(batch.next_obs)
        next_q = torch.min(*critic_target(batch.next_obs, next_actions))
    critic_loss = sac_critic_loss(*critic(batch.obs, batch.actions), rewards, batch.terminated,
                                  next_q, next_log_prob, alpha, gamma)
    optimize(critic_opt, critic_loss)
    actions, log_prob = actor.sample(batch.obs)
    actor_loss = sac_actor_loss(log_prob, *critic(batch.obs, actions), alpha)
    optimize(actor_opt, actor_loss)
    alpha_loss = temperature_loss(log_alpha, log_prob, -batch.actions.shape[-1])
    optimize(alpha_opt, alpha_loss)
    return {"critic_loss": critic_loss.detach(), "actor_loss": actor_loss.detach(),
            "alpha_loss": alpha_loss.detach(), "entropy": -log_prob.detach().mean(), "alpha": alpha,
            "batch_reward": rewards.mean()}  # the others carry no gradient


@torch.no_grad()
def soft_update(critic, critic_target, tau):
    for param, target_param in zip(critic.parameters(), critic_target.parameters()):
        target_param.lerp_(param, tau)


def act(actor, obs):
    """a ~ pi(.|s) for one observation s."""
    actions, _ = actor.sample(obs[None])
    return actions[0]


def learned_reward(reward_model, obs_action):
    """r_hat(s, a): the ensemble's mean."""
    return reward_model(obs_action).mean()


class ReplayBuffer:
    """Transitions, the oldest overwritten when full; rewards are r_hat."""

    def __init__(self, capacity, obs_dim, action_dim, device=None):
        self.size = 0
        self.pos = 0
        for name, dim in zip(Batch._fields, (obs_dim, action_dim, 1, obs_dim, 1)):
            setattr(self, name, torch.zeros(capacity, dim, device=device))

    def add(self, *transition):
        for name, value in zip(Batch._fields, transition):
            getattr(self, name)[self.pos] = torch.as_tensor(value)
        self.pos = (self.pos + 1) % len(self.obs)
        self.size = min(self.size + 1, len(self.obs))

    def sample(self, batch_size):
        idx = torch.randint(self.size, (batch_size,), device=self.obs.device)
        return Batch(*(getattr(self, name)[idx] for name in Batch._fields))

    def state_dict(self):
        """The filled part (cloned: a slice would save it all)."""
        filled = {name: getattr(self, name)[: self.size].clone() for name in Batch._fields}
        return filled | {"size": self.size, "pos": self.pos}

    def load_state_dict(self, state):
        self.size = state["size"]
        self.pos = state["pos"]
        for name in Batch._fields:
            getattr(self, name)[: self.size] = state[name]


def knn_distance(states, reference, k):
    """Eq. (8) without the log: distance to the k-th nearest other state."""
    distances = torch.cdist(states, reference)
    nearest = distances.topk(min(k + 1, len(reference)), dim=1, largest=False).values
    return nearest[:, -1:].contiguous()  # its statistics then sum in a fixed order


def intrinsic_reward(batch, buffer, k):
    """Algorithm 2's r_int(s_t) among the buffer's states."""
    return knn_distance(batch.obs, buffer.obs[: buffer.size], k)


@dataclass
class RunningMeanStd:
    """Of the kNN reward (Chan et al.'s parallel update)."""

    mean: float = 0.0
    var: float = 1.0
    count: int = 0

    def update(self, x):
        n = x.numel()
        total = self.count + n
        delta = x.mean().item() - self.mean
        m2 = self.var * self.count + x.var(unbiased=False).item() * n
        m2 += delta**2 * self.count * n / total
        self.mean += delta * n / total
        self.var = m2 / total
        self.count = total


@torch.no_grad()
def relabel(buffer, reward_model, chunk=16384):
    """PEBBLE's relabelling of every stored transition with r_hat."""
    for start in range(0, buffer.size, chunk):
        rows = slice(start, start + chunk)
        obs_action = torch.cat([buffer.obs[rows], buffer.actions[rows]], -1)
        buffer.rewards[rows] = reward_model(obs_action).mean(0)


def sac_batch(buffer, args, progress, episodes):
    """SAC's batch; while labels remain, QPA's hybrid replay: a share --her-ratio from the query
    pool's episodes (the last transitions stored), the rest from all."""
    labels_remain = progress.feedback_used < args.max_feedback and not args.ground_truth_reward
    if not (progress.pretrained and labels_remain):
        return buffer.sample(args.batch_size)
    recent = int(args.batch_size * args.her_ratio)
    window = min(sum(len(episode[0]) for episode in episodes), buffer.size)
    back = torch.randint(window, (recent,), device=buffer.obs.device)
    idx = (buffer.pos - 1 - back) % len(buffer.obs)
    batch = buffer.sample(args.batch_size - recent)
    return Batch(*(torch.cat([part, getattr(buffer, name)[idx]])
                   for name, part in zip(Batch._fields, batch)))


def crop_returns(rewards0, rewards1, crops):
    """Segment returns (pairs, 2); QPA's data augmentation: (crops x pairs, 2), sums over windows
    of one length (QPA's code: H-15 to H-5) at a random start in each segment."""
    if not crops:
        return torch.cat([rewards0.sum(1), rewards1.sum(1)], -1)
    pairs, horizon = rewards0.shape[:2]
    device = rewards0.device
    length = torch.randint(max(1, horizon - 15), max(1, horizon - 5) + 1, (crops, pairs, 1),
                           device=device)
    steps = torch.arange(horizon, device=device)
    returns = []
    for rewards in (rewards0, rewards1):
        start = (torch.rand(crops, pairs, 1, device=device) * (horizon - length + 1)).long()
        inside = (steps >= start) & (steps < start + length)
        returns.append((rewards[..., 0] * inside).sum(-1))
    return torch.stack(returns, -1).flatten(0, 1)


def coverage_features(inputs0, inputs1, obs_dim):
    """Appendix, coverage sampling: both segments' states."""
    states = [inputs0[..., :obs_dim].flatten(1), inputs1[..., :obs_dim].flatten(1)]
    return torch.cat(states, 1).cpu().numpy()


def preference_loss(segment_returns, y, label_smoothing=0.0):
    """Eq. (3): cross-entropy of P[sigma1 > sigma0] (Eq. (2)) against (1 - y, y)."""
    target = (1 - label_smoothing) * y + label_smoothing / 2
    log_probs = F.log_softmax(segment_returns, dim=-1)
    return -((1 - target) * log_probs[:, 0] + target * log_probs[:, 1]).mean()


def train_reward(reward_model, optimizer, preferences, args):
    """Algorithm 3, reward learning on crops (QPA). QPA's code on DMC: ceil(reward_updates x |D| /
    batch) steps, stopping at 98% accuracy so far; else epochs, stopping at 97% in one."""
    inputs0 = reward_model.normalize(preferences["inputs0"])
    inputs1 = reward_model.normalize(preferences["inputs1"])
    y = preferences["y"]
    size = args.reward_batch_size
    per_epoch = math.ceil(len(y) / size)
    steps = args.reward_epochs * per_epoch
    if args.reward_updates:
        steps = math.ceil(args.reward_updates * len(y) / size)
    for step in range(steps):
        start = step % per_epoch * size
        if start == 0:  # an epoch begins
            orders = [torch.randperm(len(y), device=y.device) for _ in reward_model.members]
        if step == 0 or (start == 0 and not args.reward_updates):  # so far, or per epoch
            correct = torch.zeros((), device=y.device)
            strict = torch.zeros((), device=y.device)
            losses = []
        loss = 0.0
        for member, order in zip(reward_model.members, orders):
            idx = order[start : start + size]
            returns = crop_returns(member(inputs0[idx]), member(inputs1[idx]), args.data_aug_ratio)
            labels = y[idx].repeat(max(args.data_aug_ratio, 1))
            loss = loss + preference_loss(returns, labels, args.label_smoothing)
            right = (returns[:, 1] > returns[:, 0]) == (labels > 0.5)
            correct = correct + (right & (labels != 0.5)).sum()
            strict = strict + (labels != 0.5).sum()
        optimize(optimizer, loss)
        losses.append(loss.detach() / len(reward_model.members))
        accuracy = correct.item() / max(strict.item(), 1)
        if args.reward_updates and accuracy >= 0.98:  # QPA's code: the accuracy so far
            break
        if not args.reward_updates and start + size >= len(y) and accuracy > 0.97:
            break
    loss = torch.stack(losses).mean().item()
    if not math.isfinite(loss):
        raise FloatingPointError(f"non-finite reward-model loss ({loss})")
    return loss, accuracy


def sample_queries(sampler, size, episodes, reward_model, preferences, args, rng):
    """SAMPLE() of Algorithm 3: the chosen pairs and their (obs, action) inputs."""
    n_candidates = size if sampler == "uniform" else size * args.candidate_multiplier
    candidates = draw_segments(episodes, args.segment_len, n_candidates, rng)
    inputs0, inputs1 = (torch.as_tensor(np.concatenate([candidates[f"obs{i}"], candidates[
        f"actions{i}"]], -1), device=preferences["y"].device) for i in (0, 1))
    chosen = np.arange(size)
    if sampler != "uniform":
        obs_dim = candidates["obs0"].shape[-1]
        with torch.no_grad():
            margins = reward_model(inputs1).sum(2) - reward_model(inputs0).sum(2)
        labelled = None
        features = None
        if sampler.endswith("coverage"):
            labelled = coverage_features(preferences["inputs0"], preferences["inputs1"], obs_dim)
            features = coverage_features(inputs0, inputs1, obs_dim)
        chosen = select(sampler, size, probs=torch.sigmoid(margins)[..., 0].cpu().numpy(),
                        rng=rng, labeled_features=labelled, features=features)  # Eq. (2)
    segments = {key: value[chosen] for key, value in candidates.items()}
    return segments, inputs0[chosen], inputs1[chosen]


def add_labels(preferences, inputs0, inputs1, y, keep):
    """D grows by the kept labels and both segments' (obs, action) inputs."""
    for key, value in zip(preferences, (inputs0, inputs1, y)):
        new = torch.as_tensor(value[keep]).float().to(preferences[key].device)
        preferences[key] = torch.cat([preferences[key], new])


def session_due(args, step, progress, session_sizes, episodes):
    """Algorithm 3, line 9 (with labels left and a segment to show)."""
    return (not args.ground_truth_reward and step >= progress.next_feedback_step
            and progress.sessions_done < len(session_sizes)
            and any(len(episode[0]) >= args.segment_len for episode in episodes))


def feedback_session(args, step, progress, size, episodes, preferences, reward_model,
                     reward_optimizer, teacher, rng, writer, episode_len):
    """Algorithm 3, lines 9-13: queries, labels, D, reward learning. Returns |D|."""
    sampler = args.sampler if progress.pretrained else "uniform"  # reference: first uniform
    segments, inputs0, inputs1 = sample_queries(sampler, size, episodes, reward_model, preferences,
                                                args, rng)
    # Appendix, adaptive thresholds
    mean_return = float(np.mean(progress.recent_returns))
    teacher.set_thresholds(mean_return, args.segment_len, episode_len)
    y, keep = teacher.label(segments["rewards0"], segments["rewards1"], segments | {"step": step})
    save_labels(args.output_dir, progress.sessions_done, step=step, y=y, keep=keep,
                threshold_scale=mean_return * args.segment_len / episode_len, **segments)
    progress.feedback_used += size
    progress.sessions_done += 1
    progress.next_feedback_step = step + args.feedback_every
    add_labels(preferences, inputs0, inputs1, y, keep)
    writer.add_scalar("feedback/labels", progress.feedback_used, step)
    writer.add_scalar("feedback/skipped", (~keep).sum(), step)
    if len(preferences["y"]) == 0:  # all skipped so far
        say(f"step {step}: all {size} queries skipped, the reward model stays as it is")
        return 0
    states = torch.cat([preferences["inputs0"], preferences["inputs1"]], 1)
    reward_model.set_input_stats(states[..., : segments["obs0"].shape[-1]].flatten(0, 1))
    loss, accuracy = train_reward(reward_model, reward_optimizer, preferences, args)
    writer.add_scalar("reward/loss", loss, step)
    writer.add_scalar("reward/accuracy", accuracy, step)
    say(f"step {step}: feedback session {progress.sessions_done}: reward model trained on "
        f"{len(preferences['y'])} labels, accuracy {accuracy:.3f}")
    return len(preferences["y"])


def reset_critic(critic, critic_target, critic_optimizer):
    """PEBBLE after the first reward update: fresh critics and Adam moments."""
    for layer in critic.modules():  # drawn as a new TwinCritic's
        if isinstance(layer, nn.Linear):
            layer.reset_parameters()
    orthogonal_init(critic)
    critic_target.load_state_dict(critic.state_dict())
    for state in critic_optimizer.state.values():  # in place: a CUDA graph holds these tensors
        for value in state.values():
            value.zero_()


@torch.no_grad()
def evaluate(policy, reward_model, env, seeds, device):
    """True return (B-Pref's metric), success, r_hat's correlation with the true reward."""
    returns = []
    successes = []
    true_rewards = []
    obs_actions = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        returns.append(0.0)
        successes.append(False)
        while True:
            action = policy(obs)
            obs_actions.append(torch.cat([torch.as_tensor(obs, device=device), action]))
            obs, reward, terminated, truncated, info = env.step(action.cpu().numpy())
            returns[-1] += reward
            successes[-1] |= bool(info.get("success"))
            true_rewards.append(reward)
            if terminated or truncated:
                break
    correlation = math.nan
    if reward_model is not None:
        learned = reward_model(torch.stack(obs_actions)).mean(0).flatten().cpu().numpy()
        if min(np.std(learned), np.std(true_rewards)) > 0:
            correlation = float(np.corrcoef(learned, true_rewards)[0, 1])
    return {"episode_return": float(np.mean(returns)), "episode_return_std": float(np.std(returns)),
            "success_rate": float(np.mean(successes)), "reward_correlation": correlation}


def evaluation(args, step, progress, policy, reward_model, env, writer, device):
    """A row of eval.csv."""
    if args.capture_video:
        env.name_prefix = f"step_{step}"
    first = len(progress.eval_rows) * args.eval_episodes
    seeds = [episode_seed(args.seed, EVAL_STREAM, first + j) for j in range(args.eval_episodes)]
    learned = reward_model if progress.pretrained and not args.ground_truth_reward else None
    result = evaluate(policy, learned, env, seeds, device)
    if args.capture_video and env.recording:
        env.stop_recording()
    progress.eval_rows.append({"step": step, **result, "feedback": progress.feedback_used,
                               "wall_time": round(progress.elapsed, 1)})
    text = io.StringIO()
    table = csv.DictWriter(text, fieldnames=progress.eval_rows[0].keys(),
                           lineterminator="\n")
    table.writeheader()
    table.writerows(progress.eval_rows)
    save_file(f"{args.output_dir}/eval.csv", text.getvalue().encode())
    for name, value in result.items():
        writer.add_scalar(f"eval/{name}", value, step)
    writer.add_scalar("charts/SPS", step / progress.elapsed, step)
    say(f"step {step}: eval return {result['episode_return']:.1f}, "
        f"{step / progress.elapsed:.0f} steps/s")


# Plumbing: command line, files, checkpoints, logging
def say(message):
    """A line of its own, over the progress line."""
    print(("\r\033[K" if sys.stdout.isatty() else "") + message, flush=True)


def fail(message, code=2):
    print(("\r\033[K" if sys.stderr.isatty() else "") + f"error: {message}", file=sys.stderr)
    sys.exit(code)


RESUME_MAY_CHANGE = {"resume", "output_dir", "checkpoint_every", "cuda", "track",
                     "wandb_project_name", "capture_video", "compile"}
RANGES = [  # (flags, test, rule); the teacher checks its own
    ("seed seed_steps unsup_steps checkpoint_every buffer_size query_recent_episodes "
     "critic_reset_updates", lambda v: v >= 0, ">= 0"),
    ("max_feedback feedback_per_session feedback_every hidden_dim num_layers "
     "batch_size eval_every eval_episodes knn_k reward_ensemble_size reward_batch_size "
     "reward_epochs candidate_multiplier target_update_every",
     lambda v: v >= 1, ">= 1"),
    ("learning_rate alpha_lr reward_lr init_temperature", lambda v: v > 0, "> 0"),
    ("gamma tau", lambda v: 0 < v <= 1, "in (0, 1]"),
    ("label_smoothing", lambda v: 0 <= v < 1, "in [0, 1)"),
    ("data_aug_ratio reward_updates", lambda v: v >= 0, ">= 0"),
    ("her_ratio", lambda v: 0 <= v <= 1, "in [0, 1]"),
]


def task_defaults(env_id, teacher):
    """Args with the task's preset and the teacher's fields."""
    preset = PRESETS.get(env_id.removesuffix("-v3")) or PRESETS.get(env_kind(env_id), {})
    teacher_fields = {f"teacher_{k}": v for k, v in TEACHERS.get(teacher, {}).items()}
    return Args(env_id=env_id, **preset, **teacher_fields)


def parse_args():
    """tyro's command line; its defaults: the task's preset or the resumed run's configuration."""
    # a first pass: the flags that choose the defaults
    pre = argparse.ArgumentParser(add_help=False)
    for flag in ("--env-id", "--teacher", "--resume"):
        pre.add_argument(flag, default="")
    given = pre.parse_known_args()[0]
    default = task_defaults(given.env_id or Args.env_id, given.teacher)
    marked = [f"--{k.replace('_', '-')}" for k, v in vars(default).items()
              if v != getattr(Args(), k) and k not in ("env_id", "teacher")]
    about = (f"Defaults of --env-id {default.env_id} --teacher {given.teacher or default.teacher}; "
             f"from their preset: {' '.join(marked) or 'none'}")
    if given.resume:
        try:
            with open(f"{given.resume}/config.json") as f:
                saved = json.load(f)
        except (OSError, ValueError) as error:
            fail(f"--resume {given.resume!r}: its config.json cannot be read ({error})")
        names = set(vars(Args()))
        # older runs may lack RESUME_MAY_CHANGE
        if not set(saved) <= names or names - set(saved) - RESUME_MAY_CHANGE:
            fail(f"--resume {given.resume!r}: its config.json is of another version of this script")
        default = Args(**saved)
        about = f"Defaults: the configuration of the run in {given.resume}"
    args = tyro.cli(Args, default=default, description=about)
    if given.resume:
        changed = [k for k, v in vars(args).items()
                   if v != getattr(default, k) and k not in RESUME_MAY_CHANGE]
        if changed:
            fail(f"--{changed[0].replace('_', '-')} cannot change when resuming")
        args.output_dir = given.resume
    if not args.output_dir:
        run_name = f"{args.env_id}__{args.exp_name}__{args.teacher}__{args.seed}"
        args.output_dir = f"runs/{run_name}__{int(time.time())}"
    return args


def check_args(args, episode_len):
    """ValueError naming the first flag out of its range."""
    pretrain = args.seed_steps + args.unsup_steps
    rules = RANGES + [
        ("feedback_per_session", lambda v: v <= args.max_feedback, "<= --max-feedback"),
        ("segment_len", lambda v: 1 <= v <= episode_len, f"in [1, {episode_len}] (T)"),
        ("total_timesteps", lambda v: v > pretrain, f"> --seed-steps + --unsup-steps ({pretrain})"),
        ("buffer_size", lambda v: v == 0 or v >= max(args.batch_size, episode_len),
         "0 or >= the batch size and T"),
    ]
    for names, ok, rule in rules:
        for name in names.split():
            value = getattr(args, name)
            if not ok(value):
                raise ValueError(f"--{name.replace('_', '-')} must be {rule}, got {value}")


def check_video(eval_env):
    """--capture-video: render one frame now."""
    try:
        import moviepy  # noqa: F401

        with warnings.catch_warnings(action="ignore"):
            eval_env.reset(seed=0)
            eval_env.render()
    except Exception as error:
        print(f"error: --capture-video cannot render ({type(error).__name__}); it needs moviepy "
              "and, without a display, MUJOCO_GL=egl or osmesa", file=sys.stderr, flush=True)
        os._exit(2)  # MuJoCo's half-made GL context raises in its finalizer


def snapshot(parts):
    """The checkpoint: one dict of plain tensors and numbers, a key per part."""
    state = {"torch_rng": torch.get_rng_state()}
    if torch.cuda.is_initialized():
        state["cuda_rng"] = torch.cuda.get_rng_state_all()
    for name, part in parts.items():
        if hasattr(part, "state_dict"):
            state[name] = part.state_dict()
        elif isinstance(part, np.random.Generator):
            state[name] = part.bit_generator.state
        elif is_dataclass(part):
            state[name] = asdict(part)
        else:  # a tensor, a dict of tensors, the query pool
            state[name] = list(part) if isinstance(part, deque) else part
    return state


def restore(parts, state, device):
    torch.set_rng_state(state["torch_rng"])
    if "cuda_rng" in state and device.type == "cuda":
        torch.cuda.set_rng_state_all(state["cuda_rng"])
    try:
        for name, part in parts.items():
            if hasattr(part, "load_state_dict"):
                part.load_state_dict(state[name])
            elif isinstance(part, np.random.Generator):
                part.bit_generator.state = state[name]
            elif is_dataclass(part):
                vars(part).update(state[name])
            elif torch.is_tensor(part):
                part.data.copy_(state[name])
            elif isinstance(part, dict):
                part.update({key: value.to(device) for key, value in state[name].items()})
            else:
                part.extend(state[name])
    except KeyError:  # another version's checkpoint
        fail("the checkpoint does not fit this script (written by another version?); resume it "
             "with the version that wrote it, or start afresh")


def check_finite(losses):
    """A NaN or infinity stops the run before a checkpoint could hold it."""
    if bad := [name for name, value in losses.items() if not math.isfinite(value)]:
        raise FloatingPointError(f"non-finite {', '.join(bad)}")


def save_whole(path, obj):
    data = io.BytesIO()
    torch.save(obj, data)
    save_file(path, data.getvalue())


def load_checkpoint(path):
    try:
        return torch.load(path, "cpu", weights_only=True)
    except Exception as error:
        fail(f"{path} cannot be read ({type(error).__name__}): incomplete, or not a checkpoint")


def flat_inputs(inputs):
    """Batches opened."""
    return [x for value in inputs for x in (value if isinstance(value, Batch) else [value])]


def signature(inputs):
    """Each tensor's shape and dtype, other arguments as they are."""
    return [(x.shape, x.dtype) if torch.is_tensor(x) else x for x in flat_inputs(inputs)]


def graph_input(value):
    """The graph's copy of a tensor or Batch."""
    if isinstance(value, Batch):
        return Batch(*map(torch.clone, value))
    return value.clone() if torch.is_tensor(value) else value


class CudaGraph:
    """--compile on a GPU (LeanRL's recipe): all of fn's kernels (backward and Adam's step too)
    recorded once, then replayed; a call copies its tensors into the graph's inputs."""

    def __init__(self, fn):
        self.fn = fn
        self.eager_calls = 3  # first: Adam's moments and cuBLAS's workspace are made
        self.graph = None

    def __call__(self, *inputs):
        if self.eager_calls:
            self.eager_calls -= 1
            stream = torch.cuda.Stream()  # PyTorch's rule: warm up on a side stream
            stream.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(stream):
                outputs = self.fn(*inputs)
            torch.cuda.current_stream().wait_stream(stream)
            return outputs
        if self.graph is None:
            self.inputs = [graph_input(x) for x in inputs]
            self.signature = signature(inputs)
            self.graph = torch.cuda.CUDAGraph()
            # no compiling inside the capture: an error
            with torch.compiler.set_stance("fail_on_recompile"), torch.cuda.graph(self.graph):
                self.outputs = self.fn(*self.inputs)
        if signature(inputs) != self.signature:  # else copy_ would broadcast, zip truncate
            raise ValueError(f"{self.fn.__name__}: its CUDA graph was recorded for other tensor "
                             "shapes, dtypes or arguments than this call's")
        for fixed, tensor in zip(flat_inputs(self.inputs), flat_inputs(inputs)):
            if torch.is_tensor(tensor):
                fixed.copy_(tensor)
        self.graph.replay()
        return self.outputs


@dataclass
class Progress:
    """What the main loop carries besides networks, optimizers and buffers."""

    global_step: int = 0
    episodes: int = 0
    running_episode: tuple = field(default_factory=lambda: ([], [], []))
    recent_returns: list = field(default_factory=list)  # of the last 10 episodes
    sessions_done: int = 0
    feedback_used: int = 0
    next_feedback_step: int = 0
    pretrained: bool = False
    eval_rows: list = field(default_factory=list)
    elapsed: float = 0.0  # seconds, over all of the run's processes


def duration(seconds):
    if seconds >= 5400:
        return f"{seconds / 3600:.1f} h"
    if seconds >= 90:
        return f"{seconds / 60:.0f} min"
    return f"{seconds:.0f} s"


class Console:
    """A start line, then progress: in place on a terminal, a line a minute in a file."""

    def __init__(self, args, progress, planned, device, random_steps=0):
        self.total = args.total_timesteps
        self.planned = 0 if args.ground_truth_reward else planned
        self.metaworld = env_kind(args.env_id) == "metaworld"
        self.on_cpu = device.type == "cpu"
        self.cpu_scale = CPU_SCALES.get(args.env_id.removesuffix("-v3"), CPU_SCALES["walker-walk"])
        self.random_steps = random_steps  # left out of the rate
        self.terminal = sys.stdout.isatty()
        now = time.time()
        self.clock = now - progress.elapsed
        self.minute_start = now
        self.minute_step = progress.global_step
        self.minutes = 0
        self.rate = 0.0  # steps/s, the last minute of learning
        self.shown = now
        name = f"the CPU (torch threads: {torch.get_num_threads()})"
        if not self.on_cpu:
            name = torch.cuda.get_device_name(device)
        labels = "the true reward" if args.ground_truth_reward else f"{planned} labels planned"
        say(f"{args.exp_name} on {name}: {args.total_timesteps} steps, {labels}; "
            f"outputs in {args.output_dir}")

    def update(self, progress):
        """Each step: the clock, and the line when due."""
        now = time.time()
        progress.elapsed = now - self.clock
        step = progress.global_step
        if step <= self.random_steps:  # not yet learning
            self.minute_start = now
            self.minute_step = step
        if now - self.minute_start >= 60:
            self.rate = (step - self.minute_step) / (now - self.minute_start)
            self.minute_start = now
            self.minute_step = step
            self.minutes += 1
            hours = (progress.elapsed + (self.total - step) / max(self.rate, 1e-9)) / 3600
            if self.minutes == 2 and self.on_cpu and hours > 12:
                say(f"note: on this CPU the run takes about {hours:.0f} h; the CPU scale of "
                    f"{self.cpu_scale} a run on a core of a 2-core machine; the run goes on")
        if now - self.shown < (1 if self.terminal else 60) and step < self.total:
            return
        self.shown = now
        rate = "-"
        left = "-"
        if self.rate:
            rate = f"{self.rate:.1f}" if self.rate < 10 else f"{self.rate:.0f}"
            left = duration((self.total - step) / self.rate)
        text = f"step {step}/{self.total} | {rate} steps/s | {left} left"
        if progress.eval_rows:
            text += f" | eval return {progress.eval_rows[-1]['episode_return']:.1f}"
            if self.metaworld:
                text += f", success {progress.eval_rows[-1]['success_rate']:.0%}"
        if self.planned:
            text += f" | labels {progress.feedback_used}/{self.planned}"
        if self.terminal:
            print(f"\r{text}\033[K", end="", flush=True)
        else:
            print(text, flush=True)


if __name__ == "__main__":
    args = parse_args()
    device = torch.device("cuda" if args.cuda and torch.cuda.is_available() else "cpu")
    try:
        env, episode_len = make_env(args.env_id)
        eval_env, _ = make_env(args.env_id, "rgb_array" if args.capture_video else None)
        if args.capture_video:
            check_video(eval_env)
        check_args(args, episode_len)
        sampler_seed, teacher_seed, action_seed = numpy_seeds(args.seed)
        episodes = deque(maxlen=args.query_recent_episodes or None)  # the query pool
        teacher_fields = {k.removeprefix("teacher_"): v for k, v in vars(args).items()
                          if k.startswith("teacher_")}
        teacher = make_teacher(args.teacher, teacher_seed, args.output_dir, episodes,
                               **teacher_fields)
        obs_dim = env.observation_space.shape[0]
        action_dim = env.action_space.shape[0]
        empty = torch.zeros(0, args.segment_len, obs_dim + action_dim, device=device)
        preferences = {"inputs0": empty, "inputs1": empty, "y": torch.zeros(0, device=device)}
        if args.labels_from and not args.resume:
            add_labels(preferences, *load_pairs(args.labels_from, empty.shape[1:]))
        checkpoint_path = f"{args.output_dir}/checkpoint.pt"
        if args.resume and not os.path.isfile(checkpoint_path):
            raise ValueError(f"--resume {args.output_dir!r}: no checkpoint.pt there")
        if not args.resume and os.path.isdir(args.output_dir) and os.listdir(args.output_dir):
            raise ValueError(f"--output-dir {args.output_dir!r} already holds a run")
        os.makedirs(f"{args.output_dir}/labels", exist_ok=True)
        if not args.resume:
            save_file(f"{args.output_dir}/config.json", json.dumps(vars(args)).encode())
    except (ValueError, OSError) as error:
        fail(str(error))
    if args.capture_video:
        eval_env = gym.wrappers.RecordVideo(eval_env, f"{args.output_dir}/videos",
                                            episode_trigger=lambda e: e % args.eval_episodes == 0)
    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, sync_tensorboard=True, config=vars(args),
                   name=os.path.basename(args.output_dir), save_code=True)
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(args.output_dir)
    table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
    writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")

    # Seeding: numpy streams, torch, every reset
    rng = np.random.default_rng(sampler_seed)
    action_rng = np.random.default_rng(action_seed)
    torch.manual_seed(args.seed)
    torch.set_flush_denormal(True)  # tiny floats as 0: faster on a CPU
    sizes = (obs_dim, action_dim, args.hidden_dim, args.num_layers)
    actor = Actor(*sizes).to(device)
    critic = TwinCritic(*sizes).to(device)
    critic_target = TwinCritic(*sizes).to(device)
    critic_target.load_state_dict(critic.state_dict())
    graphs = args.compile and device.type == "cuda"
    actor_optimizer = adam(actor.parameters(), args.learning_rate, graphs)
    critic_optimizer = adam(critic.parameters(), args.learning_rate, graphs)
    log_alpha = torch.tensor(math.log(args.init_temperature), device=device, requires_grad=True)
    alpha_optimizer = adam([log_alpha], args.alpha_lr, graphs)
    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = adam(reward_model.parameters(), args.reward_lr)
    buffer = ReplayBuffer(args.buffer_size or args.total_timesteps, obs_dim, action_dim, device)
    intrinsic_stats = RunningMeanStd()
    if args.compile:  # the same names, compiled; on a GPU, CUDA graphs
        sac_update = torch.compile(sac_update)
        learned_reward = torch.compile(learned_reward)
    if graphs:
        sac_update, soft_update, learned_reward, act = map(
            CudaGraph, (sac_update, soft_update, learned_reward, act))
    # Feedback sessions
    first_session = args.seed_steps + args.unsup_steps + 1
    steps = session_steps(first_session, args.feedback_every, args.total_timesteps)
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session,
                                   steps - 1, args.total_timesteps)  # t: steps before step s
    planned = planned_labels(session_sizes, first_session, args.feedback_every,
                             args.total_timesteps)
    if planned < args.max_feedback and not args.ground_truth_reward:
        say(f"note: only {planned} of the {args.max_feedback} labels fit in the run")
    progress = Progress(next_feedback_step=first_session)
    parts = {"progress": progress, "actor": actor, "critic": critic,
             "critic_target": critic_target, "reward_model": reward_model,
             "actor_optimizer": actor_optimizer, "critic_optimizer": critic_optimizer,
             "alpha_optimizer": alpha_optimizer, "reward_optimizer": reward_optimizer,
             "buffer": buffer, "teacher": teacher, "log_alpha": log_alpha,
             "intrinsic_stats": intrinsic_stats, "preferences": preferences, "rng": rng,
             "action_rng": action_rng, "episodes": episodes}
    if args.resume:
        restore(parts, load_checkpoint(checkpoint_path), device)
        for optimizer in (actor_optimizer, critic_optimizer, alpha_optimizer):
            optimizer.param_groups[0]["capturable"] = graphs  # --compile may change on resume
        if progress.global_step >= args.total_timesteps:
            fail(f"the run in {args.output_dir!r} has already finished")
        say(f"resuming from the checkpoint at step {progress.global_step}")
        set_labels_aside(args.output_dir, progress.sessions_done, progress.global_step)
    console = Console(args, progress, planned, device, args.seed_steps)
    # The running episode again from its seed and actions
    seed = episode_seed(args.seed, TRAIN_STREAM, progress.episodes)
    obs, _ = env.reset(seed=seed)
    for action in progress.running_episode[1]:
        obs = env.step(np.array(action, np.float32))[0]
    stop = []  # SIGTERM or SIGINT: checkpoint, exit
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda signum, frame: stop.append(signum))
    losses = {}

    # Algorithm 3 (PEBBLE), Algorithm 2 (unsupervised pre-training) first
    try:
        for global_step in range(progress.global_step + 1, args.total_timesteps + 1):
            # Algorithm 3, lines 9-17: a feedback session when due, then relabelling
            first_learned_reward = False
            if session_due(args, global_step, progress, session_sizes, episodes):
                if args.teacher == "human":  # --resume asks it again
                    save_whole(checkpoint_path, snapshot(parts))
                size = int(session_sizes[progress.sessions_done])
                n_labels = feedback_session(args, global_step, progress, size, episodes,
                                            preferences, reward_model, reward_optimizer, teacher,
                                            rng, writer, episode_len)
                if n_labels:
                    relabel(buffer, reward_model)
                first_learned_reward = n_labels > 0 and not progress.pretrained
            # Pre-training ends (Algorithm 2)
            true_reward_from_now = args.ground_truth_reward and global_step == first_session
            if first_learned_reward or true_reward_from_now:  # critics reset (reference)
                progress.pretrained = True
                reset_critic(critic, critic_target, critic_optimizer)
                for update in range(1, args.critic_reset_updates + 1):
                    batch = buffer.sample(args.batch_size)
                    sac_update(batch, batch.rewards, actor, critic, critic_target, log_alpha,
                               actor_optimizer, critic_optimizer, alpha_optimizer, args.gamma)
                    if update % args.target_update_every == 0:
                        soft_update(critic, critic_target, args.tau)

            # Act, step, store
            if global_step <= args.seed_steps:
                action = action_rng.uniform(-1, 1, action_dim).astype(np.float32)
            else:
                with torch.no_grad():
                    action = act(actor, torch.as_tensor(obs, device=device)).cpu().numpy()
            next_obs, true_reward, terminated, truncated, _ = env.step(action)
            if not (math.isfinite(true_reward) and np.isfinite(next_obs).all()):
                raise FloatingPointError("non-finite reward or observation from the environment")
            reward = float(true_reward) if args.ground_truth_reward else 0.0
            if progress.pretrained and not args.ground_truth_reward:
                with torch.no_grad():
                    reward = learned_reward(reward_model, torch.as_tensor(
                        np.concatenate([obs, action]), device=device))
            buffer.add(obs, action, reward, next_obs, terminated)
            for part, value in zip(progress.running_episode, (obs, action, true_reward)):
                part.append(np.asarray(value).tolist())
            obs = next_obs
            if terminated or truncated:  # to the query pool
                episodes.append((*map(torch.tensor, progress.running_episode), seed))
                episode_return = sum(progress.running_episode[2])
                progress.recent_returns = (progress.recent_returns + [episode_return])[-10:]
                writer.add_scalar("charts/episodic_return", episode_return, global_step)
                progress.running_episode = ([], [], [])
                progress.episodes += 1
                seed = episode_seed(args.seed, TRAIN_STREAM, progress.episodes)
                obs, _ = env.reset(seed=seed)

            # SAC update
            if global_step > args.seed_steps:
                batch = sac_batch(buffer, args, progress, episodes)
                rewards = batch.rewards
                if not progress.pretrained:  # Algorithm 2
                    rewards = intrinsic_reward(batch, buffer, args.knn_k)
                    intrinsic_stats.update(rewards)
                    rewards = rewards / max(math.sqrt(intrinsic_stats.var), 1e-8)
                losses = sac_update(batch, rewards, actor, critic, critic_target, log_alpha,
                                    actor_optimizer, critic_optimizer, alpha_optimizer, args.gamma)
                if (global_step - args.seed_steps) % args.target_update_every == 0:
                    soft_update(critic, critic_target, args.tau)
                if global_step % 100 == 0:
                    for name, value in losses.items():
                        writer.add_scalar(f"losses/{name}", value, global_step)
                    check_finite(losses)

            progress.global_step = global_step
            last_step = global_step == args.total_timesteps
            if global_step % args.eval_every == 0 or last_step:
                evaluation(args, global_step, progress, mean_policy(actor, device), reward_model,
                           eval_env, writer, device)
            console.update(progress)
            periodic = args.checkpoint_every and global_step % args.checkpoint_every == 0
            if periodic or stop or last_step:
                check_finite(losses)
                if last_step:  # before the checkpoint
                    final_model = {"actor": actor.state_dict(), "critic": critic.state_dict(),
                                   "reward_model": reward_model.state_dict()}
                    save_whole(f"{args.output_dir}/final_model.pt", final_model)
                save_whole(checkpoint_path, snapshot(parts))
            if stop and not last_step:
                say(f"{signal.Signals(stop[0]).name}: checkpoint saved at step {global_step}; "
                    f"continue with --resume {args.output_dir}")
                sys.exit(128 + stop[0])
    except (FloatingPointError, OSError) as error:
        fail(f"{error} at step {global_step}; the run stopped, its last checkpoint "
             f"in {args.output_dir} is intact", 3 if isinstance(error, FloatingPointError) else 4)

    say(f"done: {progress.sessions_done} feedback sessions, {progress.feedback_used} queries; "
        f"outputs in {args.output_dir}")
    eval_env.close()
    writer.close()
