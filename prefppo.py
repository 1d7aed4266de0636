# PrefPPO (Christiano et al. 2017) with PPO, as benchmarked by B-Pref (Lee et al. 2021);
# docs/prefppo.md
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
from collections import deque
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
    exp_name: str = "prefppo"
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
    """if toggled, torch.compile the PPO loss"""
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
    total_timesteps: int = 4_000_000
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
                     "entropy-coverage"] = "disagreement"
    """query selection (paper Section 4.2)"""
    schedule: Literal["uniform", "decay", "increase"] = "uniform"
    """feedback schedule (paper Section 4.2)"""
    max_feedback: int = 1000
    """total number of queries (the budget)"""
    feedback_per_session: int = 100
    """queries per feedback session (uniform schedule)"""
    feedback_every: int = 32_000
    """environment steps between feedback sessions"""
    segment_len: int = 50
    """length H of a queried segment"""
    unsup_steps: int = 32000
    """unsupervised pre-training steps (kNN state entropy)"""
    hidden_dim: int = 256
    """hidden units of the actor and critic"""
    num_layers: int = 3
    """hidden layers of the actor and critic"""
    learning_rate: float = 5e-5
    """learning rate of actor and critic"""
    num_envs: int = 32
    """parallel environments"""
    num_steps: int = 500
    """rollout length per environment"""
    update_epochs: int = 20
    """PPO epochs over a rollout after pre-training"""
    unsup_update_epochs: int = 50
    """PPO epochs over a rollout of pre-training"""
    minibatch_size: int = 64
    """PPO minibatch size"""
    gamma: float = 0.99
    """discount"""
    gae_lambda: float = 0.92
    """GAE lambda"""
    use_sde: bool = True
    """generalized state-dependent exploration (gSDE), else a Gaussian"""
    sde_freq: int = 4
    """steps between new gSDE exploration matrices"""
    clip_coef: float = 0.4
    """initial PPO clip range, decayed linearly to 0"""
    ent_coef: float = 0.0
    """entropy bonus"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """gradient clipping norm"""
    eval_every: int = 50000
    """environment steps between evaluations"""
    eval_episodes: int = 10
    """episodes per evaluation"""
    ground_truth_reward: bool = False
    """if toggled, PPO learns from the true reward, with no teacher"""
    knn_k: int = 5
    """k of the kNN state-entropy reward"""
    reward_ensemble_size: int = 3
    """reward models in the ensemble"""
    reward_lr: float = 3e-4
    """learning rate of the reward models"""
    reward_batch_size: int = 128
    """preference batch size of reward learning"""
    reward_epochs: int = 100
    """most epochs of reward learning per session (it stops at 97% accuracy)"""
    label_smoothing: float = 0.0
    """soft labels (1 - s) y + s / 2"""
    candidate_multiplier: int = 10
    """candidate pairs per query for the uncertainty and coverage samplers"""
    query_recent_episodes: int = 0
    """segments come from the last N complete episodes (0: all)"""


# Paper appendix, PrefPPO's hyperparameters; reward_epochs: the reference scripts' re_update
METAWORLD = dict(total_timesteps=3_000_000, max_feedback=10_000, feedback_every=16_000,
                 segment_len=25, learning_rate=3e-4, num_envs=8, num_steps=250, minibatch_size=128,
                 reward_epochs=50)
PRESETS = {
    "quadruped-walk": dict(num_envs=16, minibatch_size=128, gae_lambda=0.9),
    "metaworld": METAWORLD,
    "sweep-into": METAWORLD | dict(num_envs=32, minibatch_size=256),
    "gym": dict(learning_rate=3e-4, num_envs=8, num_steps=256, gae_lambda=0.95),
}


# Console's note: each task's CPU scale
CPU_SCALES = {
    "walker-walk": "walker-walk, experiments/grid.py parity-prefppo (--total-timesteps 1000000), "
    "took 27-36 min",
    "quadruped-walk": "quadruped-walk, experiments/grid.py quadruped-walk-cpu-prefppo "
    "(--total-timesteps 1000000), took 23-59 min",
    "button-press": "button-press, experiments/grid.py button-press-cpu-prefppo (--total-timesteps "
    "1000000 --max-feedback 6100), took 1.5-2.8 h",
    "sweep-into": "sweep-into, experiments/grid.py sweep-into-cpu-prefppo (--total-timesteps "
    "1000000 --max-feedback 6100), took 1.6-2.7 h",
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
def mlp(in_dim, out_dim, hidden_dim, num_layers, activation=nn.Tanh):
    layers = []
    for i in range(num_layers):
        layers += [nn.Linear(hidden_dim if i else in_dim, hidden_dim), activation()]
    return nn.Sequential(*layers, nn.Linear(hidden_dim, out_dim))


def orthogonal_init(module, gain):
    """Reference code (SB3's ActorCriticPolicy): orthogonal weights, zero biases."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)
    return module


def sde_std(latent, log_std, eps=1e-6):
    """gSDE: the std of latent @ W, W_ij ~ N(0, exp(log_std_ij)^2) (SB3)."""
    return torch.sqrt(latent**2 @ log_std.exp() ** 2 + eps)


class Actor(nn.Module):
    """SB3's PPO policy; gSDE: env n acts mean + latent @ W_n (latent: the last hidden layer)."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers, use_sde):
        super().__init__()
        self.policy = mlp(obs_dim, action_dim, hidden_dim, num_layers)
        orthogonal_init(self.policy, math.sqrt(2))
        orthogonal_init(self.policy[-1], 0.01)
        self.use_sde = use_sde
        log_std_shape = (hidden_dim, action_dim) if use_sde else (action_dim,)
        self.log_std = nn.Parameter(torch.zeros(log_std_shape))
        self.exploration = None  # gSDE: the W_n, (envs, hidden, action)

    def distribution(self, obs):
        latent = self.policy[:-1](obs)
        mean = self.policy[-1](latent)
        std = sde_std(latent.detach(), self.log_std) if self.use_sde else self.log_std.exp()
        return torch.distributions.Normal(mean, std, validate_args=False), latent

    def sample(self, obs, step, sde_freq):
        distribution, latent = self.distribution(obs)
        if not self.use_sde:
            action = distribution.sample()
        else:
            if step % sde_freq == 0:
                noise = torch.randn(len(obs), *self.log_std.shape, device=obs.device)
                self.exploration = self.log_std.exp() * noise
            action = distribution.loc + (latent.detach().unsqueeze(1) @ self.exploration)[:, 0]
        return action, distribution.log_prob(action).sum(-1)


def mean_policy(actor, obs_stats, device):
    return lambda obs: actor.policy(obs_stats.normalize(obs).to(device)).clamp(-1, 1)


def make_critic(obs_dim, hidden_dim, num_layers):
    critic = orthogonal_init(mlp(obs_dim, 1, hidden_dim, num_layers), math.sqrt(2))
    orthogonal_init(critic[-1], 1.0)
    return critic


def reset_value_head(critic):
    """Reference code (reset_value): a new output layer."""
    orthogonal_init(critic[-1], 1.0)


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
def clip_range(clip_coef, global_step, total_timesteps):
    """Reference code (SB3's linear_schedule)."""
    return clip_coef * max(0.0, 1.0 - global_step / total_timesteps)


def ppo_policy_loss(log_prob, old_log_prob, advantages, clip):
    """Appendix Eq. (4)."""
    ratio = (log_prob - old_log_prob).exp()
    clipped = ratio.clamp(1 - clip, 1 + clip)
    return torch.max(-advantages * ratio, -advantages * clipped).mean(), ratio


def optimize(optimizer, loss, max_grad_norm=None):
    """A gradient step of this optimizer's parameters only."""
    optimizer.zero_grad()
    params = [param for group in optimizer.param_groups for param in group["params"]]
    loss.backward(inputs=params)  # only this optimizer's networks
    if max_grad_norm is not None:
        nn.utils.clip_grad_norm_(params, max_grad_norm)
    optimizer.step()


def adam(params, lr, eps=1e-8):
    # fused: one kernel per step
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)


def ppo_loss(actor, critic, obs, actions, old_logprobs, advantages, returns, clip, args):
    """Appendix Eqs. (4)-(5), advantages normalised per minibatch (SB3)."""
    distribution, _ = actor.distribution(obs)
    adv = advantages
    if len(obs) > 1:
        adv = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    entropy = distribution.entropy().sum(-1).mean()
    log_prob = distribution.log_prob(actions).sum(-1)
    policy_loss, ratio = ppo_policy_loss(log_prob, old_logprobs, adv, clip)
    value_loss = F.mse_loss(critic(obs)[:, 0], returns)  # Eq. (5), unclipped (reference code)
    # approx_kl from the log-ratio: far off-policy the ratio underflows to 0 and its log is -inf
    stats = {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
             "approx_kl": ((ratio - 1) - (log_prob - old_logprobs)).mean(),
             "clipfrac": ((ratio - 1).abs() > clip).float().mean()}
    return policy_loss + args.vf_coef * value_loss - args.ent_coef * entropy, stats


def ppo_update(obs, actions, logprobs, advantages, returns, actor, critic, optimizer, epochs, clip,
               args):
    rollout = (obs, actions, logprobs, advantages, returns)
    clip_fractions = []
    for _ in range(epochs):
        order = torch.randperm(len(obs), device=obs.device)
        for minibatch in zip(*[x[order].split(args.minibatch_size) for x in rollout]):
            loss, stats = ppo_loss(actor, critic, *minibatch, clip, args)
            optimize(optimizer, loss, args.max_grad_norm)
            clip_fractions.append(stats["clipfrac"])
    stats = {name: value.detach() for name, value in stats.items()}
    return stats | {"clipfrac": torch.stack(clip_fractions).mean()}


def compute_gae(rewards, values, next_values, ends, gamma, gae_lambda):
    """GAE over a (steps, envs) rollout; next_values: V of the states reached, 0 if terminal."""
    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(rewards[0])
    for t in reversed(range(len(rewards))):
        delta = rewards[t] + gamma * next_values[t] - values[t]
        last = delta + gamma * gae_lambda * (1.0 - ends[t]) * last
        advantages[t] = last
    return advantages, advantages + values


def knn_distance(states, reference, k):
    """Eq. (8) without the log: distance to the k-th nearest other state."""
    distances = torch.cdist(states, reference)
    nearest = distances.topk(min(k + 1, len(reference)), dim=1, largest=False).values
    return nearest[:, -1:].contiguous()  # its statistics then sum in a fixed order


@dataclass
class RunningMeanStd:
    """SB3's (the reference's), not pebble.py's: per column, float64, counting from 1e-4."""

    mean: torch.Tensor = field(default_factory=lambda: torch.zeros(1).double())
    var: torch.Tensor = field(default_factory=lambda: torch.ones(1).double())
    count: float = 1e-4

    def update(self, x):
        n = len(x)
        total = self.count + n
        delta = torch.from_numpy(x.mean(0)) - self.mean
        m2 = self.var * self.count + torch.from_numpy(x.var(0)) * n
        m2 += delta**2 * self.count * n / total
        self.mean = self.mean + delta * n / total
        self.var = m2 / total
        self.count = total

    def normalize(self, x):
        """Reference code (VecNormalize)."""
        return ((torch.from_numpy(x) - self.mean) / (self.var + 1e-8).sqrt()).clamp(-10, 10).float()


@dataclass
class KnnStateEntropy(RunningMeanStd):
    """Algorithm 2's r_int(s_t) among all pre-training states, over its running std."""

    k: int = 5
    states: torch.Tensor = field(default_factory=lambda: torch.zeros(0))

    def __call__(self, states):
        self.states = torch.cat([self.states, states])
        distance = knn_distance(states, self.states, self.k)[:, 0]
        self.update(distance.numpy()[:, None])
        return distance / math.sqrt(self.var[0] + 1e-8)


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
    """Algorithm 3, reward learning (reference: stops at 97% accuracy on the strict labels)."""
    inputs0 = reward_model.normalize(preferences["inputs0"])
    inputs1 = reward_model.normalize(preferences["inputs1"])
    y = preferences["y"]
    for _ in range(args.reward_epochs):
        orders = [torch.randperm(len(y), device=y.device) for _ in reward_model.members]
        correct = torch.zeros((), device=y.device)
        losses = []
        for start in range(0, len(y), args.reward_batch_size):
            loss = 0.0
            for member, order in zip(reward_model.members, orders):
                idx = order[start : start + args.reward_batch_size]
                returns = torch.cat([member(inputs0[idx]).sum(1), member(inputs1[idx]).sum(1)], -1)
                loss += preference_loss(returns, y[idx], args.label_smoothing)
                right = (returns[:, 1] > returns[:, 0]) == (y[idx] > 0.5)
                correct += (right & (y[idx] != 0.5)).sum()
            optimize(optimizer, loss)
            losses.append(loss.detach() / len(reward_model.members))
        strict = (y != 0.5).sum().item() * len(reward_model.members)
        accuracy = correct.item() / strict if strict else 0.0  # only equal labels: no accuracy
        if accuracy > 0.97:
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


def restart_env(env, args, progress, i):
    """Env i's running episode again from its reset seed and actions."""
    obs, _ = env.reset(seed=train_seed(args, progress, i))
    for action in progress.running_episodes[i][1]:
        obs = env.step(np.array(action, np.float32))[0]
    return obs


def train_seed(args, progress, i):
    return episode_seed(args.seed, TRAIN_STREAM, progress.episodes[i] * args.num_envs + i)


def step_envs(envs, kept_obs, actions, args, progress, episodes, writer, step):
    """A step of every env; an ended episode goes to the query pool, with its reset seed."""
    results = [env.step(action) for env, action in zip(envs, actions)]
    reached, rewards, terminated, truncated = map(np.array, list(zip(*results))[:4])
    if not (np.isfinite(rewards).all() and np.isfinite(reached).all()):
        raise FloatingPointError("non-finite reward or observation from the environment")
    next_obs = reached.copy()
    for i, running in enumerate(progress.running_episodes):
        for part, value in zip(running, (kept_obs, actions, rewards)):
            part.append(value[i].tolist())
        if terminated[i] or truncated[i]:
            episodes.append((*map(torch.tensor, running), train_seed(args, progress, i)))
            progress.recent_returns = (progress.recent_returns + [sum(running[2])])[-100:]
            writer.add_scalar("charts/episodic_return", sum(running[2]), step)
            progress.running_episodes[i] = ([], [], [])
            progress.episodes[i] += 1
            next_obs[i] = restart_env(envs[i], args, progress, i)
    return next_obs, reached, rewards, terminated, terminated | truncated


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
    ("seed unsup_steps checkpoint_every ent_coef vf_coef query_recent_episodes",
     lambda v: v >= 0, ">= 0"),
    ("max_feedback feedback_per_session feedback_every hidden_dim num_layers num_envs "
     "num_steps update_epochs unsup_update_epochs minibatch_size sde_freq eval_every "
     "eval_episodes knn_k reward_ensemble_size reward_batch_size reward_epochs "
     "candidate_multiplier", lambda v: v >= 1, ">= 1"),
    ("learning_rate reward_lr clip_coef max_grad_norm", lambda v: v > 0, "> 0"),
    ("gamma", lambda v: 0 < v <= 1, "in (0, 1]"),
    ("gae_lambda", lambda v: 0 <= v <= 1, "in [0, 1]"),
    ("label_smoothing", lambda v: 0 <= v < 1, "in [0, 1)"),
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
    rollout = args.num_envs * args.num_steps
    rules = RANGES + [
        ("feedback_per_session", lambda v: v <= args.max_feedback, "<= --max-feedback"),
        ("segment_len", lambda v: 1 <= v <= episode_len, f"in [1, {episode_len}] (T)"),
        ("minibatch_size", lambda v: v <= rollout, f"<= --num-envs x --num-steps ({rollout})"),
        ("total_timesteps", lambda v: v > args.unsup_steps and v >= rollout,
         f"> --unsup-steps ({args.unsup_steps}) and >= a rollout ({rollout})"),
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


@dataclass
class Progress:
    """What the main loop carries besides networks, optimizers and buffers."""

    global_step: int = 0
    episodes: list = field(default_factory=list)  # env i runs its episode number episodes[i]
    running_episodes: list = field(default_factory=list)  # env i's: obs, actions, rewards
    recent_returns: list = field(default_factory=list)  # of the last 100 training episodes
    sessions_done: int = 0
    feedback_used: int = 0
    next_feedback_step: int = 0
    pretrained: bool = False  # PPO learns from r_hat (or the true reward)
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
        sampler_seed, teacher_seed, _ = numpy_seeds(args.seed)
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
    torch.manual_seed(args.seed)
    torch.set_flush_denormal(True)  # tiny floats as 0: faster on a CPU
    envs = [env] + [make_env(args.env_id)[0] for _ in range(args.num_envs - 1)]
    actor = Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers, args.use_sde).to(device)
    critic = make_critic(obs_dim, args.hidden_dim, args.num_layers).to(device)
    optimizer = adam([*actor.parameters(), *critic.parameters()], args.learning_rate, eps=1e-5)
    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = adam(reward_model.parameters(), args.reward_lr)
    obs_stats = RunningMeanStd()
    knn_reward = KnnStateEntropy(k=args.knn_k)
    if args.compile:  # ppo_update calls it by this name
        ppo_loss = torch.compile(ppo_loss)
    # Feedback sessions at rollout ends, from the end of pre-training
    rollout = args.num_envs * args.num_steps
    # a session opens a rollout: none at the last step
    steps = session_steps(args.unsup_steps, args.feedback_every, args.total_timesteps - 1, rollout)
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session,
                                   steps, args.total_timesteps)
    planned = planned_labels(session_sizes, args.unsup_steps, args.feedback_every,
                             args.total_timesteps - 1, rollout)
    if planned < args.max_feedback and not args.ground_truth_reward:
        say(f"note: only {planned} of the {args.max_feedback} labels fit in the run")
    progress = Progress(episodes=[0] * args.num_envs, next_feedback_step=args.unsup_steps,
                        running_episodes=[([], [], []) for _ in envs])
    parts = {"progress": progress, "actor": actor, "critic": critic, "reward_model": reward_model,
             "optimizer": optimizer, "reward_optimizer": reward_optimizer, "teacher": teacher,
             "obs_stats": obs_stats, "knn_reward": knn_reward, "preferences": preferences,
             "rng": rng, "episodes": episodes}
    if args.resume:
        restore(parts, load_checkpoint(checkpoint_path), device)
        if progress.global_step >= args.total_timesteps:
            fail(f"the run in {args.output_dir!r} has already finished")
        say(f"resuming from the checkpoint at step {progress.global_step}")
        set_labels_aside(args.output_dir, progress.sessions_done, progress.global_step)
    console = Console(args, progress, planned, device)
    raw_obs = np.stack([restart_env(env, args, progress, i) for i, env in enumerate(envs)])
    # The rollout: raw and normalised observations, sampled and clipped (executed) actions
    shape = (args.num_steps, args.num_envs)
    raw_obs_buf, obs_buf = (torch.zeros(*shape, obs_dim, device=device) for _ in range(2))
    actions_buf, env_actions_buf = (torch.zeros(*shape, action_dim, device=device)
                                    for _ in range(2))
    logprobs_buf, values_buf, next_values_buf, rewards_buf, ends_buf = (
        torch.zeros(shape, device=device) for _ in range(5))
    stop = []  # SIGTERM or SIGINT: checkpoint after this rollout, then exit
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda signum, frame: stop.append(signum))

    # Main loop: Algorithm 3 with PPO, after Algorithm 2 (unsupervised pre-training)
    try:
        while progress.global_step < args.total_timesteps:
            # Algorithm 3 with PPO: a feedback session when due
            global_step = progress.global_step
            first_learned_reward = False
            if session_due(args, global_step, progress, session_sizes, episodes):
                if args.teacher == "human":  # --resume asks this session again
                    save_whole(checkpoint_path, snapshot(parts))
                size = int(session_sizes[progress.sessions_done])
                n_labels = feedback_session(args, global_step, progress, size, episodes,
                                            preferences, reward_model, reward_optimizer, teacher,
                                            rng, writer, episode_len)
                first_learned_reward = n_labels > 0 and not progress.pretrained
            # Pre-training ends (Algorithm 2)
            true_reward_from_now = (args.ground_truth_reward and global_step >= args.unsup_steps
                                    and not progress.pretrained)
            if first_learned_reward or true_reward_from_now:  # reference: value head reset
                progress.pretrained = True
                reset_value_head(critic)

            # Rollout of num_steps in every env
            for t in range(args.num_steps):
                obs_stats.update(raw_obs)
                obs = obs_stats.normalize(raw_obs).to(device)
                with torch.no_grad():
                    action, logprobs_buf[t] = actor.sample(obs, t, args.sde_freq)
                    values_buf[t] = critic(obs)[:, 0]
                env_action = action.clamp(-1, 1)
                step = global_step + (t + 1) * args.num_envs
                next_obs, reached, true_reward, terminated, ends = step_envs(
                    envs, raw_obs, env_action.cpu().numpy(), args, progress, episodes, writer, step)
                raw_obs_buf[t] = torch.as_tensor(raw_obs)
                obs_buf[t] = obs
                actions_buf[t] = action
                env_actions_buf[t] = env_action
                if progress.pretrained:  # the true reward: r_hat's replaces it below
                    rewards_buf[t] = torch.as_tensor(true_reward)
                else:  # Algorithm 2's r_int(s_t)
                    rewards_buf[t] = knn_reward(torch.from_numpy(raw_obs))
                ends_buf[t] = torch.as_tensor(ends)
                with torch.no_grad():  # time limits bootstrapped
                    next_values = critic(obs_stats.normalize(reached).to(device))[:, 0]
                next_values_buf[t] = next_values * torch.as_tensor(~terminated, device=device)
                raw_obs = next_obs
            global_step += rollout
            progress.global_step = global_step

            # The reward PPO maximises: r_int (pre-training), r_hat or the true reward
            rewards = rewards_buf
            if progress.pretrained and not args.ground_truth_reward:
                with torch.no_grad():
                    obs_actions = torch.cat([raw_obs_buf, env_actions_buf], -1)
                    rewards = reward_model(obs_actions).mean(0)[..., 0]
                pair = torch.stack([rewards.flatten(), rewards_buf.flatten()])
                correlation = torch.corrcoef(pair)[0, 1]
                writer.add_scalar("reward/rollout_correlation", correlation, global_step)
            advantages, returns = compute_gae(rewards, values_buf, next_values_buf, ends_buf,
                                              args.gamma, args.gae_lambda)

            # PPO update (appendix Eqs. (4)-(5))
            # a tensor: --compile's loss then does not recompile for each new clip range
            clip = torch.tensor(clip_range(args.clip_coef, global_step, args.total_timesteps),
                                device=device)
            epochs = args.update_epochs if progress.pretrained else args.unsup_update_epochs
            batch = [x.flatten(0, 1) for x in (obs_buf, actions_buf, logprobs_buf, advantages,
                                               returns)]
            losses = ppo_update(*batch, actor, critic, optimizer, epochs, clip, args)
            explained = 1 - (returns - values_buf).var() / returns.var().clamp(1e-8)
            losses["explained_variance"] = explained
            for name, value in losses.items():
                writer.add_scalar(f"losses/{name}", value, global_step)
            check_finite(losses)

            console.update(progress)
            last_step = global_step >= args.total_timesteps
            if global_step % args.eval_every < rollout or last_step:
                policy = mean_policy(actor, obs_stats, device)
                evaluation(args, global_step, progress, policy, reward_model, eval_env, writer,
                           device)
            periodic = args.checkpoint_every > 0 and global_step % args.checkpoint_every < rollout
            if periodic or stop or last_step:
                if last_step:  # before the checkpoint
                    final_model = {"actor": actor.state_dict(), "critic": critic.state_dict(),
                                   "reward_model": reward_model.state_dict(),
                                   "obs_mean": obs_stats.mean, "obs_var": obs_stats.var}
                    save_whole(f"{args.output_dir}/final_model.pt", final_model)
                save_whole(checkpoint_path, snapshot(parts))
            if stop and not last_step:
                say(f"{signal.Signals(stop[0]).name}: checkpoint saved at step {global_step}; "
                    f"continue with --resume {args.output_dir}")
                sys.exit(128 + stop[0])
    except (FloatingPointError, OSError) as error:
        fail(f"{error} at step {progress.global_step}; the run stopped, its last checkpoint in "
             f"{args.output_dir} is intact", 3 if isinstance(error, FloatingPointError) else 4)

    say(f"done: {progress.sessions_done} feedback sessions, {progress.feedback_used} queries; "
        f"outputs in {args.output_dir}")
    eval_env.close()
    writer.close()
