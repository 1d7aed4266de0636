# PrefPPO (Christiano et al. 2017 with PPO) as benchmarked by B-Pref (Lee et al. 2021); docs and choices: README.md
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
from collections import deque
from dataclasses import asdict, dataclass, fields

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
    exp_name: str = "prefppo"
    """the name of this experiment (part of the run name)"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
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
    """environment steps between checkpoints (taken after a rollout) (0 = only on SIGTERM/SIGINT and non-finite values)"""
    resume: str | None = None
    """continue the run in this directory from its checkpoint, with its saved configuration"""
    labels_from: str | None = None
    """seed the preference dataset with an earlier run's labels (its directory, labels/ or one .npz)"""

    # Algorithm specific arguments; None = the task's preset (PRESETS below)
    env_id: str = "walker-walk"
    """DMC `domain-task`, Meta-World v3 task name (with or without -v3), or a Gymnasium id"""
    total_timesteps: int | None = None
    """total environment steps (all environments together)"""
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
    unsup_steps: int = 32000
    """unsupervised pre-training steps (kNN state entropy) at the start"""
    hidden_dim: int = 256
    """hidden units of the actor and critic"""
    num_layers: int = 3
    """hidden layers of the actor and critic"""
    learning_rate: float | None = None
    """learning rate of actor and critic"""
    num_envs: int | None = None
    """parallel environments"""
    num_steps: int | None = None
    """rollout length per environment"""
    update_epochs: int = 20
    """PPO epochs over each rollout after pre-training (reference code: n_epochs 20)"""
    unsup_update_epochs: int = 50
    """PPO epochs over each rollout of unsupervised pre-training (reference code: unsuper_n_epochs 50)"""
    minibatch_size: int | None = None
    """PPO minibatch size"""
    gamma: float = 0.99
    """discount"""
    gae_lambda: float | None = None
    """GAE lambda"""
    use_sde: bool = True
    """generalized state-dependent exploration, gSDE (reference code: use_sde 1); --no-use-sde: a
    state-independent Gaussian"""
    sde_freq: int = 4
    """gSDE: steps of each env between new exploration matrices (reference code: sde_freq 4)"""
    clip_coef: float = 0.4
    """initial PPO clip range (paper: 0.4), decayed linearly to 0 over training (reference code)"""
    ent_coef: float = 0.0
    """entropy bonus (paper: 0)"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    max_grad_norm: float = 0.5
    """gradient clipping norm"""
    eval_every: int = 50000
    """environment steps between evaluations (checked after each rollout)"""
    eval_episodes: int = 10
    """episodes per evaluation"""
    ground_truth_reward: bool = False
    """if toggled, train PPO on the true reward with no teacher (the normalisation denominator)"""
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
    query_recent_episodes: int = 0
    """segments are drawn from the last N complete episodes (0 = every episode so far, pre-training included:
    reference code)"""


# Paper appendix, table of PrefPPO hyperparameters (README lists the values the paper leaves open).
DMC_PRESET = dict(total_timesteps=4_000_000, max_feedback=1000, feedback_per_session=100, feedback_every=32_000,
                  segment_len=50, learning_rate=5e-5, num_envs=32, num_steps=500, minibatch_size=64, gae_lambda=0.92,
                  reward_epochs=100)  # reference code: re_update 100 (train_PrefPPO.py default, DMC scripts)
METAWORLD_PRESET = dict(total_timesteps=3_000_000, max_feedback=10_000, feedback_per_session=100, feedback_every=16_000,
                        segment_len=25, learning_rate=3e-4, num_envs=8, num_steps=250, minibatch_size=128,
                        gae_lambda=0.92, reward_epochs=50)  # reference code: --re-update 50 (Meta-World scripts)
GYM_PRESET = dict(DMC_PRESET, learning_rate=3e-4, num_envs=8, num_steps=256, minibatch_size=64, gae_lambda=0.95)
PRESETS = {
    "walker-walk": DMC_PRESET,
    "quadruped-walk": dict(DMC_PRESET, num_envs=16, minibatch_size=128, gae_lambda=0.9),
    "button-press": METAWORLD_PRESET,
    "sweep-into": dict(METAWORLD_PRESET, num_envs=32, minibatch_size=256),
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


def run_seeds(seed: int, num_envs: int) -> dict:
    """Independent random streams from the run's seed (numpy SeedSequence.spawn): a seed for each training
    env, one for the evaluation env and one for the video env, the query sampler's generator and the
    teacher's seed. Env seeds are 32-bit draws, so runs with different seeds share none (up to a chance
    of about num_envs^2 / 2^32); with env i seeded seed + i, runs s and s + 1 shared all but one."""
    envs, evaluation, video, sampler, teacher = np.random.SeedSequence(seed).spawn(5)
    return {"envs": [int(s) for s in envs.generate_state(num_envs)], "eval": int(evaluation.generate_state(1)[0]),
            "video": int(video.generate_state(1)[0]), "sampler": np.random.default_rng(sampler),
            "teacher": int(teacher.generate_state(1)[0])}


def hidden_layers(in_dim: int, hidden_dim: int, num_layers: int, activation=nn.Tanh) -> list[nn.Module]:
    layers, dim = [], in_dim
    for _ in range(num_layers):
        layers += [nn.Linear(dim, hidden_dim), activation()]
        dim = hidden_dim
    return layers


def mlp(in_dim: int, out_dim: int, hidden_dim: int, num_layers: int, activation=nn.Tanh) -> nn.Sequential:
    return nn.Sequential(*hidden_layers(in_dim, hidden_dim, num_layers, activation),
                         nn.Linear(hidden_dim if num_layers else in_dim, out_dim))


def orthogonal_init(module: nn.Module, gain: float) -> nn.Module:
    """Orthogonal weights with this gain and zero biases for every linear layer of `module` (reference code:
    SB3's ActorCriticPolicy init, gain sqrt(2) for hidden layers, 0.01 for the policy output, 1 for the value)."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)
    return module


def sde_std(latent: torch.Tensor, log_std: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """gSDE's action std (reference code: SB3's StateDependentNoiseDistribution): the noise latent @ W, with
    W_ij ~ N(0, exp(log_std_ij)^2), is Gaussian with variance sum_i latent_i^2 exp(log_std_ij)^2 for action j;
    eps (SB3's) keeps it positive. latent (batch, hidden), log_std (hidden, action) -> (batch, action)."""
    return torch.sqrt(latent**2 @ log_std.exp() ** 2 + eps)


def sde_noise(latent: torch.Tensor, matrices: torch.Tensor) -> torch.Tensor:
    """gSDE's exploration noise: row n of latent (N, hidden) times matrix n of matrices (N, hidden, action)."""
    return torch.bmm(latent.unsqueeze(1), matrices).squeeze(1)


class Actor(nn.Module):
    """Gaussian policy of the reference code's PPO (SB3's ActorCriticPolicy): a tanh MLP of its own (no layer
    shared with the value function) whose last hidden features, the latent, feed a linear mean; log std
    initialised to 0; actions are clipped to [-1, 1] in the env. With gSDE (reference code: use_sde; full_std,
    exp not expln, no squashing, the latent detached in the noise and the std) env n explores with
    mean + latent @ W_n, W_n a (hidden x action) matrix with entries N(0, exp(log_std)^2), so the action is
    N(mean, sde_std(latent, log_std)); without, the std is state-independent, one log std per action."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers, use_sde: bool):
        super().__init__()
        self.body = orthogonal_init(nn.Sequential(*hidden_layers(obs_dim, hidden_dim, num_layers)), math.sqrt(2))
        self.action_net = orthogonal_init(nn.Linear(hidden_dim, action_dim), 0.01)
        self.use_sde = use_sde
        self.log_std = nn.Parameter(torch.zeros((hidden_dim, action_dim) if use_sde else (action_dim,)))
        self.exploration = None  # gSDE: the matrices W_n in use, (envs, hidden, action), drawn by reset_noise

    def mean(self, obs):
        return self.action_net(self.body(obs))

    def distribution(self, obs) -> tuple[torch.distributions.Normal, torch.Tensor]:
        """pi(. | s) and the latent."""
        latent = self.body(obs)
        mean = self.action_net(latent)
        if self.use_sde:
            latent = latent.detach()
            return torch.distributions.Normal(mean, sde_std(latent, self.log_std)), latent
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean)), latent

    def reset_noise(self, num_envs: int):
        """gSDE: a new exploration matrix for each env."""
        with torch.no_grad():
            noise = torch.randn(num_envs, *self.log_std.shape, device=self.log_std.device)
            self.exploration = self.log_std.exp() * noise

    def sample(self, obs) -> tuple[torch.Tensor, torch.Tensor]:
        """An action for each row of obs (with gSDE, row n uses matrix W_n) and its log-probability."""
        distribution, latent = self.distribution(obs)
        action = distribution.loc + sde_noise(latent, self.exploration) if self.use_sde else distribution.sample()
        return action, distribution.log_prob(action).sum(-1)


def explore(actor: Actor, obs: torch.Tensor, step: int, sde_freq: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The actions (and log-probabilities) at step `step` of a rollout. gSDE draws new exploration matrices at
    the rollout's first step and every sde_freq steps after (reference code: collect_rollouts, sde_freq 4)."""
    if actor.use_sde and step % sde_freq == 0:
        actor.reset_noise(len(obs))
    return actor.sample(obs)


def make_critic(obs_dim: int, hidden_dim: int, num_layers: int) -> nn.Sequential:
    """V(s): a tanh MLP of its own (reference code: separate pi and vf layers), SB3's init."""
    critic = orthogonal_init(mlp(obs_dim, 1, hidden_dim, num_layers), math.sqrt(2))
    orthogonal_init(critic[-1], 1.0)
    return critic


def reset_value_head(critic: nn.Sequential):
    """The value reset after the first reward update (reference code: reset_value): only the output layer is
    drawn again; the hidden layers, and the optimizer with its moments, are kept."""
    orthogonal_init(critic[-1], 1.0)


def clip_range(clip_coef: float, global_step: int, total_timesteps: int) -> float:
    """The clip range of the update after the rollout that reached global_step (reference code: linear_schedule
    of SB3's progress_remaining = 1 - steps done / total steps): clip_coef at the start, 0 at the end."""
    return clip_coef * max(0.0, 1.0 - global_step / total_timesteps)


def ppo_loss(log_prob, old_log_prob, advantages, values, returns, entropy, clip: float, vf_coef: float,
             ent_coef: float):
    """Appendix Eqs. (4)-(5) as the reference code's PPO: the clipped surrogate on the (minibatch-normalised)
    advantages, plus vf_coef x the MSE of V against the GAE returns (no value clipping), minus ent_coef x the
    mean entropy. Returns (loss, policy_loss, value_loss, ratio)."""
    ratio = (log_prob - old_log_prob).exp()
    policy_loss = torch.max(-advantages * ratio, -advantages * ratio.clamp(1 - clip, 1 + clip)).mean()
    value_loss = F.mse_loss(values, returns)
    return policy_loss + vf_coef * value_loss - ent_coef * entropy, policy_loss, value_loss, ratio


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


class RunningMeanStd:
    """Running mean and variance (Chan et al.'s parallel update), for observations and the kNN reward.
    Normalised values are clipped to [-10, 10]; segments for the teacher stay in raw observations."""

    def __init__(self, dim):
        self.mean, self.var, self.count = np.zeros(dim), np.ones(dim), 1e-4

    def update(self, x: np.ndarray):
        batch_mean, batch_var, batch_count = x.mean(0), x.var(0), len(x)
        total = self.count + batch_count
        delta = batch_mean - self.mean
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total
        self.mean, self.var, self.count = self.mean + delta * batch_count / total, m2 / total, total

    def normalize(self, x: np.ndarray) -> np.ndarray:
        return np.clip((x - self.mean) / np.sqrt(self.var + 1e-8), -10, 10).astype(np.float32)


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


class KnnStateEntropy:
    """Algorithm 2's intrinsic reward r_int(s_t): the distance from s_t to its k-th nearest neighbour among every
    state of pre-training so far, this step's states of all envs included (reference code: a growing buffer on
    the device, raw observations), divided by a running standard deviation of these distances."""

    def __init__(self, obs_dim: int, k: int, device: torch.device):
        self.k, self.count = k, 0
        self.states = torch.zeros(1024, obs_dim, device=device)  # the buffer; its first `count` rows are filled
        self.stats = RunningMeanStd(1)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        """Adds this step's states (one per env) to the buffer; returns their normalised rewards."""
        if self.count + len(states) > len(self.states):  # grow: doubling keeps the copies linear in total
            self.states = torch.cat([self.states, self.states.new_zeros(max(len(self.states), len(states)),
                                                                          self.states.shape[1])])
        self.states[self.count : self.count + len(states)] = states
        self.count += len(states)
        distance = knn_distance(states, self.states[: self.count], self.k)[:, 0]
        self.stats.update(distance.cpu().numpy()[:, None])
        return distance / math.sqrt(self.stats.var[0] + 1e-8)

    def state_dict(self) -> dict:
        return {"states": self.states[: self.count].cpu(), "stats": dict(vars(self.stats))}

    def load_state_dict(self, state: dict):
        self.states, self.count = state["states"].to(self.states.device), len(state["states"])
        vars(self.stats).update(state["stats"])


def annotation_buffer(recent_episodes: int) -> deque:
    """The complete episodes that segments are drawn from, in raw observations (obs, actions, true rewards): the
    last `recent_episodes`, or every one with 0 (reference code: add_data_batch never trims; 4M walker steps hold
    4M x (24 + 6 + 1) float32 = 0.5 GB, quadruped's 4M x 91 = 1.5 GB, Meta-World's 3M x 44 = 0.5 GB)."""
    return deque(maxlen=recent_episodes or None)


def true_next_observations(next_obs: np.ndarray, infos: dict, done: np.ndarray) -> np.ndarray:
    """With Gymnasium's same-step autoreset, `next_obs` of an environment whose episode just ended
    is already the first observation of its next episode; the last one is in infos["final_obs"]."""
    real = next_obs.copy()
    for i in np.flatnonzero(done):
        real[i] = infos["final_obs"][i]
    return real


def compute_gae(rewards, values, next_values, dones, gamma, gae_lambda):
    """Generalised advantage estimation over a rollout of shape (T, N). next_values[t] is V of the
    state after step t; a done step (termination or truncation) cuts the recursion. A truncated step
    carries gamma * V(final observation) in its reward already, so time limits are bootstrapped."""
    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(rewards[0])
    for t in reversed(range(len(rewards))):
        not_done = 1.0 - dones[t]
        delta = rewards[t] + gamma * next_values[t] * not_done - values[t]
        last = delta + gamma * gae_lambda * not_done * last
        advantages[t] = last
    return advantages, advantages + values


def learned_rewards(reward_model: RewardEnsemble, raw_obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """r_hat(s, a) of the ensemble mean for every step of a rollout: (T, N, obs), (T, N, act) -> (T, N)."""
    with torch.no_grad():
        return reward_model(torch.cat([raw_obs, actions], dim=-1)).mean(0)[..., 0]


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


def resolve(args: Args) -> Args:
    """Fill every field left None from the task's preset and the teacher's; a flag the user gave wins."""
    family = {"dmc": DMC_PRESET, "metaworld": METAWORLD_PRESET, "gym": GYM_PRESET}[env_kind(args.env_id)]
    preset = PRESETS.get(args.env_id.removesuffix("-v3"), family)
    for key, value in preset.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.teacher in TEACHERS:  # every field of the teacher the run uses, so that config.json records it
        teacher = make_teacher(args.teacher)
        for name in ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal"):
            if getattr(args, f"teacher_{name}") is None:
                setattr(args, f"teacher_{name}", getattr(teacher, name))
    return args


def check_args(args: Args, episode_len: int) -> str | None:
    """The first problem with the configuration as one line, or None."""
    overrides = {"teacher_beta": (args.teacher_beta, "must be >= 0 (inf = rational)", lambda v: v >= 0),
                 "teacher_gamma": (args.teacher_gamma, "must be in (0, 1]", lambda v: 0 < v <= 1)}
    for name in ("teacher_eps_mistake", "teacher_eps_skip", "teacher_eps_equal"):
        overrides[name] = (getattr(args, name), "must be in [0, 1]", lambda v: 0 <= v <= 1)
    rollout = args.num_envs * args.num_steps
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
        (args.unsup_steps >= 0, f"--unsup-steps must be >= 0, got {args.unsup_steps}"),
        (min(args.num_envs, args.num_steps, args.update_epochs, args.unsup_update_epochs, args.sde_freq) >= 1,
         "--num-envs, --num-steps, --update-epochs, --unsup-update-epochs and --sde-freq must be >= 1"),
        (1 <= args.minibatch_size <= rollout,
         f"--minibatch-size must be in [1, --num-envs x --num-steps = {rollout}], got {args.minibatch_size}"),
        (args.total_timesteps > args.unsup_steps and args.total_timesteps >= rollout,
         f"--total-timesteps ({args.total_timesteps}) must exceed --unsup-steps ({args.unsup_steps}) and one rollout ({rollout})"),
        (min(args.hidden_dim, args.num_layers, args.reward_batch_size, args.reward_ensemble_size) >= 1,
         "--hidden-dim, --num-layers, --reward-batch-size and --reward-ensemble-size must be >= 1"),
        (min(args.eval_every, args.eval_episodes, args.knn_k, args.candidate_multiplier, args.reward_epochs) >= 1,
         "--eval-every, --eval-episodes, --knn-k, --candidate-multiplier and --reward-epochs must be >= 1"),
        (args.learning_rate > 0 and args.reward_lr > 0, "--learning-rate and --reward-lr must be > 0"),
        (0 < args.gamma <= 1 and 0 <= args.gae_lambda <= 1, "--gamma must be in (0, 1] and --gae-lambda in [0, 1]"),
        (args.clip_coef > 0 and args.ent_coef >= 0 and args.vf_coef >= 0 and args.max_grad_norm > 0,
         "--clip-coef and --max-grad-norm must be > 0, --ent-coef and --vf-coef >= 0"),
        (0 <= args.label_smoothing < 1, f"--label-smoothing must be in [0, 1), got {args.label_smoothing}"),
        (args.query_recent_episodes >= 0, f"--query-recent-episodes must be >= 0, got {args.query_recent_episodes}"),
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


def evaluate(actor, obs_stats, reward_model, env, episodes, device) -> dict:
    """Mean-action episodes with the true reward (B-Pref's metric), Meta-World success (success at any
    step), and the Pearson correlation of learned and true per-step rewards (the paper's reward analysis)."""
    returns, successes, true_rewards, learned = [], [], [], []
    for _ in range(episodes):
        obs, _ = env.reset()
        done, episode_return, success = False, 0.0, False
        while not done:
            with torch.no_grad():
                action = actor.mean(torch.as_tensor(obs_stats.normalize(obs), device=device)).clamp(-1, 1)
                if reward_model is not None:
                    learned.append(reward_model(torch.cat([torch.as_tensor(obs, device=device), action])).mean().item())
            obs, reward, terminated, truncated, info = env.step(action.cpu().numpy())
            done = terminated or truncated
            episode_return += reward
            true_rewards.append(reward)
            success = success or bool(info.get("success", False))
        returns.append(episode_return)
        successes.append(success)
    correlation = float("nan")
    if learned and np.std(learned) > 0 and np.std(true_rewards) > 0:
        correlation = float(np.corrcoef(learned, true_rewards)[0, 1])
    return {"episode_return": float(np.mean(returns)), "episode_return_std": float(np.std(returns)),
            "success_rate": float(np.mean(successes)), "reward_correlation": correlation}


def record_video(actor, obs_stats, video_env, device, name: str):
    """--capture-video: one more mean-action episode, saved as videos/<name>.mp4 and not counted in the
    evaluation (so metrics and resumed runs are the same with or without videos)."""
    obs, _ = video_env.reset()
    video_env.start_recording(name)
    done = False
    while not done:
        with torch.no_grad():
            action = actor.mean(torch.as_tensor(obs_stats.normalize(obs), device=device)).clamp(-1, 1)
        obs, _, terminated, truncated, _ = video_env.step(action.cpu().numpy())
        done = terminated or truncated
    video_env.stop_recording()  # writes the file now


if __name__ == "__main__":
    args = tyro.cli(Args)
    try:
        args = resumed_args(args) if args.resume else resolve(args)
        if args.seed < 0:  # before make_env: the env seeds are derived from it
            raise ValueError(f"--seed must be >= 0, got {args.seed}")
        env, episode_len = make_env(args.env_id, args.seed)
        problem = check_args(args, episode_len)
        obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
        if not problem and args.labels_from and not args.resume:
            imported_labels = load_labels(args.labels_from, obs_dim, action_dim, args.segment_len)
    except (ValueError, OSError, KeyError) as error:
        fail(str(error))
    if problem:
        fail(problem)
    seeds = run_seeds(args.seed, args.num_envs)
    try:
        env_state(env)
    except Exception as error:  # an env that cannot be pickled cannot be checkpointed
        fail(f"--env-id {args.env_id!r} cannot be checkpointed ({type(error).__name__}: {error})")
    env.close()
    video_env = None
    if args.capture_video:  # render one frame now rather than fail at the first evaluation
        try:
            import moviepy  # noqa: F401

            with warnings.catch_warnings(action="ignore"):  # GLFW warns before it fails without a display
                video_env, _ = make_env(args.env_id, seeds["video"], render_mode="rgb_array")
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

    # Seeding: numpy (query sampler; the teacher has its own stream), torch (networks, actions), environments
    rng = seeds["sampler"]
    torch.manual_seed(args.seed)
    # MuJoCo's float64 states cast to float32 give denormal numbers (tiny velocities), which make
    # CPU matrix products ~10x slower; flushing them to zero changes nothing measurable
    torch.set_flush_denormal(True)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if args.cuda else "cpu")
    envs = gym.vector.SyncVectorEnv(
        [lambda i=i: make_env(args.env_id, seeds["envs"][i])[0] for i in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
    eval_env, _ = make_env(args.env_id, seeds["eval"])
    if video_env is not None:  # recorded on demand by record_video
        video_env = gym.wrappers.RecordVideo(video_env, os.path.join(output_dir, "videos"), episode_trigger=lambda _: False)

    actor = Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers, args.use_sde).to(device)
    critic = make_critic(obs_dim, args.hidden_dim, args.num_layers).to(device)
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=args.learning_rate, eps=1e-5)
    critic_optimizer = torch.optim.Adam(critic.parameters(), lr=args.learning_rate, eps=1e-5)
    obs_stats, knn_reward = RunningMeanStd(obs_dim), KnnStateEntropy(obs_dim, args.knn_k, device)

    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = torch.optim.Adam(reward_model.parameters(), lr=args.reward_lr)
    teacher = make_teacher(args.teacher, seed=seeds["teacher"], **{k: v for k, v in {
        "beta": args.teacher_beta, "gamma": args.teacher_gamma, "eps_mistake": args.teacher_eps_mistake,
        "eps_skip": args.teacher_eps_skip, "eps_equal": args.teacher_eps_equal}.items() if v is not None})
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session)
    preference_inputs0, preference_inputs1, preference_y, labelled_features = [], [], [], []
    feedback_used = sessions_done = 0
    if args.labels_from and not args.resume:  # earlier labels: free, not counted in this run's budget
        preference_inputs0.append(torch.as_tensor(imported_labels["inputs0"], device=device))
        preference_inputs1.append(torch.as_tensor(imported_labels["inputs1"], device=device))
        preference_y.append(torch.as_tensor(imported_labels["y"], device=device))
        labelled_features.append(imported_labels["features"])
        print(f"--labels-from: {len(imported_labels['y'])} labels from {args.labels_from}")
    episodes = annotation_buffer(args.query_recent_episodes)

    def feedback_session(size: int, first: bool) -> int:
        """Algorithm 3, reward learning: SAMPLE() queries, ask SimTeacher, save the labels, learn r_hat."""
        global feedback_used, sessions_done
        usable = [e for e in episodes if len(e[2]) >= args.segment_len]
        sampler = "uniform" if first else args.sampler  # the first session is always uniform (reference code)
        n_candidates = size if sampler == "uniform" else size * args.candidate_multiplier
        e0, s0, e1, s1 = random_pairs([len(e[2]) for e in usable], args.segment_len, n_candidates, rng)
        window = np.arange(args.segment_len)
        obs0 = np.stack([usable[e][0][s + window] for e, s in zip(e0, s0)])
        obs1 = np.stack([usable[e][0][s + window] for e, s in zip(e1, s1)])
        act0 = np.stack([usable[e][1][s + window] for e, s in zip(e0, s0)])
        act1 = np.stack([usable[e][1][s + window] for e, s in zip(e1, s1)])
        true0 = np.stack([usable[e][2][s + window] for e, s in zip(e0, s0)])
        true1 = np.stack([usable[e][2][s + window] for e, s in zip(e1, s1)])
        inputs0 = torch.as_tensor(np.concatenate([obs0, act0], -1), device=device)
        inputs1 = torch.as_tensor(np.concatenate([obs1, act1], -1), device=device)
        features = None  # appendix: the states of both segments concatenated
        if args.sampler.endswith("coverage"):
            features = np.concatenate([obs0.reshape(len(obs0), -1), obs1.reshape(len(obs1), -1)], axis=1)
        if sampler == "uniform":  # random_pairs already drew `size` uniform pairs
            chosen = np.arange(size)
        else:
            with torch.no_grad():
                probs = torch.sigmoid(reward_model(inputs1).sum(2) - reward_model(inputs0).sum(2))[..., 0].cpu().numpy()
            labelled = np.concatenate(labelled_features) if labelled_features else None
            chosen = select(sampler, size, probs=probs, features=features, labeled_features=labelled, rng=rng)
        obs0, obs1, act0, act1, true0, true1 = obs0[chosen], obs1[chosen], act0[chosen], act1[chosen], true0[chosen], true1[chosen]

        # Appendix, adaptive thresholds: from the mean true return of the last 100 training episodes
        teacher.set_thresholds(float(np.mean(recent_returns)), args.segment_len, episode_len)
        y, keep = teacher.label(true0, true1)
        write_atomic_npz(os.path.join(output_dir, "labels", f"session_{sessions_done:04d}.npz"), step=global_step,
                         obs0=obs0, actions0=act0, obs1=obs1, actions1=act1, rewards0=true0, rewards1=true1, y=y, keep=keep)
        feedback_used += size
        sessions_done += 1
        kept = torch.as_tensor(chosen[keep], device=device)
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

    # Main loop: Algorithm 3 with PPO, after Algorithm 2 (pre-training) for the first unsup_steps
    eval_path = os.path.join(output_dir, "eval.csv")
    eval_fields = ["step", "episode_return", "episode_return_std", "success_rate", "feedback", "reward_correlation",
                   "wall_time", "overhead_seconds"]
    counts = dict(updates_on_knn_reward=0, updates_on_learned_reward=0, value_resets=0, ppo_epochs=0)
    overhead_seconds = 0.0  # time in the preference-learning parts: kNN reward, queries, reward learning
    rollout_shape = (args.num_steps, args.num_envs)
    raw_obs_buf = torch.zeros(*rollout_shape, obs_dim, device=device)
    obs_buf = torch.zeros(*rollout_shape, obs_dim, device=device)
    actions_buf, env_actions_buf = (torch.zeros(*rollout_shape, action_dim, device=device) for _ in range(2))
    logprobs_buf, values_buf, next_values_buf = (torch.zeros(rollout_shape, device=device) for _ in range(3))
    true_rewards_buf, bootstrap_buf, dones_buf = (torch.zeros(rollout_shape, device=device) for _ in range(3))
    intrinsic_buf = torch.zeros(rollout_shape, device=device)
    current = [([], [], []) for _ in range(args.num_envs)]  # the running episode of each env
    recent_returns = deque(maxlen=100)
    episode_returns = np.zeros(args.num_envs)
    raw_obs, _ = envs.reset(seed=seeds["envs"])  # each env's own seed again, as make_env reset it
    next_feedback_step = args.unsup_steps
    next_eval_step, last_eval = args.eval_every, float("nan")
    reward_ready = False  # PPO trains on r_hat (or the true reward) instead of the kNN reward
    global_step, wall_time, eval_log = 0, 0.0, []  # eval_log: the rows of eval.csv
    next_checkpoint_step = args.checkpoint_every
    # The loop's progress: a checkpoint saves these names (and every object above), a resume restores them
    progress_names = ["global_step", "wall_time", "raw_obs", "current", "episodes", "recent_returns", "episode_returns",
                      "next_feedback_step", "next_eval_step", "next_checkpoint_step", "last_eval", "reward_ready",
                      "feedback_used", "sessions_done", "counts", "overhead_seconds", "eval_log"]

    def learner_state() -> dict:
        """Every network and optimizer by name."""
        return {"actor": actor, "critic": critic, "reward_model": reward_model, "actor_optimizer": actor_optimizer,
                "critic_optimizer": critic_optimizer, "reward_optimizer": reward_optimizer}

    def save_checkpoint(filename: str = "checkpoint.pt"):
        """Everything the run needs to go on exactly, after a rollout: networks, optimizers, normalisers, kNN
        buffer, preferences, annotation episodes, teacher, random generators, environments, counters and logs.
        gSDE's exploration matrices are not saved: every rollout draws new ones at its first step."""
        save_start, path = time.perf_counter(), os.path.join(output_dir, filename)
        atomic_torch_save({
            "progress": {name: globals()[name] for name in progress_names} | {"wall_time": time.time() - start_time},
            **{name: part.state_dict() for name, part in learner_state().items()},
            "obs_stats": vars(obs_stats), "knn_reward": knn_reward.state_dict(),
            "preferences": [preference_inputs0, preference_inputs1, preference_y, labelled_features],
            "teacher": teacher, "rng": rng, "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if args.cuda else None,
            "envs": [env_state(e) for e in envs.envs], "eval_env": env_state(eval_env),
        }, path)
        print(f"step {global_step}: {filename} saved ({os.path.getsize(path) / 2**20:.1f} MiB in "
              f"{time.perf_counter() - save_start:.1f} s)", flush=True)

    if checkpoint:  # --resume: put every saved part back
        for name, part in learner_state().items():
            part.load_state_dict(checkpoint[name])
        vars(obs_stats).update(checkpoint["obs_stats"])
        knn_reward.load_state_dict(checkpoint["knn_reward"])
        preference_inputs0, preference_inputs1, preference_y = ([t.to(device) for t in part] for part in checkpoint["preferences"][:3])
        labelled_features, teacher, rng = checkpoint["preferences"][3], checkpoint["teacher"], checkpoint["rng"]
        torch.set_rng_state(checkpoint["torch_rng"])
        if args.cuda:
            torch.cuda.set_rng_state_all(checkpoint["cuda_rng"])
        for sub_env, state in zip(envs.envs, checkpoint["envs"]):
            load_env_state(sub_env, state)
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
        """SIGTERM (a cluster's time limit) or SIGINT (Ctrl-C): checkpoint after this rollout, then exit."""
        global stop_signal
        stop_signal = signum

    signal.signal(signal.SIGTERM, request_stop)
    signal.signal(signal.SIGINT, request_stop)
    start_time = last_print = time.time() - wall_time
    try:
        while global_step < args.total_timesteps:
            # Feedback sessions at rollout boundaries: the first after pre-training, then every feedback_every
            if global_step >= args.unsup_steps and not reward_ready and args.ground_truth_reward:
                reward_ready = True
            if (not args.ground_truth_reward and global_step >= next_feedback_step and sessions_done < len(session_sizes)
                    and any(len(e[2]) >= args.segment_len for e in episodes)):
                session_start = time.perf_counter()
                if feedback_session(int(session_sizes[sessions_done]), first=not reward_ready):
                    reward_ready = True
                next_feedback_step = global_step + args.feedback_every
                overhead_seconds += time.perf_counter() - session_start
            if reward_ready and counts["value_resets"] == 0:  # the end of pre-training: a new value head
                reset_value_head(critic)
                counts["value_resets"] += 1

            # Rollout of num_steps in every environment
            for step in range(args.num_steps):
                obs_stats.update(raw_obs)
                obs = torch.as_tensor(obs_stats.normalize(raw_obs), device=device)
                if not reward_ready:  # pre-training: r_int(s_t) of Algorithm 2
                    knn_start = time.perf_counter()
                    intrinsic_buf[step] = knn_reward(torch.as_tensor(raw_obs, dtype=torch.float32, device=device))
                    overhead_seconds += time.perf_counter() - knn_start
                with torch.no_grad():
                    action, logprobs_buf[step] = explore(actor, obs, step, args.sde_freq)
                    values_buf[step] = critic(obs)[:, 0]
                env_action = action.clamp(-1, 1)  # executed and judged; PPO's ratio uses the sampled `action`
                env_action_np = env_action.cpu().numpy()
                next_raw_obs, true_reward, terminated, truncated, infos = envs.step(env_action_np)
                if not (np.isfinite(true_reward).all() and np.isfinite(next_raw_obs).all()):
                    raise NonFiniteError(f"non-finite reward ({true_reward.min()}) or observation from the environment")
                done = terminated | truncated
                real_next = true_next_observations(next_raw_obs, infos, done)
                raw_obs_buf[step], obs_buf[step], actions_buf[step] = torch.as_tensor(raw_obs), obs, action
                env_actions_buf[step] = env_action
                true_rewards_buf[step], dones_buf[step] = torch.as_tensor(true_reward), torch.as_tensor(done, dtype=torch.float32)
                with torch.no_grad():  # V of the state after this step; at a truncation it bootstraps the reward
                    next_values = critic(torch.as_tensor(obs_stats.normalize(real_next), device=device))[:, 0]
                next_values_buf[step] = next_values
                bootstrap_buf[step] = args.gamma * next_values * torch.as_tensor(truncated & ~terminated, dtype=torch.float32)
                for i in range(args.num_envs):
                    current[i][0].append(raw_obs[i])
                    current[i][1].append(env_action_np[i])
                    current[i][2].append(true_reward[i])
                    episode_returns[i] += true_reward[i]
                    if done[i]:
                        episodes.append(tuple(np.array(part, dtype=np.float32) for part in current[i]))
                        recent_returns.append(episode_returns[i])
                        writer.add_scalar("charts/episodic_return", episode_returns[i], global_step + step * args.num_envs)
                        current[i], episode_returns[i] = ([], [], []), 0.0
                raw_obs = next_raw_obs
            global_step += args.num_envs * args.num_steps

            # The reward PPO maximises: kNN state entropy (pre-training), r_hat (Algorithm 3) or the true reward
            if not reward_ready:
                rewards = intrinsic_buf
                counts["updates_on_knn_reward"] += 1
            elif args.ground_truth_reward:
                rewards = true_rewards_buf.clone()
                counts["updates_on_learned_reward"] += 1
            else:
                inference_start = time.perf_counter()
                rewards = learned_rewards(reward_model, raw_obs_buf, env_actions_buf)
                overhead_seconds += time.perf_counter() - inference_start
                counts["updates_on_learned_reward"] += 1
            advantages, returns = compute_gae(rewards + bootstrap_buf, values_buf, next_values_buf, dones_buf,
                                              args.gamma, args.gae_lambda)

            # PPO update (appendix Eqs. (4)-(5)): clipped surrogate, value regression, no entropy bonus
            b_obs, b_actions = obs_buf.reshape(-1, obs_dim), actions_buf.reshape(-1, action_dim)
            b_logprobs, b_advantages, b_returns, b_values = (x.reshape(-1) for x in (logprobs_buf, advantages, returns, values_buf))
            batch_size, clip_fractions = b_obs.shape[0], []
            clip = clip_range(args.clip_coef, global_step, args.total_timesteps)
            epochs = args.update_epochs if reward_ready else args.unsup_update_epochs
            for epoch in range(epochs):
                order = torch.randperm(batch_size, device=device)
                for start in range(0, batch_size, args.minibatch_size):
                    idx = order[start : start + args.minibatch_size]
                    distribution, _ = actor.distribution(b_obs[idx])
                    adv = b_advantages[idx]
                    adv = (adv - adv.mean()) / (adv.std() + 1e-8) if len(idx) > 1 else adv
                    entropy = distribution.entropy().sum(-1).mean()
                    loss, policy_loss, value_loss, ratio = ppo_loss(
                        distribution.log_prob(b_actions[idx]).sum(-1), b_logprobs[idx], adv, critic(b_obs[idx])[:, 0],
                        b_returns[idx], entropy, clip, args.vf_coef, args.ent_coef)
                    with torch.no_grad():
                        approx_kl = ((ratio - 1) - ratio.log()).mean()
                        clip_fractions.append(((ratio - 1).abs() > clip).float().mean().item())
                    check_finite("PPO loss", loss)  # before the step: the networks stay finite
                    actor_optimizer.zero_grad()
                    critic_optimizer.zero_grad()
                    loss.backward()
                    nn.utils.clip_grad_norm_([*actor.parameters(), *critic.parameters()], args.max_grad_norm)
                    actor_optimizer.step()
                    critic_optimizer.step()
            counts["ppo_epochs"] += epochs
            explained_variance = 1 - (b_returns - b_values).var() / b_returns.var().clamp(min=1e-8)
            writer.add_scalar("charts/clip_range", clip, global_step)
            for name, value in {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy, "approx_kl": approx_kl,
                                "clipfrac": np.mean(clip_fractions), "explained_variance": explained_variance}.items():
                writer.add_scalar(f"losses/{name}", float(value), global_step)
            writer.add_scalar("charts/SPS", int(global_step / (time.time() - start_time)), global_step)

            if global_step >= next_eval_step or global_step >= args.total_timesteps:
                next_eval_step += args.eval_every
                result = evaluate(actor, obs_stats, reward_model if reward_ready and not args.ground_truth_reward else None,
                                  eval_env, args.eval_episodes, device)
                last_eval = result["episode_return"]
                row = {"step": global_step, **result, "feedback": feedback_used, "wall_time": round(time.time() - start_time, 1),
                       "overhead_seconds": round(overhead_seconds, 1)}
                with open(eval_path, "a", newline="") as f:
                    csv.DictWriter(f, eval_fields).writerow(row)
                eval_log.append(row)
                for name in ("episode_return", "success_rate", "reward_correlation"):
                    writer.add_scalar(f"eval/{name}", result[name], global_step)
                if video_env is not None:
                    record_video(actor, obs_stats, video_env, device, f"step_{global_step}")
            if time.time() - last_print > 10 or global_step >= args.total_timesteps:
                last_print = time.time()
                sps = global_step / (last_print - start_time)
                print(f"step {global_step}/{args.total_timesteps} | {sps:.0f} SPS | ETA {(args.total_timesteps - global_step) / sps / 60:.1f} min"
                      f" | last eval return {last_eval:.1f} | labels {feedback_used}/{args.max_feedback}", flush=True)

            if args.checkpoint_every and global_step >= next_checkpoint_step or stop_signal:
                next_checkpoint_step = (global_step // args.checkpoint_every + 1) * args.checkpoint_every if args.checkpoint_every else 0
                save_checkpoint()
            if stop_signal:
                print(f"{signal.Signals(stop_signal).name}: checkpoint saved at step {global_step}; "
                      f"continue with --resume {output_dir}", flush=True)
                sys.exit(128 + stop_signal)
    except NonFiniteError as error:
        # Mid-rollout or mid-update the envs have moved past the last checkpoint, which stays as it is. The state
        # at the failure (finite: the checks come before the optimizer steps) goes to a file of its own, to
        # inspect, not to resume from
        save_checkpoint("checkpoint_nonfinite.pt")
        last = os.path.join(output_dir, "checkpoint.pt")
        fail(f"{error} at step {global_step}; run stopped, "
             f"{'its last checkpoint is intact in ' + last if os.path.exists(last) else 'no checkpoint was due yet'}, "
             f"the state at the failure is in {output_dir}/checkpoint_nonfinite.pt and the labels in "
             f"{output_dir}/labels", code=3)
    except OSError as error:
        fail(f"writing to {output_dir!r} failed at step {global_step} ({error.strerror or error}); "
             "the last checkpoint there is intact", code=1)

    print(f"done: {counts} (updates_on_learned_reward: the true reward with --ground-truth-reward), "
          f"{sessions_done} feedback sessions, {feedback_used} queries; outputs in {output_dir}")
    torch.save({"actor": actor.state_dict(), "critic": critic.state_dict(), "reward_model": reward_model.state_dict(),
                "obs_mean": obs_stats.mean, "obs_var": obs_stats.var}, os.path.join(output_dir, "final_model.pt"))
    for each_env in (envs, eval_env, video_env):
        if each_env is not None:
            each_env.close()
    writer.close()
