# PEBBLE (Lee, Smith, Abbeel 2021) as benchmarked by B-Pref (Lee et al. 2021); docs/pebble.md
import contextlib
import glob
import io
import json
import math
import os
import signal
import sys
import time
import warnings
from collections import deque, namedtuple
from dataclasses import asdict, dataclass, field, fields
from typing import Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro

from samplers import draw_segments, planned_labels, schedule_sizes, select, session_steps
from sim_teacher import make_teacher


@dataclass
class Args:
    exp_name: str = "pebble"
    """the name of this experiment (part of the run name)"""
    seed: int = 1
    """seed of the experiment"""
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
    """seed the preference dataset with an earlier run's labels (its directory, labels/ or one .npz)
    """

    # Algorithm specific arguments; None = the task's preset (PRESETS below)
    env_id: str = "walker-walk"
    """DMC `domain-task`, Meta-World v3 task name (with or without -v3), or a Gymnasium id"""
    total_timesteps: int | None = None
    """total environment steps"""
    teacher: Literal["oracle", "stoc", "mistake", "skip", "equal", "myopic", "human"] = "oracle"
    """simulated teacher (paper Section 3.3), or human: a person, in label_server.py's page"""
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
    sampler: Literal["uniform", "disagreement", "entropy", "coverage", "disagreement-coverage",
                     "entropy-coverage"] = "disagreement"
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
    reward_input_norm: bool = False
    """if toggled, the reward model sees observations standardised by D's states, clipped to +-10
    (reference code: raw observations)"""
    candidate_multiplier: int = 10
    """candidate pairs per query for the uncertainty and coverage samplers"""
    query_recent_episodes: int = 100
    """segments come from the last N complete episodes (reference code: 100; 0 = all so far)"""
    critic_reset_updates: int = 100
    """SAC updates on relabelled data right after the critic reset of the first reward update"""

# Paper appendix, Table of PEBBLE hyperparameters (sources of the others: docs/differences.md).
# Meta-World: feedback every 4950 steps, not the paper's 5000, so that all 200 sessions (10,000
# labels) fit in 1M steps (planned_labels); segments of 50, not the table's 25: the reference's
# Meta-World scripts never set it, so its runs used 50
DMC_PRESET = dict(total_timesteps=500_000, max_feedback=1000, feedback_per_session=100,
                  feedback_every=20_000, segment_len=50, hidden_dim=1024, num_layers=2,
                  batch_size=1024, learning_rate=5e-4, reward_epochs=50)
METAWORLD_PRESET = dict(total_timesteps=1_000_000, max_feedback=10_000, feedback_per_session=50,
                        feedback_every=4950, segment_len=50, hidden_dim=256, num_layers=3,
                        batch_size=512, learning_rate=3e-4, reward_epochs=10)
GYM_PRESET = dict(DMC_PRESET, hidden_dim=256, num_layers=2, batch_size=256, learning_rate=3e-4)
PRESETS = {"walker-walk": DMC_PRESET, "button-press": METAWORLD_PRESET,
           "sweep-into": METAWORLD_PRESET,
           "quadruped-walk": dict(DMC_PRESET, total_timesteps=1_000_000, feedback_every=30_000,
                                  learning_rate=1e-4)}
CPU_SCALE = ("python pebble.py --env-id walker-walk --total-timesteps 100000 --hidden-dim 256 "
             "--num-layers 2 --batch-size 256 --max-feedback 1000 --feedback-per-session 100 "
             "--feedback-every 9000")  # the README's


# Environments
class DMCEnv(gym.Env):
    """A dm_control suite task as a Gymnasium env: flat observations, episodes end by truncation;
    reset(seed=s) re-seeds the task's random state: an episode is a function of s and the
    actions."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, domain: str, task: str, render_mode: str | None = None):
        from dm_control import suite

        self.dmc = suite.load(domain, task)
        self.render_mode = render_mode
        obs_dim = sum(int(np.prod(v.shape)) for v in self.dmc.observation_spec().values())
        spec = self.dmc.action_spec()
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(spec.minimum.astype(np.float32),
                                           spec.maximum.astype(np.float32))

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.dmc.task.random.seed(seed)
        return np.concatenate([np.ravel(v) for v in self.dmc.reset().observation.values()]), {}

    def step(self, action):
        step = self.dmc.step(action)
        obs = np.concatenate([np.ravel(v) for v in step.observation.values()])
        terminated = step.last() and step.discount == 0
        truncated = step.last() and step.discount != 0
        return obs, step.reward, terminated, truncated, {}

    def render(self):
        return self.dmc.physics.render(height=240, width=320, camera_id=0)

    def close(self):  # frees the renderer's context (else dm_control complains at exit)
        self.dmc.physics.free()


class MetaWorldSeeding(gym.Wrapper):
    """Meta-World's reset ignores `seed`: here it seeds the generator of object and goal positions.
    """

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.env.unwrapped.seed(seed)
        return self.env.reset(options=options)


def env_kind(env_id: str) -> str:
    """'dmc' for a suite task (domain-task), 'metaworld' for a v3 task name, else 'gym'."""
    import metaworld

    with warnings.catch_warnings(action="ignore"):  # GLFW's "failed to open display" when headless
        from dm_control import suite
    if tuple(env_id.split("-", 1)) in suite.ALL_TASKS:
        return "dmc"
    if f"{env_id.removesuffix('-v3')}-v3" in metaworld.ALL_V3_ENVIRONMENTS:
        return "metaworld"
    return "gym"


def make_env(env_id: str, render_mode: str | None = None) -> tuple[gym.Env, int]:
    """(env, episode length T): actions rescaled to [-1, 1], observations flat float32. Every reset
    is seeded by the caller (episode_seed), so nothing carries over from one episode to the next."""
    kind = env_kind(env_id)
    if kind == "dmc":
        env = DMCEnv(*env_id.split("-", 1), render_mode)
        episode_len = int(env.dmc._step_limit)
    elif kind == "metaworld":
        # disable_env_checker: its checker warns about the hidden goal's zero bounds
        env = gym.make("Meta-World/MT1", env_name=f"{env_id.removesuffix('-v3')}-v3",
                       render_mode=render_mode, disable_env_checker=True)
        # B-Pref: fixed 500-step episodes
        env.get_wrapper_attr("toggle_terminate_on_success")(False)
        # Reference code (utils.make_metaworld_env): a fresh goal from the task's whole range at
        # every reset, not one of MT1's 50 fixed goals: one task for its settings, then the random
        # vector (object and goal positions) is unfrozen and drawn from the env's generator. The
        # goal is hidden (zeros), as in the reference's v2 envs
        env.unwrapped.set_task(env.get_wrapper_attr("tasks")[0])
        env.get_wrapper_attr("toggle_sample_tasks_on_reset")(False)
        env.unwrapped._partially_observable = True
        env.unwrapped._freeze_rand_vec = False
        env.unwrapped.seeded_rand_vec = True
        episode_len = env.spec.max_episode_steps or 500
        env = MetaWorldSeeding(env)
    else:
        try:  # "my_package:MyEnv-v0": Gymnasium imports my_package, which registers MyEnv-v0
            env = gym.make(env_id, **({"render_mode": render_mode} if render_mode else {}))
        except (gym.error.Error, ImportError) as error:
            raise ValueError(f"--env-id {env_id!r} is not a DMC task (domain-task, e.g. "
                             "walker-walk), a Meta-World v3 task (e.g. button-press) or a "
                             f"Gymnasium id (optionally module:id): {error}") from None
        episode_len = env.spec.max_episode_steps
        boxes = isinstance(env.action_space, gym.spaces.Box) and isinstance(
            env.observation_space, gym.spaces.Box)
        if not (boxes and episode_len):
            raise ValueError(f"--env-id {env_id!r} needs Box observation and action spaces and a "
                             "time limit")
    bound = np.ones(env.action_space.shape, np.float32)  # float32: no "precision lowered" warnings
    env = gym.wrappers.RescaleAction(env, -bound, bound)
    space = gym.spaces.Box(-np.inf, np.inf, env.observation_space.shape, np.float32)
    env = gym.wrappers.TransformObservation(env, lambda obs: np.asarray(obs, np.float32), space)
    return env, episode_len


TRAIN_STREAM = 0  # the streams of episode seeds of the training and the evaluation envs
EVAL_STREAM = 1


def numpy_seeds(seed: int) -> list[np.random.SeedSequence]:
    """Independent streams from one run seed: query sampler, teacher, the seed steps' random
    actions."""
    return np.random.SeedSequence(seed).spawn(3)


def episode_seed(run_seed: int, stream: int, episode: int) -> int:
    """The reset seed of an episode of a stream, drawn from SeedSequence([run_seed, stream,
    episode]): any episode can be played again alone, and runs with different seeds share no
    episode."""
    return int(np.random.SeedSequence([run_seed, stream, episode]).generate_state(1)[0])


# Networks
def mlp(in_dim: int, out_dim: int, hidden_dim: int, num_layers: int, activation=nn.ReLU):
    layers = []
    for i in range(num_layers):
        layers += [nn.Linear(hidden_dim if i else in_dim, hidden_dim), activation()]
    return nn.Sequential(*layers, nn.Linear(hidden_dim if num_layers else in_dim, out_dim))


def orthogonal_init(module: nn.Module) -> nn.Module:
    """Reference code (utils.weight_init, applied to actor and critics): orthogonal weights, zero
    biases."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight)
            nn.init.zeros_(layer.bias)
    return module


LOG_STD_MIN = -5  # the reference SAC's log std bounds
LOG_STD_MAX = 2


class Actor(nn.Module):
    """Tanh-squashed Gaussian policy; log std bounded to [-5, 2] as in the reference SAC."""

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


def mean_policy(actor: Actor, device) -> callable:
    """The policy evaluated: an observation -> the mean action, a tensor on the device."""
    return lambda obs: torch.tanh(actor(torch.as_tensor(obs, device=device))[0])


class TwinCritic(nn.Module):
    """Two Q-networks, Q(s, a) -> (q1, q2)."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers):
        super().__init__()
        self.sizes = (obs_dim, action_dim, hidden_dim, num_layers)
        self.q1 = mlp(obs_dim + action_dim, 1, hidden_dim, num_layers)
        self.q2 = mlp(obs_dim + action_dim, 1, hidden_dim, num_layers)
        orthogonal_init(self)

    def forward(self, obs, action):
        x = torch.cat([obs, action], dim=-1)
        return self.q1(x), self.q2(x)


class RewardEnsemble(nn.Module):
    """Appendix "Reward model": members of 3 x 256 LeakyReLU layers with a tanh-bounded output;
    (..., obs+action) -> each member's reward (members, ..., 1). Its inputs pass normalize(): the
    identity, or with --reward-input-norm the observations standardised and clipped."""

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

    def set_input_stats(self, states: torch.Tensor):
        """--reward-input-norm: standardise observations by these states (rows), clip to +-10."""
        obs_dim = states.shape[-1]
        self.input_mean[:obs_dim] = states.mean(0)
        self.input_std[:obs_dim] = (states.var(0, unbiased=False) + 1e-8).sqrt()
        self.input_clip.fill_(10.0)

    def forward(self, obs_action):
        inputs = self.normalize(obs_action)
        return torch.stack([member(inputs) for member in self.members])


# Algorithm: the math a reader must trust (each unit-tested), the replay buffer, reward learning
def tanh_gaussian_log_prob(mean, log_std, pre_tanh) -> torch.Tensor:
    """log pi(a|s) of a = tanh(u), u ~ N(mean, exp(log_std)^2), summed over the action (batch, 1):
    the Gaussian's log-density minus log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)) (SAC paper,
    appendix C; stable form)."""
    z = (pre_tanh - mean) / log_std.exp()
    gaussian = -0.5 * z**2 - log_std - 0.5 * math.log(2 * math.pi)
    squash = 2 * (math.log(2) - pre_tanh - F.softplus(-2 * pre_tanh))
    return (gaussian - squash).sum(-1, keepdim=True)


def sac_critic_loss(q1, q2, rewards, terminated, next_q, next_log_prob, alpha, gamma):
    """Appendix Eq. (6), both critics: target r + gamma (1 - terminated) (min target Q(s', a') -
    alpha log pi(a'|s')), a' ~ pi(s'); it bootstraps through a time limit, not a termination."""
    target = (rewards + gamma * (1 - terminated) * (next_q - alpha * next_log_prob)).detach()
    return F.mse_loss(q1, target) + F.mse_loss(q2, target)


def sac_actor_loss(log_prob, q1, q2, alpha) -> torch.Tensor:
    """Appendix Eq. (7): E[alpha log pi(a|s) - Q(s, a)], a ~ pi(s), with the smaller critic."""
    return (alpha * log_prob - torch.min(q1, q2)).mean()


def temperature_loss(log_alpha, log_prob, target_entropy: float) -> torch.Tensor:
    """SAC's learned temperature (reference code: agent/sac.py): alpha grows while the policy's
    entropy -log pi is below the target entropy (-action dim), and shrinks while above."""
    return (log_alpha.exp() * (-log_prob.detach() - target_entropy)).mean()


def optimize(optimizer, loss: torch.Tensor):
    """One gradient step of this optimizer's parameters only (the actor's loss: no critic
    gradient)."""
    optimizer.zero_grad()
    loss.backward(inputs=[param for group in optimizer.param_groups for param in group["params"]])
    optimizer.step()


def adam(params, lr: float, eps: float = 1e-8) -> torch.optim.Adam:
    """Adam with fused kernels (one kernel a step): the same update, up to float rounding."""
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)


Batch = namedtuple("Batch", "obs actions rewards next_obs terminated")  # replay-buffer rows


def sac_update(batch, rewards, actor, critic, critic_target, log_alpha, actor_opt, critic_opt,
               alpha_opt, gamma) -> dict:
    """One SAC step on a batch whose rewards are r_hat, the true reward or the kNN state entropy."""
    alpha = log_alpha.exp().detach()
    with torch.no_grad():
        next_actions, next_log_prob = actor.sample(batch.next_obs)
        next_q = torch.min(*critic_target(batch.next_obs, next_actions))
    q1, q2 = critic(batch.obs, batch.actions)
    critic_loss = sac_critic_loss(q1, q2, rewards, batch.terminated, next_q, next_log_prob, alpha,
                                  gamma)
    optimize(critic_opt, critic_loss)
    actions, log_prob = actor.sample(batch.obs)
    actor_loss = sac_actor_loss(log_prob, *critic(batch.obs, actions), alpha)
    optimize(actor_opt, actor_loss)
    alpha_loss = temperature_loss(log_alpha, log_prob, -batch.actions.shape[-1])
    optimize(alpha_opt, alpha_loss)
    losses = {"critic_loss": critic_loss, "actor_loss": actor_loss, "alpha_loss": alpha_loss,
              "entropy": -log_prob.mean(), "alpha": alpha, "batch_reward": rewards.mean()}
    return {name: value.detach() for name, value in losses.items()}


def soft_update(critic: nn.Module, critic_target: nn.Module, tau: float):
    with torch.no_grad():
        for param, target_param in zip(critic.parameters(), critic_target.parameters()):
            target_param.lerp_(param, tau)


class ReplayBuffer:
    """Transitions on the training device, the oldest overwritten when full; `rewards` holds r_hat.
    """

    def __init__(self, capacity, obs_dim, action_dim, device):
        self.capacity = capacity
        self.size = 0
        self.pos = 0
        self.device = device
        for name, dim in zip(Batch._fields, (obs_dim, action_dim, 1, obs_dim, 1)):
            setattr(self, name, torch.zeros(capacity, dim, device=device))

    def add(self, *transition):  # obs, action, reward, next obs, terminated
        for name, value in zip(Batch._fields, transition):
            getattr(self, name)[self.pos] = torch.as_tensor(value)
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size) -> Batch:
        idx = torch.randint(self.size, (batch_size,), device=self.device)
        return Batch(*(getattr(self, name)[idx] for name in Batch._fields))

    def state_dict(self) -> dict:
        """The filled rows only, copied (a slice would save the whole tensor)."""
        rows = {name: getattr(self, name)[: self.size].clone() for name in Batch._fields}
        return rows | {"pos": self.pos}

    def load_state_dict(self, state: dict):
        self.pos = state["pos"]
        self.size = len(state["obs"])
        for name in Batch._fields:
            getattr(self, name)[: self.size] = state[name]


def knn_distance(states: torch.Tensor, reference: torch.Tensor, k: int) -> torch.Tensor:
    """Eq. (8) without the log (docs): distance to the k-th nearest neighbour in `reference`, not
    counting the state itself (its zero distance): the (k+1)-th smallest. Memory: states x
    reference distances."""
    distances = torch.cdist(states, reference)
    # topk: ~5x faster than kthvalue on a 10K-state buffer
    nearest = distances.topk(min(k + 1, len(reference)), dim=1, largest=False).values
    return nearest[:, -1:].contiguous()


def intrinsic_reward(batch: Batch, buffer: ReplayBuffer, k: int) -> torch.Tensor:
    """Algorithm 2's r_int(s_t) before normalisation: kNN distance of the batch's s_t (obs, not
    next_obs; reference code: agent/sac.py) among all states in the buffer (s_t is one of them:
    knn_distance skips its zero distance)."""
    return knn_distance(batch.obs, buffer.obs[: buffer.size], k)


class RunningMeanStd:
    """Of the kNN reward: Chan et al.'s parallel update (the reference's was wrong)."""

    def __init__(self):
        self.mean = 0.0
        self.var = 1.0
        self.count = 0

    def update(self, x: torch.Tensor):
        batch_mean = x.mean().item()
        batch_var = x.var(unbiased=False).item()
        batch_count = x.numel()
        total = self.count + batch_count
        delta = batch_mean - self.mean
        m2 = self.var * self.count + batch_var * batch_count
        m2 += delta**2 * self.count * batch_count / total
        self.mean += delta * batch_count / total
        self.var = m2 / total
        self.count = total


def relabel(buffer: ReplayBuffer, reward_model: RewardEnsemble, chunk: int = 16384):
    """PEBBLE's relabelling: r_hat = ensemble mean for every stored transition (wrapped ones too).
    """
    with torch.no_grad():
        for i in range(0, buffer.size, chunk):
            obs_action = torch.cat([buffer.obs[i : i + chunk], buffer.actions[i : i + chunk]], -1)
            buffer.rewards[i : i + chunk] = reward_model(obs_action).mean(0)


def coverage_features(inputs0: torch.Tensor, inputs1: torch.Tensor, obs_dim: int) -> np.ndarray:
    """Appendix, coverage sampling: the states of both segments of each query, flattened and
    concatenated."""
    states = [inputs0[..., :obs_dim].flatten(1), inputs1[..., :obs_dim].flatten(1)]
    return torch.cat(states, 1).cpu().numpy()


def preference_loss(segment_returns, y: torch.Tensor, label_smoothing: float = 0.0) -> torch.Tensor:
    """Eq. (3): cross-entropy of P[sigma1 > sigma0] = softmax(sum r_hat) (Eq. (2)) against (1 - y,
    y), (batch, 2)."""
    target = (1 - label_smoothing) * y + label_smoothing / 2
    log_probs = F.log_softmax(segment_returns, dim=-1)
    return -((1 - target) * log_probs[:, 0] + target * log_probs[:, 1]).mean()


def preference_accuracy(segment_returns, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(correct, counted) over strict labels: an equal label has no right side (the reference code
    counted it)."""
    strict = y != 0.5
    correct = (segment_returns[:, 1] > segment_returns[:, 0]) == (y > 0.5)
    return (correct & strict).sum(), strict.sum()


def train_reward(reward_model, optimizer, preferences: dict, args) -> tuple[float, float]:
    """Algorithm 3, reward learning: up to --reward-epochs passes over D, one shuffle per member,
    until 97% accuracy."""
    inputs0 = reward_model.normalize(preferences["inputs0"])
    inputs1 = reward_model.normalize(preferences["inputs1"])
    y = preferences["y"]
    for _ in range(args.reward_epochs):
        orders = [torch.randperm(len(y), device=y.device) for _ in reward_model.members]
        # summed on the device: one sync an epoch
        correct = counted = loss_sum = torch.zeros((), device=y.device)
        for start in range(0, len(y), args.reward_batch_size):
            loss = 0.0
            for member, order in zip(reward_model.members, orders):
                idx = order[start : start + args.reward_batch_size]
                returns = torch.cat([member(inputs0[idx]).sum(1), member(inputs1[idx]).sum(1)], -1)
                loss = loss + preference_loss(returns, y[idx], args.label_smoothing)
                member_correct, member_counted = preference_accuracy(returns.detach(), y[idx])
                correct = correct + member_correct
                counted = counted + member_counted
            optimize(optimizer, loss)
            loss_sum = loss_sum + loss.detach() / len(reward_model.members)
        accuracy = correct.item() / counted.item() if counted else float("nan")
        if accuracy > 0.97:
            break
    loss = (loss_sum / math.ceil(len(y) / args.reward_batch_size)).item()
    if not math.isfinite(loss):
        raise FloatingPointError(f"non-finite reward-model loss ({loss})")
    return loss, accuracy


def sample_queries(sampler, size, episodes, reward_model, preferences, args, rng) -> tuple:
    """SAMPLE() of Algorithm 3: `size` segment pairs from the query pool, chosen by the sampler
    among size x candidate_multiplier random pairs. Returns the pairs (arrays, true rewards
    included) and both segments' (observation, action) per step as tensors on the reward model's
    device."""
    n_candidates = size if sampler == "uniform" else size * args.candidate_multiplier
    candidates = draw_segments(episodes, args.segment_len, n_candidates, rng)
    device = preferences["y"].device
    inputs0 = np.concatenate([candidates["obs0"], candidates["actions0"]], -1)
    inputs0 = torch.as_tensor(inputs0, device=device)
    inputs1 = np.concatenate([candidates["obs1"], candidates["actions1"]], -1)
    inputs1 = torch.as_tensor(inputs1, device=device)
    chosen = np.arange(size)  # uniform: `size` uniform pairs were drawn
    if sampler != "uniform":
        obs_dim = candidates["obs0"].shape[-1]
        with torch.no_grad():
            probs = torch.sigmoid(reward_model(inputs1).sum(2) - reward_model(inputs0).sum(2))
        labelled = None
        if sampler.endswith("coverage"):
            labelled = coverage_features(preferences["inputs0"], preferences["inputs1"], obs_dim)
        features = coverage_features(inputs0, inputs1, obs_dim)
        probs = probs[..., 0].cpu().numpy()
        chosen = select(sampler, size, probs=probs, rng=rng, labeled_features=labelled,
                        features=features)
    segments = {key: value[chosen] for key, value in candidates.items()}
    return segments, inputs0[chosen], inputs1[chosen]


def feedback_session(args, progress, size, episodes, preferences, reward_model, reward_optimizer,
                     teacher, rng, writer, episode_len) -> int:
    """Algorithm 3's feedback session: SAMPLE() queries, SimTeacher's labels (saved to labels/ at
    once), D grows by the kept ones (in place), r_hat learns on D. Returns the number of labels
    in D."""
    # the first session: uniform (reference code)
    sampler = args.sampler if progress.pretrained else "uniform"
    segments, inputs0, inputs1 = sample_queries(sampler, size, episodes, reward_model, preferences,
                                                args, rng)
    # Appendix, adaptive thresholds from the mean true return of recent episodes (reference code)
    mean_return = float(np.mean(progress.recent_returns))
    teacher.set_thresholds(mean_return, args.segment_len, episode_len)
    if args.teacher == "human":
        y, keep = ask_person(args, progress, segments, episodes)
    else:
        y, keep = teacher.label(segments["rewards0"], segments["rewards1"])
    # the thresholds' unit (fit_teacher.py reads it)
    threshold_scale = mean_return * args.segment_len / episode_len
    data = io.BytesIO()
    np.savez(data, step=progress.global_step, y=y, keep=keep, threshold_scale=threshold_scale,
             **segments)
    file_name = f"session_{progress.sessions_done:04d}.npz"
    save_file(os.path.join(args.output_dir, "labels", file_name), data.getvalue())
    progress.feedback_used += size
    progress.sessions_done += 1
    progress.next_feedback_step = progress.global_step + args.feedback_every
    kept = torch.as_tensor(keep, device=inputs0.device)
    y_kept = torch.as_tensor(y[keep], dtype=torch.float32, device=inputs0.device)
    new = {"inputs0": inputs0[kept], "inputs1": inputs1[kept], "y": y_kept}
    for key in preferences:
        preferences[key] = torch.cat([preferences[key], new[key]])
    skipped = int((~keep).sum())
    equal = int((y[keep] == 0.5).sum())
    n_labels = len(preferences["y"])
    for name, value in [("labels", progress.feedback_used), ("skipped", skipped), ("equal", equal)]:
        writer.add_scalar(f"feedback/{name}", value, progress.global_step)
    if n_labels == 0:  # every query so far was skipped: nothing to learn from yet
        print(f"step {progress.global_step}: all {size} queries skipped, the reward model stays as "
              "it is")
        return 0
    if args.reward_input_norm:  # statistics of D's states, fixed until the next session
        states = torch.cat([preferences["inputs0"], preferences["inputs1"]], 1)
        obs_dim = segments["obs0"].shape[-1]
        reward_model.set_input_stats(states[..., :obs_dim].flatten(0, 1))
    loss, accuracy = train_reward(reward_model, reward_optimizer, preferences, args)
    writer.add_scalar("reward/loss", loss, progress.global_step)
    writer.add_scalar("reward/accuracy", accuracy, progress.global_step)
    print(f"step {progress.global_step}: feedback session {progress.sessions_done}: {size} queries "
          f"({skipped} skipped, {equal} equal), reward model trained on {n_labels} labels, "
          f"accuracy {accuracy:.3f}")
    return n_labels


def reset_critic(critic, critic_target, critic_optimizer):
    """PEBBLE after the first reward update: fresh critics and Adam moments (not the actor or
    temperature)."""
    critic.load_state_dict(TwinCritic(*critic.sizes).state_dict())
    critic_target.load_state_dict(critic.state_dict())
    critic_optimizer.state.clear()


def log_losses(writer, losses: dict, step: int):
    """The losses to TensorBoard; a NaN or infinity stops the run (FloatingPointError). Checked
    where the values reach the host anyway and before each checkpoint, not at each optimizer step
    (a device sync each): a checkpoint never holds a diverged network."""
    for name, value in losses.items():
        value = float(value)
        if not math.isfinite(value):
            raise FloatingPointError(f"non-finite {name} ({value})")
        writer.add_scalar(f"losses/{name}", value, step)


# Plumbing: command line, files, evaluation, checkpoints, the loop's state
def fail(message: str, code: int = 2):
    print(f"error: {message}", file=sys.stderr)
    sys.exit(code)


def parse_args() -> Args:
    """tyro's command line (--help lists every flag and choice); its error box becomes one line."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            args = tyro.cli(Args)
    except SystemExit as exit_:
        if exit_.code:  # not --help: the box's text up to its first rule
            lines = captured.getvalue().splitlines()[1:]
            text = "\n".join(line.strip("│╭╰╮╯ ") for line in lines)
            fail(" ".join(text.split("\n─")[0].split()))
        raise
    sys.stderr.write(captured.getvalue())  # tyro's warnings, if any
    return args


RESUME_MAY_CHANGE = ("resume", "checkpoint_every", "cuda", "track", "wandb_project_name",
                     "capture_video")
# SimTeacher's fields: the --teacher-* flags
TEACHER_FIELDS = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal")


def resolve(args: Args) -> Args:
    """Every field left None from the task's preset and the teacher's (a flag the user gave wins).
    With --resume DIR: the configuration saved in DIR; a flag that would change the experiment is
    refused."""
    if args.resume:
        if not os.path.isfile(os.path.join(args.resume, "checkpoint.pt")):
            raise ValueError(f"--resume {args.resume!r}: no checkpoint.pt there (a run stopped "
                             "before its first checkpoint has to start again)")
        with open(os.path.join(args.resume, "config.json")) as f:
            saved = json.load(f)
        names = [f.name for f in fields(Args)]
        if missing := [name for name in names if name not in saved]:
            raise ValueError(f"--resume {args.resume!r}: its config.json has no "
                             f"{', '.join(missing)} (written by an older "
                             f"{os.path.basename(__file__)})")
        for name in names:
            given = getattr(args, name)
            if name not in RESUME_MAY_CHANGE and given not in (getattr(Args(), name), saved[name]):
                raise ValueError(f"--{name.replace('_', '-')} cannot change when resuming (the run "
                                 f"has {saved[name]!r}, got {given!r})")
        kept = {name: getattr(args, name) for name in RESUME_MAY_CHANGE}
        return Args(**saved | kept | {"output_dir": args.resume})
    families = {"dmc": DMC_PRESET, "metaworld": METAWORLD_PRESET, "gym": GYM_PRESET}
    family = families[env_kind(args.env_id)]
    teacher = make_teacher("oracle" if args.teacher == "human" else args.teacher)
    preset = PRESETS.get(args.env_id.removesuffix("-v3"), family)
    preset |= {f"teacher_{name}": getattr(teacher, name) for name in TEACHER_FIELDS}
    for key, value in preset.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    args.buffer_size = args.buffer_size or args.total_timesteps
    return args


def check_args(args: Args, episode_len: int):
    """ValueError naming the first number out of its range (tyro checks types and choices)."""
    a = args
    pretrain = a.seed_steps + a.unsup_steps
    rules = [
        ("seed", a.seed >= 0, ">= 0"),
        ("teacher_beta", a.teacher_beta >= 0, ">= 0 (inf = rational)"),
        *[(n, 0 < getattr(a, n) <= 1, "in (0, 1]") for n in ("teacher_gamma", "gamma", "tau")],
        *[(n, 0 <= getattr(a, n) <= 1, "in [0, 1]")
          for n in ("teacher_eps_mistake", "teacher_eps_skip", "teacher_eps_equal")],
        *[(n, getattr(a, n) >= 1, ">= 1")
          for n in ("max_feedback", "feedback_every", "hidden_dim", "num_layers", "batch_size",
                    "reward_batch_size", "reward_ensemble_size", "eval_every", "eval_episodes",
                    "knn_k", "candidate_multiplier", "reward_epochs", "target_update_every")],
        *[(n, getattr(a, n) >= 0, ">= 0")
          for n in ("seed_steps", "unsup_steps", "critic_reset_updates", "query_recent_episodes",
                    "checkpoint_every")],
        *[(n, getattr(a, n) > 0, "> 0")
          for n in ("learning_rate", "alpha_lr", "reward_lr", "init_temperature")],
        ("label_smoothing", 0 <= a.label_smoothing < 1, "in [0, 1)"),
        ("feedback_per_session", 1 <= a.feedback_per_session <= a.max_feedback,
         f"in [1, --max-feedback={a.max_feedback}]"),
        ("segment_len", 1 <= a.segment_len <= episode_len,
         f"in [1, {episode_len}] (the episode length)"),
        ("total_timesteps", a.total_timesteps > pretrain,
         f"> --seed-steps + --unsup-steps ({pretrain})"),
        ("buffer_size", a.buffer_size >= max(a.batch_size, episode_len),
         ">= max(batch size, episode length)"),
    ]
    for name, ok, rule in rules:
        if not ok:
            raise ValueError(f"--{name.replace('_', '-')} must be {rule}, got {getattr(a, name)}")


def load_labels(path: str, obs_dim: int, action_dim: int, segment_len: int) -> dict:
    """--labels-from: the kept labels of saved sessions (a run directory, its labels/ or one .npz)
    as the labelled dataset's inputs0, inputs1 (observation and action per step) and y."""
    files = [path]
    if not os.path.isfile(path):
        files = sorted(glob.glob(os.path.join(path, "labels", "session_*.npz"))
                       or glob.glob(os.path.join(path, "session_*.npz")))
    sessions = [dict(np.load(file)) for file in files]
    shape = (segment_len, obs_dim, action_dim)
    if not sessions or any(s["obs0"].shape[1:] + s["actions0"].shape[2:] != shape
                           for s in sessions):
        raise ValueError(f"--labels-from {path!r}: no session_*.npz files, or segments that do not "
                         f"fit this run ({segment_len} steps of {obs_dim} observations and "
                         f"{action_dim} actions)")
    kept = {key: np.concatenate([s[key][s["keep"]] for s in sessions])
            for key in ("obs0", "actions0", "obs1", "actions1", "y")}
    return {"inputs0": np.concatenate([kept["obs0"], kept["actions0"]], -1),
            "inputs1": np.concatenate([kept["obs1"], kept["actions1"]], -1),
            "y": kept["y"].astype(np.float32)}


def check_video(eval_env: gym.Env):
    """--capture-video: one frame rendered now rather than a failure at the first evaluation."""
    try:
        import moviepy  # noqa: F401

        # GLFW warns before it fails without a display
        with warnings.catch_warnings(action="ignore"):
            eval_env.reset(seed=0)
            eval_env.render()
    except Exception as error:
        reason = f"{type(error).__name__}: {(str(error) or '-').splitlines()[0]}"
        print(f"error: --capture-video cannot render ({reason}); it needs moviepy and, without a "
              "display, MUJOCO_GL=egl (GPU) or MUJOCO_GL=osmesa (CPU)", file=sys.stderr, flush=True)
        os._exit(2)  # not sys.exit: the half-made GL context's finalizer would print a traceback


def prepare(args: Args) -> tuple:
    """Every user error before any work, as one `error: ...` line: the configuration, the
    environments, --labels-from, --capture-video, the output directory (config.json written
    there)."""
    try:
        args = resolve(args)
        env, episode_len = make_env(args.env_id)
        eval_env, _ = make_env(args.env_id, render_mode="rgb_array" if args.capture_video else None)
        check_args(args, episode_len)
        imported_labels = None
        if args.labels_from and not args.resume:
            dims = (env.observation_space.shape[0], env.action_space.shape[0])
            imported_labels = load_labels(args.labels_from, *dims, args.segment_len)
    except (ValueError, OSError, KeyError) as error:
        fail(str(error))
    if args.capture_video:
        check_video(eval_env)
    if args.output_dir is None:
        run_name = f"{args.env_id}__{args.exp_name}__{args.teacher}__{args.seed}"
        args.output_dir = os.path.join("runs", f"{run_name}__{int(time.time())}")
    if not args.resume and os.path.isdir(args.output_dir) and os.listdir(args.output_dir):
        fail(f"--output-dir {args.output_dir!r} already holds a run; continue it with --resume "
             f"{args.output_dir} or choose another directory")
    try:
        os.makedirs(os.path.join(args.output_dir, "labels"), exist_ok=True)
        if not args.resume:
            config = json.dumps(asdict(args), indent=2).encode()
            save_file(os.path.join(args.output_dir, "config.json"), config)
    except OSError as error:
        fail(f"cannot write to --output-dir {args.output_dir!r}: {error.strerror}")
    return args, env, eval_env, episode_len, imported_labels


def start_logging(args: Args, device: torch.device):
    """The configuration and the device printed; TensorBoard (and W&B with --track) opened."""
    config = asdict(args)
    print("configuration:\n" + "\n".join(f"  {key}: {value}" for key, value in config.items()))
    if device.type == "cuda":
        print(f"device: {torch.cuda.get_device_name(device)}", flush=True)
    else:
        print(f"device: cpu ({'torch sees no GPU' if args.cuda else '--no-cuda'})", flush=True)
    from torch.utils.tensorboard import SummaryWriter

    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, sync_tensorboard=True, config=config,
                   name=os.path.basename(args.output_dir), save_code=True)
    writer = SummaryWriter(args.output_dir)
    table = "\n".join(f"|{key}|{value}|" for key, value in config.items())
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + table)
    return writer


def save_file(path: str, data: bytes):
    """Written to a temporary file, flushed to disk, then renamed: a kill during the write leaves
    the old file."""
    try:
        with open(f"{path}.tmp", "wb") as f:
            f.write(data)
            os.fsync(f.fileno())
        os.replace(f"{path}.tmp", path)
    finally:
        if os.path.exists(f"{path}.tmp"):
            os.remove(f"{path}.tmp")


def tree_map(fn, tree):
    """fn applied to every leaf of nested lists, tuples and dicts."""
    if isinstance(tree, dict):
        return {key: tree_map(fn, value) for key, value in tree.items()}
    if isinstance(tree, (list, tuple)):
        return type(tree)(tree_map(fn, value) for value in tree)
    return fn(tree)


def plain(leaf):
    """A leaf as plain data (numpy arrays as tensors, numpy scalars as numbers): torch.load(...,
    weights_only=True) reads a checkpoint of plain data and tensors without running code from it."""
    if isinstance(leaf, np.ndarray):
        return torch.tensor(leaf)
    return leaf.item() if isinstance(leaf, np.generic) else leaf


def unplain(leaf):
    """plain()'s inverse for the parts the loop keeps in numpy."""
    return leaf.numpy() if isinstance(leaf, torch.Tensor) else leaf


def snapshot(parts: dict) -> dict:
    """Each part's state as tensors and plain data (torch's and numpy's generators' states
    included)."""
    state = {"torch_rng": torch.get_rng_state()}
    if torch.cuda.is_initialized():
        state["cuda_rng"] = torch.cuda.get_rng_state_all()
    for name, part in parts.items():
        if hasattr(part, "state_dict"):  # networks, optimizers, the replay buffer, the teacher
            state[name] = part.state_dict()
        elif isinstance(part, np.random.Generator):
            state[name] = part.bit_generator.state
        elif isinstance(part, torch.Tensor):
            state[name] = part.detach().clone()
        elif isinstance(part, deque):
            state[name] = tree_map(plain, list(part))
        else:  # a dict of tensors, or an object's attributes (Progress, running statistics)
            state[name] = tree_map(plain, part if isinstance(part, dict) else vars(part))
    return state


def restore(parts: dict, state: dict, device: torch.device):
    """snapshot()'s inverse, part by part, in place."""
    torch.set_rng_state(state["torch_rng"])
    if "cuda_rng" in state and device.type == "cuda":
        torch.cuda.set_rng_state_all(state["cuda_rng"])
    for name, part in parts.items():
        if hasattr(part, "load_state_dict"):
            part.load_state_dict(state[name])
        elif isinstance(part, np.random.Generator):
            part.bit_generator.state = state[name]
        elif isinstance(part, torch.Tensor):
            with torch.no_grad():
                part.copy_(state[name])
        elif isinstance(part, deque):
            part.extend(tree_map(unplain, state[name]))
        elif isinstance(part, dict):
            part.update({key: value.to(device) for key, value in state[name].items()})
        else:
            vars(part).update(tree_map(unplain, state[name]))


def save_checkpoint(path: str, state: dict, step: int):
    """torch.save in memory first (a full disk is then a plain OSError), then save_file."""
    start = time.perf_counter()
    data = io.BytesIO()
    torch.save(state, data)
    save_file(path, data.getvalue())
    seconds = time.perf_counter() - start
    print(f"step {step}: {os.path.basename(path)} saved ({len(data.getvalue()) / 2**20:.1f} MiB in "
          f"{seconds:.1f} s)", flush=True)


def set_labels_aside(output_dir: str, progress):
    """--resume: label files of sessions after the checkpoint go to labels/before_resume_at_step_N
    (the run asks those queries again)."""
    kept_dir = os.path.join(output_dir, "labels", f"before_resume_at_step_{progress.global_step}")
    paths = sorted(glob.glob(os.path.join(output_dir, "labels", "session_*.npz")))
    for path in paths[progress.sessions_done :]:
        os.makedirs(kept_dir, exist_ok=True)
        os.replace(path, os.path.join(kept_dir, os.path.basename(path)))


def ask_person(args, progress, segments, episodes) -> tuple[np.ndarray, np.ndarray]:
    """--teacher human: the session's queries go to queries/session_N.npz, where label_server.py
    finds them (it replays each segment's episode from its reset seed and actions to show it as a
    clip); the answers come back from queries/session_N_answers.json, which its page writes one by
    one. Returns (y, keep) as a SimTeacher does, once every query has an answer."""
    path = os.path.join(args.output_dir, "queries", f"session_{progress.sessions_done:04d}")
    n = len(segments["start0"])
    queries = {"step": progress.global_step}
    for side in (0, 1):
        pool = [episodes[e] for e in segments[f"episode{side}"]]
        ends = segments[f"start{side}"] + args.segment_len
        actions = np.zeros((n, ends.max(), pool[0][1].shape[1]), np.float32)
        for i, (episode, end) in enumerate(zip(pool, ends)):
            actions[i, :end] = episode[1][:end]
        queries[f"seed{side}"] = np.array([episode[3] for episode in pool])
        queries[f"start{side}"] = segments[f"start{side}"]
        queries[f"actions{side}"] = actions
    os.makedirs(os.path.dirname(path), exist_ok=True)
    data = io.BytesIO()
    np.savez(data, **queries)
    save_file(f"{path}.npz", data.getvalue())
    print(f"step {progress.global_step}: {n} queries wait for a person: python label_server.py "
          f"{args.output_dir} and open http://127.0.0.1:8000 (stopping the run now loses nothing: "
          "--resume asks this session again, with the answers given)", flush=True)
    # While it waits, SIGTERM or SIGINT end the run at once (the checkpoint is already written)
    handlers = {signum: signal.signal(signum, signal.SIG_DFL)
                for signum in (signal.SIGTERM, signal.SIGINT)}
    answers = {}
    while len(answers) < n:
        time.sleep(1)
        with contextlib.suppress(OSError, ValueError, KeyError):
            with open(f"{path}_answers.json") as f:
                answers = json.load(f)["answers"]
    for signum, handler in handlers.items():
        signal.signal(signum, handler)
    values = {"left": 0.0, "right": 1.0, "equal": 0.5, "skip": math.nan}
    y = np.array([values[answers[str(i)]] for i in range(n)])
    return y, ~np.isnan(y)


def labelled_dataset(imported_labels, args, obs_dim: int, action_dim: int, device) -> dict:
    """The labelled dataset D: both segments' (observation, action) per step, and the label;
    --labels-from's labels first (they do not count against --max-feedback)."""
    empty = np.zeros((0, args.segment_len, obs_dim + action_dim), np.float32)
    preferences = {"inputs0": empty, "inputs1": empty, "y": np.zeros(0, np.float32)}
    if imported_labels:
        preferences = imported_labels
        print(f"--labels-from: {len(preferences['y'])} labels from {args.labels_from}")
    return {key: torch.as_tensor(value, device=device) for key, value in preferences.items()}


EVAL_COLUMNS = ("step", "episode_return", "episode_return_std", "success_rate", "feedback",
                "reward_correlation", "wall_time", "overhead_seconds")


def eval_csv(rows: list[dict]) -> bytes:
    """eval.csv, written whole after each evaluation (a resumed run writes its checkpoint's rows
    again)."""
    lines = [EVAL_COLUMNS] + [[row[column] for column in EVAL_COLUMNS] for row in rows]
    return "".join(",".join(map(str, line)) + "\n" for line in lines).encode()


def evaluate(policy, reward_model, env, seeds: list[int], device) -> dict:
    """Episodes of policy(observation) -> action (one per reset seed) with the true reward (B-Pref's
    metric), Meta-World success (at any step), and the Pearson correlation of learned and true
    per-step rewards."""
    returns = []
    successes = []
    true_rewards = []
    learned = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done = success = False
        returns.append(0.0)
        while not done:
            with torch.no_grad():
                action = policy(obs)
                if reward_model is not None:
                    obs_action = torch.cat([torch.as_tensor(obs, device=device), action])
                    learned.append(reward_model(obs_action).mean().item())
            obs, reward, terminated, truncated, info = env.step(action.cpu().numpy())
            done = terminated or truncated
            returns[-1] += reward
            success = success or info.get("success")
            true_rewards.append(reward)
        successes.append(bool(success))
    correlation = math.nan
    if learned and np.std(learned) > 0 and np.std(true_rewards) > 0:
        correlation = float(np.corrcoef(learned, true_rewards)[0, 1])
    return {"episode_return": float(np.mean(returns)), "episode_return_std": float(np.std(returns)),
            "success_rate": float(np.mean(successes)), "reward_correlation": correlation}


def evaluation(args, progress, policy, reward_model, eval_env, writer, start_time: float, device):
    """The next eval_episodes evaluation episodes: a row of eval.csv (rewritten whole), TensorBoard.
    """
    if args.capture_video:
        eval_env.name_prefix = f"step_{progress.global_step}"
    first = len(progress.eval_rows) * args.eval_episodes
    seeds = [episode_seed(args.seed, EVAL_STREAM, first + j) for j in range(args.eval_episodes)]
    learned_reward = reward_model if progress.pretrained and not args.ground_truth_reward else None
    result = evaluate(policy, learned_reward, eval_env, seeds, device)
    if args.capture_video and eval_env.recording:  # write the video now, not at the next reset
        eval_env.stop_recording()
    progress.eval_rows.append({"step": progress.global_step, **result,
                               "feedback": progress.feedback_used,
                               "wall_time": round(time.time() - start_time, 1),
                               "overhead_seconds": round(progress.overhead_seconds, 1)})
    save_file(os.path.join(args.output_dir, "eval.csv"), eval_csv(progress.eval_rows))
    for name in ("episode_return", "success_rate", "reward_correlation"):
        writer.add_scalar(f"eval/{name}", result[name], progress.global_step)


def print_progress(args, progress, start_time: float, writer):
    """A line of progress, steps per second to TensorBoard."""
    sps = progress.global_step / (time.time() - start_time)
    writer.add_scalar("charts/SPS", sps, progress.global_step)
    minutes_left = (args.total_timesteps - progress.global_step) / sps / 60
    last_return = progress.eval_rows[-1]["episode_return"] if progress.eval_rows else math.nan
    print(f"step {progress.global_step}/{args.total_timesteps} | {sps:.0f} SPS | ETA "
          f"{minutes_left:.1f} min | last eval return {last_return:.1f} | labels "
          f"{progress.feedback_used}/{args.max_feedback}", flush=True)


@dataclass
class Progress:
    """What the main loop carries besides networks, optimizers and buffers; a checkpoint saves every
    field."""

    global_step: int = 0
    episodes: int = 0  # training episodes before the running one (its number for episode_seed)
    # the running episode's observations, actions and true rewards so far
    running_episode: tuple = field(default_factory=lambda: ([], [], []))
    # true returns of the last 10 training episodes
    recent_returns: list = field(default_factory=list)
    sessions_done: int = 0
    feedback_used: int = 0
    next_feedback_step: int = 0
    eval_rows: list = field(default_factory=list)  # eval.csv
    pretrained: bool = False  # pre-training is over: SAC learns from r_hat (or the true reward)
    # PEBBLE's own parts: kNN reward, queries, reward learning, relabelling
    overhead_seconds: float = 0.0
    wall_time: float = 0.0
    counts: dict = field(default_factory=lambda: dict.fromkeys(  # how often each phase ran
        ("updates_on_knn_reward", "updates_on_learned_reward", "relabels", "critic_resets"), 0))

    @contextlib.contextmanager
    def overhead(self):
        start = time.perf_counter()
        yield
        self.overhead_seconds += time.perf_counter() - start


if __name__ == "__main__":
    args, env, eval_env, episode_len, imported_labels = prepare(parse_args())
    obs_dim = env.observation_space.shape[0]
    action_dim = env.action_space.shape[0]
    device = torch.device("cuda" if args.cuda and torch.cuda.is_available() else "cpu")
    writer = start_logging(args, device)
    if device.type == "cpu" and args.hidden_dim * args.batch_size > 256 * 256:
        print("note: networks of this size train for days on a CPU; use a GPU, or the CPU scale of "
              f"docs/results.md: {CPU_SCALE}", flush=True)

    # Seeding: numpy (query sampler, teacher, seed steps' actions: independent streams), torch
    # (networks, batches), every reset (episode_seed): an env is a function of its seed and actions
    sampler_seed, teacher_seed, action_seed = numpy_seeds(args.seed)
    rng = np.random.default_rng(sampler_seed)
    action_rng = np.random.default_rng(action_seed)
    torch.manual_seed(args.seed)
    torch.set_flush_denormal(True)  # MuJoCo's tiny float32 velocities: denormals, slow on a CPU
    actor = Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic = TwinCritic(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic_target = TwinCritic(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic_target.load_state_dict(critic.state_dict())
    actor_optimizer = adam(actor.parameters(), args.learning_rate)
    critic_optimizer = adam(critic.parameters(), args.learning_rate)
    log_alpha = torch.tensor(math.log(args.init_temperature), device=device, requires_grad=True)
    alpha_optimizer = adam([log_alpha], args.alpha_lr)
    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = adam(reward_model.parameters(), args.reward_lr)
    buffer = ReplayBuffer(args.buffer_size, obs_dim, action_dim, device)
    intrinsic_stats = RunningMeanStd()
    teacher_fields = {name: getattr(args, f"teacher_{name}") for name in TEACHER_FIELDS}
    teacher_name = "oracle" if args.teacher == "human" else args.teacher  # human: not used
    teacher = make_teacher(teacher_name, seed=teacher_seed, **teacher_fields)
    # Feedback sessions from the end of pre-training, every feedback_every steps
    first_session = args.seed_steps + args.unsup_steps + 1
    steps = session_steps(first_session, args.feedback_every, args.total_timesteps)
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session,
                                   steps - 1, args.total_timesteps)  # steps - 1: the steps done
    planned = planned_labels(session_sizes, first_session, args.feedback_every,
                             args.total_timesteps)
    if planned < args.max_feedback and not args.ground_truth_reward:
        print(f"note: only {planned} of the {args.max_feedback} labels of --max-feedback fit in "
              f"{args.total_timesteps} steps (sessions from step {first_session}, every "
              f"{args.feedback_every} steps)")
    preferences = labelled_dataset(imported_labels, args, obs_dim, action_dim, device)
    # The query pool: the last query_recent_episodes complete episodes (reference code: 100)
    episodes = deque(maxlen=args.query_recent_episodes or None)
    progress = Progress(next_feedback_step=first_session)
    parts = {"progress": progress, "actor": actor, "critic": critic,
             "critic_target": critic_target, "reward_model": reward_model,
             "actor_optimizer": actor_optimizer, "critic_optimizer": critic_optimizer,
             "alpha_optimizer": alpha_optimizer, "reward_optimizer": reward_optimizer,
             "buffer": buffer, "teacher": teacher, "log_alpha": log_alpha,
             "intrinsic_stats": intrinsic_stats, "preferences": preferences, "rng": rng,
             "action_rng": action_rng, "episodes": episodes}
    checkpoint_path = os.path.join(args.output_dir, "checkpoint.pt")
    if args.resume:  # every part back (weights_only: a shared run directory runs no code)
        restore(parts, torch.load(checkpoint_path, "cpu", weights_only=True), device)
        print(f"resuming from the checkpoint at step {progress.global_step}")
        if progress.global_step >= args.total_timesteps:
            fail(f"the run in {args.output_dir!r} has already finished "
                 f"({progress.global_step} steps)")
        set_labels_aside(args.output_dir, progress)
    # The training env at the start of its running episode (that episode's seed), then that
    # episode's actions so far again: MuJoCo is deterministic, so a resumed env is where it was
    obs, _ = env.reset(seed=episode_seed(args.seed, TRAIN_STREAM, progress.episodes))
    for action in progress.running_episode[1]:
        obs = env.step(action)[0]
    if args.capture_video:  # the first episode of each evaluation: videos/step_N-episode-M.mp4
        eval_env = gym.wrappers.RecordVideo(
            eval_env, os.path.join(args.output_dir, "videos"),
            episode_trigger=lambda episode: episode % args.eval_episodes == 0)
    stop = []  # SIGTERM (a time limit) or SIGINT (Ctrl-C): checkpoint after this step, then exit
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    signal.signal(signal.SIGINT, lambda signum, frame: stop.append(signum))
    start_time = time.time() - progress.wall_time
    last_print = start_time

    # Main loop: Algorithm 3 (PEBBLE) with Algorithm 2 (unsupervised pre-training) first
    try:
        save_file(os.path.join(args.output_dir, "eval.csv"), eval_csv(progress.eval_rows))
        for global_step in range(progress.global_step + 1, args.total_timesteps + 1):
            progress.global_step = global_step
            # The critic reset comes with the first reward update (--ground-truth-reward: at the
            # step it would come, as PEBBLE on the true reward)
            new_reward = args.ground_truth_reward and global_step == first_session
            if (not args.ground_truth_reward and global_step >= progress.next_feedback_step
                    and progress.sessions_done < len(session_sizes)
                    and any(len(episode[0]) >= args.segment_len for episode in episodes)):
                if args.teacher == "human":  # a checkpoint first: --resume asks this session again
                    progress.wall_time = time.time() - start_time
                    state = snapshot(parts)
                    state["progress"]["global_step"] = global_step - 1  # the state after that step
                    save_checkpoint(checkpoint_path, state, global_step - 1)
                with progress.overhead():
                    size = int(session_sizes[progress.sessions_done])
                    n_labels = feedback_session(args, progress, size, episodes, preferences,
                                                reward_model, reward_optimizer, teacher, rng,
                                                writer, episode_len)
                    if n_labels:  # PEBBLE's relabelling: every stored transition gets r_hat
                        relabel(buffer, reward_model)
                        progress.counts["relabels"] += 1
                new_reward = n_labels > 0 and not progress.pretrained
            if new_reward:  # then critic_reset_updates SAC updates on the relabelled buffer
                progress.pretrained = True
                progress.counts["critic_resets"] += 1
                reset_critic(critic, critic_target, critic_optimizer)
                for update in range(1, args.critic_reset_updates + 1):
                    batch = buffer.sample(args.batch_size)
                    sac_update(batch, batch.rewards, actor, critic, critic_target, log_alpha,
                               actor_optimizer, critic_optimizer, alpha_optimizer, args.gamma)
                    if update % args.target_update_every == 0:
                        soft_update(critic, critic_target, args.tau)

            if global_step <= args.seed_steps:  # Algorithm 2: random actions, from their generator
                action = action_rng.uniform(-1, 1, action_dim).astype(np.float32)
            else:
                with torch.no_grad():
                    action = actor.sample(torch.as_tensor(obs, device=device)[None])[0]
                action = action[0].cpu().numpy()
            next_obs, true_reward, terminated, truncated, _ = env.step(action)
            if not (math.isfinite(true_reward) and np.isfinite(next_obs).all()):
                raise FloatingPointError(f"non-finite reward ({true_reward}) or observation from "
                                         "the environment")
            reward = float(true_reward) if args.ground_truth_reward else 0.0
            if progress.pretrained and not args.ground_truth_reward:  # Algorithm 3: r_hat(s, a)
                with progress.overhead(), torch.no_grad():  # a tensor on the device: no host sync
                    obs_action = torch.as_tensor(np.concatenate([obs, action]), device=device)
                    reward = reward_model(obs_action).mean()
            buffer.add(obs, action, reward, next_obs, terminated)
            for part, value in zip(progress.running_episode, (obs, action, true_reward)):
                part.append(value)
            obs = next_obs
            if terminated or truncated:  # to the query pool; the next episode from its own seed
                # the episode's arrays and its reset seed (--teacher human replays it)
                seed = episode_seed(args.seed, TRAIN_STREAM, progress.episodes)
                episodes.append((*(np.array(part, np.float32) for part in progress.running_episode),
                                 seed))
                episode_return = float(sum(progress.running_episode[2]))
                progress.recent_returns = (progress.recent_returns + [episode_return])[-10:]
                writer.add_scalar("charts/episodic_return", episode_return, global_step)
                progress.running_episode = ([], [], [])
                progress.episodes += 1
                obs, _ = env.reset(seed=episode_seed(args.seed, TRAIN_STREAM, progress.episodes))

            evaluating = global_step % args.eval_every == 0 or global_step == args.total_timesteps
            checkpointing = args.checkpoint_every and global_step % args.checkpoint_every == 0
            # Policy learning: SAC on the kNN state entropy during pre-training (and while every
            # query was skipped), then on the learned reward (or the true reward)
            if global_step > args.seed_steps:
                batch = buffer.sample(args.batch_size)
                rewards = batch.rewards
                if not progress.pretrained:  # Algorithm 2: r_int(s_t) over its running std
                    with progress.overhead():
                        rewards = intrinsic_reward(batch, buffer, args.knn_k)
                        intrinsic_stats.update(rewards)
                        rewards = rewards / max(math.sqrt(intrinsic_stats.var), 1e-8)
                losses = sac_update(batch, rewards, actor, critic, critic_target, log_alpha,
                                    actor_optimizer, critic_optimizer, alpha_optimizer, args.gamma)
                reward_kind = "learned" if progress.pretrained else "knn"
                progress.counts[f"updates_on_{reward_kind}_reward"] += 1
                if (global_step - args.seed_steps) % args.target_update_every == 0:
                    soft_update(critic, critic_target, args.tau)
                if global_step % 1000 == 0 or evaluating or checkpointing or stop:
                    log_losses(writer, losses, global_step)

            if evaluating:
                evaluation(args, progress, mean_policy(actor, device), reward_model, eval_env,
                           writer, start_time, device)
            if time.time() - last_print > 10 or global_step == args.total_timesteps:
                last_print = time.time()
                print_progress(args, progress, start_time, writer)
            if checkpointing or stop:
                progress.wall_time = time.time() - start_time
                save_checkpoint(checkpoint_path, snapshot(parts), global_step)
            if stop:
                print(f"{signal.Signals(stop[0]).name}: checkpoint saved at step {global_step}; "
                      f"continue with --resume {args.output_dir}", flush=True)
                writer.close()
                sys.exit(128 + stop[0])
    except FloatingPointError as error:  # a NaN or infinity in a loss or from the environment
        # The last checkpoint stays as it is; the state at the failure goes to a file of its own
        nonfinite_path = os.path.join(args.output_dir, "checkpoint_nonfinite.pt")
        save_checkpoint(nonfinite_path, snapshot(parts), progress.global_step)
        last = "no checkpoint was due yet"
        if os.path.exists(checkpoint_path):
            last = f"its last checkpoint is intact in {checkpoint_path}"
        fail(f"{error} at step {progress.global_step}; run stopped, {last}, the state at the "
             f"failure is in {nonfinite_path} and the labels in {args.output_dir}/labels", code=3)
    except OSError as error:
        fail(f"writing to {args.output_dir!r} failed at step {progress.global_step} "
             f"({error.strerror or error}); the last checkpoint there is intact", code=1)

    print(f"done: {progress.counts} (updates_on_learned_reward: the true reward with "
          f"--ground-truth-reward), {progress.sessions_done} feedback sessions, "
          f"{progress.feedback_used} queries; outputs in {args.output_dir}")
    final_model = {"actor": actor.state_dict(), "critic": critic.state_dict(),
                   "reward_model": reward_model.state_dict()}
    torch.save(final_model, os.path.join(args.output_dir, "final_model.pt"))
    eval_env.close()
    writer.close()
