# PrefPPO (Christiano et al. 2017, with PPO) as benchmarked by B-Pref (Lee et al. 2021); docs/prefppo.md
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
from collections import deque
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
    exp_name: str = "prefppo"
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
    compile: bool = False
    """if toggled, torch.compile the PPO minibatch loss (faster after a first compilation of about 10 s)"""
    output_dir: str | None = None
    """where the run's files go (default: runs/<run name>)"""
    checkpoint_every: int = 50000
    """environment steps between checkpoints, taken after a rollout (0 = only on SIGTERM/SIGINT)"""
    resume: str | None = None
    """continue the run in this directory from its checkpoint, with its saved configuration"""
    labels_from: str | None = None
    """seed the preference dataset with an earlier run's labels (its directory, labels/ or one .npz)"""

    # Algorithm specific arguments; None = the task's preset (PRESETS below)
    env_id: str = "walker-walk"
    """DMC `domain-task`, Meta-World v3 task name (with or without -v3), or a Gymnasium id"""
    total_timesteps: int | None = None
    """total environment steps (all environments together)"""
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
    """generalized state-dependent exploration, gSDE (reference code: use_sde 1); --no-use-sde: a Gaussian"""
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
    """episodes per evaluation (the reference's PrefPPO evaluated none: docs/differences.md 15)"""
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
    """segments come from the last N complete episodes (0 = all so far, pre-training's too: reference code)"""


# Paper appendix, table of PrefPPO hyperparameters (docs/prefppo.md lists the values the paper leaves open)
DMC_PRESET = dict(total_timesteps=4_000_000, max_feedback=1000, feedback_per_session=100, feedback_every=32_000,
                  segment_len=50, learning_rate=5e-5, num_envs=32, num_steps=500, minibatch_size=64, gae_lambda=0.92,
                  reward_epochs=100)  # reference code: re_update 100 (train_PrefPPO.py default, DMC scripts)
METAWORLD_PRESET = dict(total_timesteps=3_000_000, max_feedback=10_000, feedback_per_session=100,
                        feedback_every=16_000, segment_len=25, learning_rate=3e-4, num_envs=8, num_steps=250,
                        minibatch_size=128, gae_lambda=0.92, reward_epochs=50)  # reference code: --re-update 50
GYM_PRESET = dict(DMC_PRESET, learning_rate=3e-4, num_envs=8, num_steps=256, minibatch_size=64, gae_lambda=0.95)
PRESETS = {"walker-walk": DMC_PRESET, "button-press": METAWORLD_PRESET,
           "sweep-into": dict(METAWORLD_PRESET, num_envs=32, minibatch_size=256),
           "quadruped-walk": dict(DMC_PRESET, num_envs=16, minibatch_size=128, gae_lambda=0.9)}
CPU_SCALE = "python prefppo.py --env-id walker-walk --total-timesteps 1000000"  # docs/results.md


# Environments
class DMCEnv(gym.Env):
    """A dm_control suite task as a Gymnasium env: flat observations, episodes end by truncation; reset(seed=s)
    re-seeds the task's random state, so an episode is a function of s and the actions."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, domain: str, task: str, render_mode: str | None = None):
        from dm_control import suite

        self.dmc, self.render_mode = suite.load(domain, task), render_mode
        obs_dim, spec = sum(int(np.prod(v.shape)) for v in self.dmc.observation_spec().values()), self.dmc.action_spec()
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(spec.minimum.astype(np.float32), spec.maximum.astype(np.float32))

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.dmc.task.random.seed(seed)
        return np.concatenate([np.ravel(v) for v in self.dmc.reset().observation.values()]), {}

    def step(self, action):
        step = self.dmc.step(action)
        obs = np.concatenate([np.ravel(v) for v in step.observation.values()])
        return obs, step.reward, step.last() and step.discount == 0, step.last() and step.discount != 0, {}

    def render(self):
        return self.dmc.physics.render(height=240, width=320, camera_id=0)


class MetaWorldSeeding(gym.Wrapper):
    """Meta-World's reset ignores `seed`: here it seeds the generator of object and goal positions first."""

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self.env.unwrapped.seed(seed)
        return self.env.reset(options=options)


def env_kind(env_id: str) -> str:
    """'dmc' for a suite task (domain-task), 'metaworld' for a v3 task name (with or without -v3), else 'gym'."""
    import metaworld

    with warnings.catch_warnings(action="ignore"):  # GLFW's "failed to open display" on a headless machine
        from dm_control import suite
    if tuple(env_id.split("-", 1)) in suite.ALL_TASKS:
        return "dmc"
    return "metaworld" if f"{env_id.removesuffix('-v3')}-v3" in metaworld.ALL_V3_ENVIRONMENTS else "gym"


def make_env(env_id: str, render_mode: str | None = None) -> tuple[gym.Env, int]:
    """(env, episode length T): actions rescaled to [-1, 1], observations flat float32. Every reset is
    seeded by the caller (episode_seed), so nothing carries over from one episode to the next."""
    kind = env_kind(env_id)
    if kind == "dmc":
        env = DMCEnv(*env_id.split("-", 1), render_mode)
        episode_len = int(env.dmc._step_limit)
    elif kind == "metaworld":
        env = gym.make("Meta-World/MT1", env_name=f"{env_id.removesuffix('-v3')}-v3", render_mode=render_mode,
                       disable_env_checker=True)  # its checker warns about the hidden goal's zero bounds
        env.get_wrapper_attr("toggle_terminate_on_success")(False)  # B-Pref: fixed 500-step episodes
        # Reference code (utils.make_metaworld_env): a fresh goal from the task's whole range at every reset, not one
        # of MT1's 50 fixed goals: one task for its settings, then the random vector (object and goal positions) is
        # unfrozen and drawn from the env's generator. The goal is hidden (zeros), as in the reference's v2 envs
        env.unwrapped.set_task(env.get_wrapper_attr("tasks")[0])
        env.get_wrapper_attr("toggle_sample_tasks_on_reset")(False)
        env.unwrapped._partially_observable, env.unwrapped._freeze_rand_vec = True, False
        env.unwrapped.seeded_rand_vec = True
        env, episode_len = MetaWorldSeeding(env), env.spec.max_episode_steps or 500
    else:
        try:  # "my_package:MyEnv-v0": Gymnasium imports my_package, which registers MyEnv-v0
            env = gym.make(env_id, **({"render_mode": render_mode} if render_mode else {}))
        except (gym.error.Error, ImportError) as error:
            raise ValueError(f"--env-id {env_id!r} is not a DMC task (domain-task, e.g. walker-walk), a Meta-World v3 "
                             f"task (e.g. button-press) or a Gymnasium id (optionally module:id): {error}") from None
        episode_len = env.spec.max_episode_steps
        if not (isinstance(env.action_space, gym.spaces.Box) and isinstance(env.observation_space, gym.spaces.Box)
                and episode_len):
            raise ValueError(f"--env-id {env_id!r} needs Box observation and action spaces and a time limit")
    bound = np.ones(env.action_space.shape, np.float32)  # float32 bounds: no "precision lowered" warnings
    env = gym.wrappers.RescaleAction(env, -bound, bound)
    space = gym.spaces.Box(-np.inf, np.inf, env.observation_space.shape, np.float32)
    return gym.wrappers.TransformObservation(env, lambda obs: np.asarray(obs, np.float32), space), episode_len


TRAIN_STREAM, EVAL_STREAM = 0, 1  # the streams of episode seeds of the training and the evaluation envs


def numpy_seeds(seed: int) -> list[np.random.SeedSequence]:
    """Independent streams from one run seed: query sampler, teacher."""
    return np.random.SeedSequence(seed).spawn(2)


def episode_seed(run_seed: int, stream: int, episode: int) -> int:
    """The reset seed of an episode of a stream, drawn from SeedSequence([run_seed, stream, episode]): any episode
    can be played again alone, and runs with different seeds share no episode (up to chance)."""
    return int(np.random.SeedSequence([run_seed, stream, episode]).generate_state(1)[0])


# Networks
def mlp(in_dim: int, out_dim: int, hidden_dim: int, num_layers: int, activation=nn.Tanh) -> nn.Sequential:
    layers = [m for i in range(num_layers) for m in (nn.Linear(hidden_dim if i else in_dim, hidden_dim), activation())]
    return nn.Sequential(*layers, nn.Linear(hidden_dim if num_layers else in_dim, out_dim))


def orthogonal_init(module: nn.Module, gain: float) -> nn.Module:
    """Orthogonal weights with this gain, zero biases (reference code: SB3's ActorCriticPolicy init, gain sqrt(2)
    for hidden layers, 0.01 for the policy output, 1 for the value output)."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)
    return module


def sde_std(latent: torch.Tensor, log_std: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """gSDE's action std (reference code: SB3's StateDependentNoiseDistribution): latent @ W, W_ij ~ N(0,
    exp(log_std_ij)^2), is Gaussian with variance sum_i latent_i^2 exp(log_std_ij)^2 for action j (+ SB3's eps).
    latent (batch, hidden), log_std (hidden, action) -> (batch, action)."""
    return torch.sqrt(latent**2 @ log_std.exp() ** 2 + eps)


class Actor(nn.Module):
    """The reference code's PPO policy (SB3's ActorCriticPolicy): a tanh MLP of its own whose last hidden features,
    the latent, feed a linear mean; log std starts at 0; actions are clipped to [-1, 1] in the env. gSDE (reference
    code: use_sde, full_std, no squashing, latent detached in the noise and std): env n acts mean + latent @ W_n,
    W_n with entries N(0, exp(log_std)^2), i.e. N(mean, sde_std); without gSDE one log std per action."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers, use_sde: bool):
        super().__init__()
        self.policy = orthogonal_init(mlp(obs_dim, action_dim, hidden_dim, num_layers), math.sqrt(2))
        orthogonal_init(self.policy[-1], 0.01)
        self.use_sde = use_sde
        self.log_std = nn.Parameter(torch.zeros((hidden_dim, action_dim) if use_sde else (action_dim,)))
        self.exploration = None  # gSDE: the matrices W_n in use, (envs, hidden, action)

    def mean(self, obs):
        return self.policy(obs)

    def distribution(self, obs) -> tuple[torch.distributions.Normal, torch.Tensor]:
        """pi(. | s) and the latent."""
        latent = self.policy[:-1](obs)
        if self.use_sde:
            std = sde_std(latent.detach(), self.log_std)
            return torch.distributions.Normal(self.policy[-1](latent), std, validate_args=False), latent
        mean = self.policy[-1](latent)
        return torch.distributions.Normal(mean, self.log_std.exp().expand_as(mean), validate_args=False), latent

    def sample(self, obs, step: int, sde_freq: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Actions and log-probabilities at step `step` of a rollout. gSDE draws each env's W_n at the rollout's
        first step and every sde_freq steps after (reference code: collect_rollouts, sde_freq 4)."""
        distribution, latent = self.distribution(obs)
        if not self.use_sde:
            action = distribution.sample()
        else:
            if step % sde_freq == 0:
                self.exploration = self.log_std.exp() * torch.randn(len(obs), *self.log_std.shape, device=obs.device)
            action = distribution.loc + torch.bmm(latent.detach().unsqueeze(1), self.exploration).squeeze(1)
        return action, distribution.log_prob(action).sum(-1)


def make_critic(obs_dim: int, hidden_dim: int, num_layers: int) -> nn.Sequential:
    """V(s): a tanh MLP of its own (reference code: separate pi and vf layers), SB3's init."""
    critic = orthogonal_init(mlp(obs_dim, 1, hidden_dim, num_layers), math.sqrt(2))
    orthogonal_init(critic[-1], 1.0)
    return critic


def reset_value_head(critic: nn.Sequential):
    """The value reset after the first reward update (reference code: reset_value): only the output layer is
    drawn again; the hidden layers, and the optimizer with its moments, are kept."""
    orthogonal_init(critic[-1], 1.0)


class RewardEnsemble(nn.Module):
    """Appendix "Reward model": members of 3 x 256 LeakyReLU layers with a tanh-bounded output; (..., obs+action)
    -> each member's reward (members, ..., 1)."""

    def __init__(self, obs_dim, action_dim, size):
        super().__init__()
        self.members = nn.ModuleList(
            nn.Sequential(mlp(obs_dim + action_dim, 1, 256, 3, nn.LeakyReLU), nn.Tanh()) for _ in range(size))

    def forward(self, obs_action):
        return torch.stack([member(obs_action) for member in self.members])


# Algorithm: the math a reader must trust (each unit-tested), the kNN reward, reward learning
def clip_range(clip_coef: float, global_step: int, total_timesteps: int) -> float:
    """The clip range of the update after the rollout that reached global_step (reference code: SB3's
    linear_schedule of progress_remaining = 1 - steps done / total): clip_coef at the start, 0 at the end."""
    return clip_coef * max(0.0, 1.0 - global_step / total_timesteps)


def ppo_policy_loss(log_prob, old_log_prob, advantages, clip: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Appendix Eq. (4), PPO's clipped surrogate: mean of max(-A ratio, -A clip(ratio, 1 - clip, 1 + clip)),
    ratio = pi(a|s) / pi_old(a|s). Returns (loss, ratio)."""
    ratio = (log_prob - old_log_prob).exp()
    return torch.max(-advantages * ratio, -advantages * ratio.clamp(1 - clip, 1 + clip)).mean(), ratio


def ppo_value_loss(values: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    """Appendix Eq. (5): the MSE of V against the GAE returns, no clipping (reference code: SB3's PPO, which
    weighs it by vf_coef 0.5 in the total loss)."""
    return F.mse_loss(values, returns)


def optimize(optimizer, loss: torch.Tensor, name: str, max_grad_norm: float | None = None):
    """One gradient step, the gradients clipped to max_grad_norm; a non-finite loss stops the run before it
    (FloatingPointError): the networks stay finite. Backward computes the gradients of this optimizer's parameters."""
    if not torch.isfinite(loss).all():
        raise FloatingPointError(f"non-finite {name} ({loss.detach().flatten()[0].item()})")
    optimizer.zero_grad()
    loss.backward(inputs=(params := [param for group in optimizer.param_groups for param in group["params"]]))
    if max_grad_norm is not None:
        nn.utils.clip_grad_norm_(params, max_grad_norm)
    optimizer.step()


def adam(params, lr: float, eps: float = 1e-8) -> torch.optim.Adam:
    """Adam with fused kernels (PyTorch's fused=True: one kernel a step, not a loop of small ones over the
    parameters): the same update, up to float rounding."""
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)


def ppo_loss(actor, critic, obs, actions, old_logprobs, advantages, returns, clip, args) -> tuple[torch.Tensor, dict]:
    """Appendix Eqs. (4)-(5) on a minibatch: the clipped surrogate + vf_coef x the value loss - ent_coef x the entropy,
    advantages normalised per minibatch; and the minibatch's statistics, on the device (no host sync)."""
    distribution, _ = actor.distribution(obs)
    adv = (advantages - advantages.mean()) / (advantages.std() + 1e-8) if len(obs) > 1 else advantages
    entropy = distribution.entropy().sum(-1).mean()
    policy_loss, ratio = ppo_policy_loss(distribution.log_prob(actions).sum(-1), old_logprobs, adv, clip)
    value_loss = ppo_value_loss(critic(obs)[:, 0], returns)
    stats = {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
             "approx_kl": ((ratio - 1) - ratio.log()).mean(), "clipfrac": ((ratio - 1).abs() > clip).float().mean()}
    return policy_loss + args.vf_coef * value_loss - args.ent_coef * entropy, stats


def ppo_update(obs, actions, logprobs, advantages, returns, actor, critic, optimizer, epochs, clip, args,
               loss_fn=ppo_loss) -> dict:
    """PPO's update of a rollout: `epochs` passes over it in shuffled minibatches, one step of loss_fn (ppo_loss,
    compiled with --compile) each. The last minibatch's statistics, the clip fraction over all of them."""
    clip_fractions = []
    for _ in range(epochs):
        order = torch.randperm(len(obs), device=obs.device)  # the rollout shuffled once an epoch, cut in minibatches
        shuffled = [x[order].split(args.minibatch_size) for x in (obs, actions, logprobs, advantages, returns)]
        for minibatch in zip(*shuffled):
            loss, stats = loss_fn(actor, critic, *minibatch, clip, args)
            optimize(optimizer, loss, "PPO loss", args.max_grad_norm)
            clip_fractions.append(stats["clipfrac"])
    return {name: value.detach() for name, value in stats.items()} | {"clipfrac": torch.stack(clip_fractions).mean()}


def compute_gae(rewards, values, next_values, dones, gamma, gae_lambda):
    """Generalised advantage estimation over a rollout of shape (T, N). next_values[t] is V of the state after
    step t; a done step (termination or truncation) cuts the recursion. A truncated step carries
    gamma * V(final observation) in its reward already, so time limits are bootstrapped."""
    advantages, last = torch.zeros_like(rewards), torch.zeros_like(rewards[0])
    for t in reversed(range(len(rewards))):
        not_done = 1.0 - dones[t]
        last = rewards[t] + gamma * next_values[t] * not_done - values[t] + gamma * gae_lambda * not_done * last
        advantages[t] = last
    return advantages, advantages + values


def knn_distance(states: torch.Tensor, reference: torch.Tensor, k: int) -> torch.Tensor:
    """Eq. (8) without the log (docs): distance to the k-th nearest neighbour in `reference`, not counting the
    state itself (its zero distance): the (k+1)-th smallest. Memory: states x reference distances."""
    distances = torch.cdist(states, reference).topk(min(k + 1, len(reference)), dim=1, largest=False).values
    return distances[:, -1:].contiguous()  # topk: ~5x faster than kthvalue on a 10K-state buffer


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


class KnnStateEntropy:
    """Algorithm 2's r_int(s_t): the distance from s_t to its k-th nearest neighbour among every state of
    pre-training so far, this step's included (reference code: a growing buffer of raw observations on the
    device), divided by a running standard deviation of these distances."""

    def __init__(self, obs_dim: int, k: int, device: torch.device):
        self.k, self.states, self.stats = k, torch.zeros(0, obs_dim, device=device), RunningMeanStd(1)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        """Adds this step's states (one per env) to the buffer; returns their normalised rewards."""
        self.states = torch.cat([self.states, states])
        distance = knn_distance(states, self.states, self.k)[:, 0]
        self.stats.update(distance.cpu().numpy()[:, None])
        return distance / math.sqrt(self.stats.var[0] + 1e-8)


def coverage_features(inputs0: torch.Tensor, inputs1: torch.Tensor, obs_dim: int) -> np.ndarray:
    """Appendix, coverage sampling: the states of both segments of each query, flattened and concatenated."""
    return torch.cat([inputs0[..., :obs_dim].flatten(1), inputs1[..., :obs_dim].flatten(1)], 1).cpu().numpy()


def preference_loss(segment_returns: torch.Tensor, y: torch.Tensor, label_smoothing: float = 0.0) -> torch.Tensor:
    """Eq. (3): cross-entropy of P[sigma1 > sigma0] = softmax(sum r_hat) (Eq. (2)) against (1 - y, y), (batch, 2)."""
    target = (1 - label_smoothing) * y + label_smoothing / 2
    log_probs = F.log_softmax(segment_returns, dim=-1)
    return -((1 - target) * log_probs[:, 0] + target * log_probs[:, 1]).mean()


def preference_accuracy(segment_returns: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(correct, counted) over strict labels: an equal label has no right side (the reference code counted it)."""
    strict = y != 0.5
    return (((segment_returns[:, 1] > segment_returns[:, 0]) == (y > 0.5)) & strict).sum(), strict.sum()


def train_reward(reward_model, optimizer, preferences: dict, args) -> tuple[float, float]:
    """Algorithm 3, reward learning: up to --reward-epochs passes over D, one shuffle per member, until 97% accuracy."""
    inputs0, inputs1, y = preferences["inputs0"], preferences["inputs1"], preferences["y"]
    for _ in range(args.reward_epochs):
        orders = [torch.randperm(len(y), device=y.device) for _ in reward_model.members]
        correct = counted = loss_sum = torch.zeros((), device=y.device)  # summed on the device: one sync an epoch
        for start in range(0, len(y), args.reward_batch_size):
            loss = 0.0
            for member, order in zip(reward_model.members, orders):
                idx = order[start : start + args.reward_batch_size]
                returns = torch.cat([member(inputs0[idx]).sum(1), member(inputs1[idx]).sum(1)], dim=-1)
                loss = loss + preference_loss(returns, y[idx], args.label_smoothing)
                c, m = preference_accuracy(returns.detach(), y[idx])
                correct, counted = correct + c, counted + m
            optimize(optimizer, loss, "reward-model loss")
            loss_sum = loss_sum + loss.detach() / len(reward_model.members)
        accuracy = correct.item() / counted.item() if counted else float("nan")
        if accuracy > 0.97:
            break
    return (loss_sum / math.ceil(len(y) / args.reward_batch_size)).item(), accuracy


# Plumbing: command line, files, evaluation, the loop's state
def fail(message: str, code: int = 2):
    print(f"error: {message}", file=sys.stderr)
    sys.exit(code)


def parse_args() -> Args:
    """tyro's command line (--help lists every flag and choice); its error box becomes one `error: ...` line."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            args = tyro.cli(Args)
    except SystemExit as exit_:
        if exit_.code:  # not --help: the box's text up to its first rule
            text = "\n".join(line.strip("│╭╰╮╯ ") for line in captured.getvalue().splitlines()[1:])
            fail(" ".join(text.split("\n─")[0].split()))
        raise
    sys.stderr.write(captured.getvalue())  # tyro's warnings, if any
    return args


RESUME_MAY_CHANGE = ("resume", "checkpoint_every", "cuda", "track", "wandb_project_name", "capture_video", "compile")
TEACHER_FIELDS = ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal")  # SimTeacher's, --teacher-* here


def resolve(args: Args) -> Args:
    """Every field left None from the task's preset and the teacher's (a flag the user gave wins). With
    --resume DIR: the configuration saved in DIR; a flag that would change the experiment is refused."""
    if args.resume:
        if not os.path.isfile(os.path.join(args.resume, "checkpoint.pt")):
            raise ValueError(f"--resume {args.resume!r}: no checkpoint.pt there (a run stopped before its first "
                             "checkpoint has to start again)")
        with open(os.path.join(args.resume, "config.json")) as f:
            saved, names = json.load(f), [f.name for f in fields(Args)]
        if missing := [name for name in names if name not in saved]:
            raise ValueError(f"--resume {args.resume!r}: its config.json has no {', '.join(missing)} (written by an "
                             f"older {os.path.basename(__file__)}, whose run this one cannot continue)")
        for name in (name for name in names if name not in RESUME_MAY_CHANGE):
            if getattr(args, name) not in (getattr(Args(), name), saved[name]):
                raise ValueError(f"--{name.replace('_', '-')} cannot change when resuming (the run has "
                                 f"{saved[name]!r}, got {getattr(args, name)!r})")
        return Args(**saved | {name: getattr(args, name) for name in RESUME_MAY_CHANGE} | {"output_dir": args.resume})
    family = {"dmc": DMC_PRESET, "metaworld": METAWORLD_PRESET, "gym": GYM_PRESET}[env_kind(args.env_id)]
    teacher = make_teacher(args.teacher)
    preset = PRESETS.get(args.env_id.removesuffix("-v3"), family)
    for key, value in (preset | {f"teacher_{name}": getattr(teacher, name) for name in TEACHER_FIELDS}).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    return args


def check_args(args: Args, episode_len: int):
    """ValueError naming the first number out of its range (tyro checks types and choices)."""
    a, rollout = args, args.num_envs * args.num_steps
    rules = [("seed", a.seed >= 0, ">= 0"), ("teacher_beta", a.teacher_beta >= 0, ">= 0 (inf = rational)"),
             *[(n, 0 < getattr(a, n) <= 1, "in (0, 1]") for n in ("teacher_gamma", "gamma")],
             *[(n, 0 <= getattr(a, n) <= 1, "in [0, 1]") for n in ("teacher_eps_mistake", "teacher_eps_skip",
                                                                   "teacher_eps_equal", "gae_lambda")],
             *[(n, getattr(a, n) >= 1, ">= 1") for n in (
                 "max_feedback", "feedback_every", "hidden_dim", "num_layers", "num_envs", "num_steps",
                 "update_epochs", "unsup_update_epochs", "sde_freq", "reward_batch_size", "reward_ensemble_size",
                 "eval_every", "eval_episodes", "knn_k", "candidate_multiplier", "reward_epochs")],
             *[(n, getattr(a, n) >= 0, ">= 0") for n in ("unsup_steps", "ent_coef", "vf_coef", "query_recent_episodes",
                                                         "checkpoint_every")],
             *[(n, getattr(a, n) > 0, "> 0") for n in ("learning_rate", "reward_lr", "clip_coef", "max_grad_norm")],
             ("label_smoothing", 0 <= a.label_smoothing < 1, "in [0, 1)"),
             ("feedback_per_session", 1 <= a.feedback_per_session <= a.max_feedback,
              f"in [1, --max-feedback={a.max_feedback}]"),
             ("segment_len", 1 <= a.segment_len <= episode_len, f"in [1, {episode_len}] (the episode length)"),
             ("minibatch_size", 1 <= a.minibatch_size <= rollout, f"in [1, --num-envs x --num-steps = {rollout}]"),
             ("total_timesteps", a.total_timesteps > a.unsup_steps and a.total_timesteps >= rollout,
              f"> --unsup-steps ({a.unsup_steps}) and >= one rollout ({rollout})")]
    for name, ok, rule in rules:
        if not ok:
            raise ValueError(f"--{name.replace('_', '-')} must be {rule}, got {getattr(a, name)}")


def load_labels(path: str, obs_dim: int, action_dim: int, segment_len: int) -> dict:
    """--labels-from: the kept labels of saved sessions (a run directory, its labels/ or one .npz) as the labelled
    dataset's inputs0, inputs1 (observation and action per step) and y."""
    files = [path] if os.path.isfile(path) else sorted(glob.glob(os.path.join(path, "labels", "session_*.npz"))
                                                      or glob.glob(os.path.join(path, "session_*.npz")))
    sessions = [dict(np.load(file)) for file in files]
    if not sessions or any(s["obs0"].shape[1:] + s["actions0"].shape[2:] != (segment_len, obs_dim, action_dim)
                           for s in sessions):
        raise ValueError(f"--labels-from {path!r}: no session_*.npz files, or segments that do not fit this run "
                         f"({segment_len} steps of {obs_dim} observations and {action_dim} actions)")
    kept = {key: np.concatenate([s[key][s["keep"]] for s in sessions]) for key in ("obs0", "actions0", "obs1",
                                                                                   "actions1", "y")}
    return {"inputs0": np.concatenate([kept["obs0"], kept["actions0"]], -1),
            "inputs1": np.concatenate([kept["obs1"], kept["actions1"]], -1), "y": kept["y"].astype(np.float32)}


def save_file(path: str, data: bytes):
    """Written to a temporary file, flushed to disk, then renamed: a kill during the write leaves the old file."""
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
    """A checkpoint's leaf as plain data (numpy arrays as tensors, numpy scalars as Python numbers), so that
    torch.load(..., weights_only=True) reads the checkpoint without running code from the file."""
    if isinstance(leaf, np.ndarray):
        return torch.tensor(leaf)
    return leaf.item() if isinstance(leaf, np.generic) else leaf


def unplain(leaf):
    """plain()'s inverse for the parts the loop keeps in numpy."""
    return leaf.numpy() if isinstance(leaf, torch.Tensor) else leaf


EVAL_COLUMNS = ("step", "episode_return", "episode_return_std", "success_rate", "feedback", "reward_correlation",
                "wall_time", "overhead_seconds")


def eval_csv(rows: list[dict]) -> bytes:
    """eval.csv, written whole after each evaluation (a resumed run writes its checkpoint's rows again: none twice)."""
    lines = [EVAL_COLUMNS] + [[row[column] for column in EVAL_COLUMNS] for row in rows]
    return "".join(",".join(map(str, line)) + "\n" for line in lines).encode()


def evaluate(actor, obs_stats, reward_model, env, seeds: list[int], device) -> dict:
    """Mean-action episodes (one per reset seed) with the true reward (B-Pref's metric), Meta-World success
    (at any step), and the Pearson correlation of learned and true per-step rewards (the paper's analysis)."""
    returns, successes, true_rewards, learned = [], [], [], []
    for seed in seeds:
        (obs, _), done, success = env.reset(seed=seed), False, False
        returns.append(0.0)
        while not done:
            with torch.no_grad():
                action = actor.mean(torch.as_tensor(obs_stats.normalize(obs), device=device)).clamp(-1, 1)
                if reward_model is not None:
                    learned.append(reward_model(torch.cat([torch.as_tensor(obs, device=device), action])).mean().item())
            obs, reward, terminated, truncated, info = env.step(action.cpu().numpy())
            done, returns[-1], success = terminated or truncated, returns[-1] + reward, success or info.get("success")
            true_rewards.append(reward)
        successes.append(bool(success))
    correlation = float("nan")
    if learned and np.std(learned) > 0 and np.std(true_rewards) > 0:
        correlation = float(np.corrcoef(learned, true_rewards)[0, 1])
    return {"episode_return": float(np.mean(returns)), "episode_return_std": float(np.std(returns)),
            "success_rate": float(np.mean(successes)), "reward_correlation": correlation}


def projected_cpu_hours(args: Args, env: gym.Env, obs_dim: int) -> float:
    """The run on this CPU, from 20 timed environment steps and 5 PPO minibatch updates of throwaway networks of
    the actor's size on random data, timed before the run seeds torch (its state is untouched)."""
    net, batch = mlp(obs_dim, 1, args.hidden_dim, args.num_layers), torch.randn(args.minibatch_size, obs_dim)
    env.reset(seed=0)
    start = time.perf_counter()
    for _ in range(20):
        env.step(env.action_space.sample())
    step_seconds, start = (time.perf_counter() - start) / 20, time.perf_counter()
    for _ in range(5):
        net(batch).square().mean().backward()
    update_seconds = 2 * (time.perf_counter() - start) / 5  # actor and critic
    updates = args.total_timesteps / args.minibatch_size * args.update_epochs
    return (args.total_timesteps * step_seconds + updates * update_seconds) / 3600


@dataclass
class Progress:
    """What the main loop carries besides networks, optimizers and buffers: a checkpoint saves asdict(progress), a
    resume restores Progress(**saved), so a field added here is checkpointed by construction."""

    global_step: int = 0
    episodes: list = field(default_factory=list)  # env i runs its episode number episodes[i]
    current: list = field(default_factory=list)  # env i's running episode: observations, actions, true rewards so far
    recent_returns: list = field(default_factory=list)  # true returns of the last 100 training episodes
    sessions_done: int = 0
    feedback_used: int = 0
    next_feedback_step: int = 0
    next_checkpoint_step: int = 0
    eval_rows: list = field(default_factory=list)  # eval.csv
    reward_ready: bool = False  # PPO trains on r_hat (or the true reward), no longer on the kNN reward
    overhead_seconds: float = 0.0  # PrefPPO's own parts: kNN reward, queries, reward learning, r_hat
    wall_time: float = 0.0
    counts: dict = field(default_factory=lambda: dict.fromkeys(  # how often each phase ran, for the last line
        ("updates_on_knn_reward", "updates_on_learned_reward", "value_resets", "ppo_epochs"), 0))

    @contextlib.contextmanager
    def overhead(self):
        start = time.perf_counter()
        yield
        self.overhead_seconds += time.perf_counter() - start


if __name__ == "__main__":
    args = parse_args()
    try:  # every user error: one line, before any work
        args = resolve(args)
        env, episode_len = make_env(args.env_id)
        eval_env, _ = make_env(args.env_id, render_mode="rgb_array" if args.capture_video else None)
        obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
        check_args(args, episode_len)
        imported = (load_labels(args.labels_from, obs_dim, action_dim, args.segment_len)
                    if args.labels_from and not args.resume else None)
    except (ValueError, OSError, KeyError) as error:
        fail(str(error))
    if args.capture_video:  # render one frame now rather than fail at the first evaluation
        try:
            import moviepy  # noqa: F401

            with warnings.catch_warnings(action="ignore"):  # GLFW warns before it fails without a display
                eval_env.reset(seed=0)
                eval_env.render()
        except Exception as error:
            print(f"error: --capture-video cannot render ({type(error).__name__}: {(str(error) or '-').splitlines()[0]}"
                  "); it needs moviepy and, without a display, MUJOCO_GL=egl (GPU) or MUJOCO_GL=osmesa (CPU)",
                  file=sys.stderr, flush=True)
            os._exit(2)  # not sys.exit: the half-made GL context's finalizer would print a traceback
    run_name = f"{args.env_id}__{args.exp_name}__{args.teacher}__{args.seed}__{int(time.time())}"
    output_dir, config = args.output_dir or os.path.join("runs", run_name), asdict(args)
    if not args.resume and os.path.isdir(output_dir) and os.listdir(output_dir):
        fail(f"--output-dir {output_dir!r} already holds a run; continue it with --resume {output_dir} or choose "
             "another directory")
    try:
        os.makedirs(os.path.join(output_dir, "labels"), exist_ok=True)
        if not args.resume:
            save_file(os.path.join(output_dir, "config.json"), json.dumps(config, indent=2).encode())
    except OSError as error:
        fail(f"cannot write to --output-dir {output_dir!r}: {error.strerror}")
    print("configuration:\n" + "\n".join(f"  {key}: {value}" for key, value in config.items()))
    device = torch.device("cuda" if args.cuda and torch.cuda.is_available() else "cpu")
    print(f"device: {torch.cuda.get_device_name(device) if device.type == 'cuda' else 'cpu'}"
          + ("" if device.type == "cuda" else " (torch sees no GPU)" if args.cuda else " (--no-cuda)"), flush=True)
    if device.type == "cpu" and args.total_timesteps > 1_000_000:  # beyond the CPU scale of docs/results.md
        print(f"note: this run needs about {projected_cpu_hours(args, env, obs_dim):.0f} h on this CPU "
              f"(projected); use a GPU, or the CPU scale of docs/results.md: {CPU_SCALE}", flush=True)

    from torch.utils.tensorboard import SummaryWriter

    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, sync_tensorboard=True, config=config, name=run_name, save_code=True)
    checkpoint_path, eval_path = os.path.join(output_dir, "checkpoint.pt"), os.path.join(output_dir, "eval.csv")
    checkpoint = torch.load(checkpoint_path, map_location="cpu", weights_only=True) if args.resume else None
    writer = SummaryWriter(output_dir, purge_step=checkpoint["progress"]["global_step"] + 1 if checkpoint else None)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in config.items()))

    # Seeding: numpy (query sampler and teacher: independent streams), torch (networks, actions, minibatches),
    # every reset (episode_seed): an env is a function of its episode's seed and actions
    sampler_seed, teacher_seed = numpy_seeds(args.seed)
    rng = np.random.default_rng(sampler_seed)
    torch.manual_seed(args.seed)
    torch.set_flush_denormal(True)  # MuJoCo's tiny float32 velocities are denormals, ~10x slower on a CPU
    envs = [env] + [make_env(args.env_id)[0] for _ in range(args.num_envs - 1)]
    actor = Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers, args.use_sde).to(device)
    critic = make_critic(obs_dim, args.hidden_dim, args.num_layers).to(device)
    # one Adam over both networks, as SB3's policy (Adam works per parameter: the same as one for each)
    optimizer = adam([*actor.parameters(), *critic.parameters()], args.learning_rate, eps=1e-5)
    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = adam(reward_model.parameters(), args.reward_lr)
    obs_stats, knn_reward = RunningMeanStd(obs_dim), KnnStateEntropy(obs_dim, args.knn_k, device)
    loss_fn = torch.compile(ppo_loss) if args.compile else ppo_loss  # the eager ppo_loss is the reference
    teacher = make_teacher(args.teacher, seed=teacher_seed,
                           **{name: getattr(args, f"teacher_{name}") for name in TEACHER_FIELDS})
    rollout = args.num_envs * args.num_steps
    steps = session_steps(args.unsup_steps, args.feedback_every, args.total_timesteps - 1, rollout)
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session, steps,
                                   args.total_timesteps)
    spent = planned_labels(session_sizes, args.unsup_steps, args.feedback_every, args.total_timesteps - 1, rollout)
    if spent < args.max_feedback and not args.ground_truth_reward:
        print(f"note: only {spent} of the {args.max_feedback} labels of --max-feedback fit in {args.total_timesteps} "
              f"steps (sessions from step {args.unsup_steps}, every {args.feedback_every} steps, at rollout ends)")
    # The labelled dataset D: both segments' (observation, action) per step, and the label (--labels-from's are free)
    empty = np.zeros((0, args.segment_len, obs_dim + action_dim), np.float32)
    preferences = imported or {"inputs0": empty, "inputs1": empty, "y": np.zeros(0, np.float32)}
    preferences = {key: torch.as_tensor(value, device=device) for key, value in preferences.items()}
    if imported:
        print(f"--labels-from: {len(imported['y'])} labels from {args.labels_from}")
    # The query pool: the last query_recent_episodes complete episodes, (observations, actions, true rewards) each
    episodes = deque(maxlen=args.query_recent_episodes or None)  # (reference code: all, add_data_batch never trims)
    progress = Progress(episodes=[0] * args.num_envs, current=[([], [], []) for _ in range(args.num_envs)],
                        next_feedback_step=args.unsup_steps, next_checkpoint_step=args.checkpoint_every)
    learners = {"actor": actor, "critic": critic, "reward_model": reward_model, "optimizer": optimizer,
                "reward_optimizer": reward_optimizer, "teacher": teacher}
    if checkpoint:  # --resume: every part back, key by key
        saved_progress = checkpoint["progress"]
        progress = Progress(**saved_progress | {"current": tree_map(unplain, saved_progress["current"])})
        print(f"resuming from the checkpoint at step {progress.global_step}")
        for name, part in learners.items():
            part.load_state_dict(checkpoint[name])
        vars(obs_stats).update(tree_map(unplain, checkpoint["obs_stats"]))
        knn_reward.states = checkpoint["knn_states"].to(device)
        vars(knn_reward.stats).update(tree_map(unplain, checkpoint["knn_stats"]))
        preferences = {key: value.to(device) for key, value in checkpoint["preferences"].items()}
        rng.bit_generator.state = checkpoint["rng"]
        episodes.extend(tree_map(unplain, checkpoint["episodes"]))
        torch.set_rng_state(checkpoint["torch_rng"])
        if device.type == "cuda" and checkpoint["cuda_rng"] is not None:
            torch.cuda.set_rng_state_all(checkpoint["cuda_rng"])
        if progress.global_step >= args.total_timesteps:
            fail(f"the run in {output_dir!r} has already finished ({progress.global_step} steps)")
        aside = os.path.join(output_dir, "labels", f"before_resume_at_step_{progress.global_step}")
        for path in sorted(glob.glob(os.path.join(output_dir, "labels", "session_*.npz")))[progress.sessions_done:]:
            os.makedirs(aside, exist_ok=True)  # asked after the checkpoint: kept aside, the run asks them again
            os.replace(path, os.path.join(aside, os.path.basename(path)))
    # Each env at the start of its running episode (that episode's seed), then that episode's actions so far again:
    # MuJoCo is deterministic, so a resumed env is exactly where it was (a new run has no actions to replay)
    raw_obs = np.stack([e.reset(seed=episode_seed(args.seed, TRAIN_STREAM, progress.episodes[i] * args.num_envs + i))[0]
                        for i, e in enumerate(envs)])  # episode j of env i: number j * num_envs + i of the stream
    for i, action in ((i, action) for i in range(args.num_envs) for action in progress.current[i][1]):
        raw_obs[i] = envs[i].step(action)[0]
    if args.capture_video:  # the first episode of each evaluation: videos/step_N-episode-M.mp4
        eval_env = gym.wrappers.RecordVideo(eval_env, os.path.join(output_dir, "videos"),
                                            episode_trigger=lambda episode: episode % args.eval_episodes == 0)
    rollout_shape = (args.num_steps, args.num_envs)
    raw_obs_buf, obs_buf = (torch.zeros(*rollout_shape, obs_dim, device=device) for _ in range(2))
    actions_buf, env_actions_buf = (torch.zeros(*rollout_shape, action_dim, device=device) for _ in range(2))
    logprobs_buf, values_buf, next_values_buf, intrinsic_buf, true_rewards_buf, bootstrap_buf, dones_buf = (
        torch.zeros(rollout_shape, device=device) for _ in range(7))
    stop = []  # SIGTERM (a cluster's time limit) or SIGINT (Ctrl-C): checkpoint after this rollout, then exit
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    signal.signal(signal.SIGINT, lambda signum, frame: stop.append(signum))
    start_time = last_print = time.time() - progress.wall_time

    def checkpoint_state() -> dict:
        """Everything the run needs to go on exactly after this rollout, but the envs (each reset with its episode's
        seed, then the episode's actions replayed) and gSDE's matrices (each rollout draws new ones)."""
        return {"progress": tree_map(plain, asdict(progress) | {"wall_time": time.time() - start_time}),
                **{name: part.state_dict() for name, part in learners.items()},
                "obs_stats": tree_map(plain, vars(obs_stats)),
                "knn_states": knn_reward.states.cpu(), "knn_stats": tree_map(plain, vars(knn_reward.stats)),
                "preferences": preferences, "rng": rng.bit_generator.state, "episodes": tree_map(plain, list(episodes)),
                "torch_rng": torch.get_rng_state(),
                "cuda_rng": torch.cuda.get_rng_state_all() if device.type == "cuda" else None}

    # Main loop: Algorithm 3 with PPO, after Algorithm 2 (pre-training) for the first unsup_steps
    try:
        save_file(eval_path, eval_csv(progress.eval_rows))  # a resumed run drops the rows after its checkpoint
        while progress.global_step < args.total_timesteps:
            global_step = progress.global_step
            progress.reward_ready |= args.ground_truth_reward and global_step >= args.unsup_steps
            # Feedback session (Algorithm 3, reward learning) at a rollout's end: the first after pre-training,
            # then every feedback_every steps. SAMPLE() queries, ask SimTeacher, save the labels, learn r_hat
            if (not args.ground_truth_reward and global_step >= progress.next_feedback_step
                    and progress.sessions_done < len(session_sizes)
                    and any(len(episode[0]) >= args.segment_len for episode in episodes)):
                with progress.overhead():
                    size = int(session_sizes[progress.sessions_done])
                    sampler = args.sampler if progress.reward_ready else "uniform"  # the first: uniform (reference)
                    n_candidates = size if sampler == "uniform" else size * args.candidate_multiplier
                    candidates = draw_segments(episodes, args.segment_len, n_candidates, rng)
                    sides = [np.concatenate([candidates[f"obs{i}"], candidates[f"actions{i}"]], -1) for i in (0, 1)]
                    inputs0, inputs1 = (torch.as_tensor(side, device=device) for side in sides)  # (s, a) per step
                    chosen = np.arange(size)  # uniform: `size` uniform pairs were drawn
                    if sampler != "uniform":
                        with torch.no_grad():
                            probs = torch.sigmoid(reward_model(inputs1).sum(2) - reward_model(inputs0).sum(2))[..., 0]
                        labelled = (coverage_features(preferences["inputs0"], preferences["inputs1"], obs_dim)
                                    if sampler.endswith("coverage") else None)
                        chosen = select(sampler, size, probs=probs.cpu().numpy(), rng=rng, labeled_features=labelled,
                                        features=coverage_features(inputs0, inputs1, obs_dim))
                    segments = {key: value[chosen] for key, value in candidates.items()}
                    # Appendix, adaptive thresholds: mean true return of the last 100 training episodes (reference code)
                    teacher.set_thresholds(float(np.mean(progress.recent_returns)), args.segment_len, episode_len)
                    y, keep = teacher.label(segments["rewards0"], segments["rewards1"])
                    np.savez(data := io.BytesIO(), step=global_step, y=y, keep=keep, **segments)
                    save_file(os.path.join(output_dir, "labels", f"session_{progress.sessions_done:04d}.npz"),
                              data.getvalue())
                    progress.feedback_used += size
                    progress.sessions_done += 1
                    progress.next_feedback_step = global_step + args.feedback_every
                    new = {"inputs0": inputs0[chosen[keep]], "inputs1": inputs1[chosen[keep]],
                           "y": torch.as_tensor(y[keep], dtype=torch.float32, device=device)}
                    preferences = {key: torch.cat([preferences[key], new[key]]) for key in preferences}
                    skipped, equal, n_labels = (~keep).sum(), (y[keep] == 0.5).sum(), len(preferences["y"])
                    for name, value in [("labels", progress.feedback_used), ("skipped", skipped), ("equal", equal)]:
                        writer.add_scalar(f"feedback/{name}", int(value), global_step)
                    if n_labels == 0:  # every query so far was skipped: nothing to learn from yet
                        print(f"step {global_step}: all {size} queries skipped, the reward model stays as it is")
                    else:
                        loss, accuracy = train_reward(reward_model, reward_optimizer, preferences, args)
                        progress.reward_ready = True
                        writer.add_scalar("reward/loss", loss, global_step)
                        writer.add_scalar("reward/accuracy", accuracy, global_step)
                        print(f"step {global_step}: feedback session {progress.sessions_done}: {size} queries "
                              f"({skipped} skipped, {equal} equal), reward model trained on {n_labels} labels, "
                              f"accuracy {accuracy:.3f}")
            if progress.reward_ready and progress.counts["value_resets"] == 0:  # the end of pre-training: a new value
                reset_value_head(critic)  # head
                progress.counts["value_resets"] += 1

            # Rollout of num_steps in every env; an env whose episode ends is reset by us with its next episode's seed
            for t in range(args.num_steps):
                obs_stats.update(raw_obs)
                obs = torch.as_tensor(obs_stats.normalize(raw_obs), device=device)
                if not progress.reward_ready:  # pre-training: r_int(s_t) of Algorithm 2
                    with progress.overhead():
                        intrinsic_buf[t] = knn_reward(torch.as_tensor(raw_obs, device=device))
                with torch.no_grad():
                    action, logprobs_buf[t] = actor.sample(obs, t, args.sde_freq)
                    values_buf[t] = critic(obs)[:, 0]
                env_action = action.clamp(-1, 1)  # executed and judged; PPO's ratio uses the sampled `action`
                env_action_np, next_raw_obs, final_obs = env_action.cpu().numpy(), raw_obs.copy(), raw_obs.copy()
                true_reward, terminated, truncated = np.zeros(args.num_envs), *np.zeros((2, args.num_envs), bool)
                for i, train_env in enumerate(envs):
                    final_obs[i], true_reward[i], terminated[i], truncated[i], _ = train_env.step(env_action_np[i])
                    if not (np.isfinite(true_reward[i]) and np.isfinite(final_obs[i]).all()):
                        raise FloatingPointError(f"non-finite reward ({true_reward[i]}) or observation from the "
                                                 "environment")
                    for part, value in zip(progress.current[i], (raw_obs[i], env_action_np[i], true_reward[i])):
                        part.append(value)
                    next_raw_obs[i] = final_obs[i]
                    if terminated[i] or truncated[i]:  # final_obs[i] stays the episode's real last state
                        episodes.append(tuple(np.array(part, dtype=np.float32) for part in progress.current[i]))
                        episode_return = float(sum(progress.current[i][2]))
                        progress.recent_returns = (progress.recent_returns + [episode_return])[-100:]
                        writer.add_scalar("charts/episodic_return", episode_return, global_step + t * args.num_envs)
                        progress.current[i], progress.episodes[i] = ([], [], []), progress.episodes[i] + 1
                        seed = episode_seed(args.seed, TRAIN_STREAM, progress.episodes[i] * args.num_envs + i)
                        next_raw_obs[i] = train_env.reset(seed=seed)[0]
                raw_obs_buf[t], obs_buf[t], actions_buf[t] = torch.as_tensor(raw_obs), obs, action
                env_actions_buf[t], true_rewards_buf[t] = env_action, torch.as_tensor(true_reward)
                dones_buf[t] = torch.as_tensor(terminated | truncated)
                with torch.no_grad():  # V of the state after this step; at a truncation it bootstraps the reward
                    next_values_buf[t] = critic(torch.as_tensor(obs_stats.normalize(final_obs), device=device))[:, 0]
                truncated_only = torch.as_tensor(truncated & ~terminated, device=device)
                bootstrap_buf[t] = args.gamma * next_values_buf[t] * truncated_only
                raw_obs = next_raw_obs
            progress.global_step += rollout

            # The reward PPO maximises: kNN state entropy (pre-training), r_hat (Algorithm 3) or the true reward
            progress.counts["updates_on_learned_reward" if progress.reward_ready else "updates_on_knn_reward"] += 1
            rewards = true_rewards_buf if progress.reward_ready else intrinsic_buf
            if progress.reward_ready and not args.ground_truth_reward:
                with progress.overhead(), torch.no_grad():  # r_hat(s, a): the ensemble mean
                    rewards = reward_model(torch.cat([raw_obs_buf, env_actions_buf], dim=-1)).mean(0)[..., 0]
            advantages, returns = compute_gae(rewards + bootstrap_buf, values_buf, next_values_buf, dones_buf,
                                              args.gamma, args.gae_lambda)

            # PPO update (appendix Eqs. (4)-(5)): clipped surrogate, value regression, no entropy bonus
            b_obs, b_actions = obs_buf.reshape(-1, obs_dim), actions_buf.reshape(-1, action_dim)
            b_logprobs, b_advantages, b_returns, b_values = (
                x.reshape(-1) for x in (logprobs_buf, advantages, returns, values_buf))
            clip = clip_range(args.clip_coef, progress.global_step, args.total_timesteps)
            epochs = args.update_epochs if progress.reward_ready else args.unsup_update_epochs
            losses = ppo_update(b_obs, b_actions, b_logprobs, b_advantages, b_returns, actor, critic, optimizer, epochs,
                                torch.tensor(clip, device=device), args, loss_fn)  # a tensor: compiled once
            progress.counts["ppo_epochs"] += epochs
            losses["explained_variance"] = 1 - (b_returns - b_values).var() / b_returns.var().clamp(1e-8)
            writer.add_scalar("charts/clip_range", clip, progress.global_step)
            for name, value in losses.items():
                writer.add_scalar(f"losses/{name}", float(value), progress.global_step)
            writer.add_scalar("charts/SPS", progress.global_step / (time.time() - start_time), progress.global_step)

            if progress.global_step >= min((len(progress.eval_rows) + 1) * args.eval_every, args.total_timesteps):
                if args.capture_video:
                    eval_env.name_prefix = f"step_{progress.global_step}"
                seeds = [episode_seed(args.seed, EVAL_STREAM, len(progress.eval_rows) * args.eval_episodes + j)
                         for j in range(args.eval_episodes)]
                judged = reward_model if progress.reward_ready and not args.ground_truth_reward else None
                result = evaluate(actor, obs_stats, judged, eval_env, seeds, device)
                if args.capture_video and eval_env.recording:  # write the video now, not at the next reset
                    eval_env.stop_recording()
                progress.eval_rows.append({"step": progress.global_step, **result, "feedback": progress.feedback_used,
                                           "wall_time": round(time.time() - start_time, 1),
                                           "overhead_seconds": round(progress.overhead_seconds, 1)})
                save_file(eval_path, eval_csv(progress.eval_rows))
                for name in ("episode_return", "success_rate", "reward_correlation"):
                    writer.add_scalar(f"eval/{name}", result[name], progress.global_step)
            if time.time() - last_print > 10 or progress.global_step >= args.total_timesteps:
                last_print, left = time.time(), args.total_timesteps - progress.global_step
                sps, last_eval = progress.global_step / (last_print - start_time), (progress.eval_rows or [{}])[-1]
                print(f"step {progress.global_step}/{args.total_timesteps} | {sps:.0f} SPS | ETA {left / sps / 60:.1f} "
                      f"min | last eval return {last_eval.get('episode_return', math.nan):.1f} | labels "
                      f"{progress.feedback_used}/{args.max_feedback}", flush=True)

            if args.checkpoint_every and progress.global_step >= progress.next_checkpoint_step or stop:
                every = args.checkpoint_every or 1
                progress.next_checkpoint_step = (progress.global_step // every + 1) * every
                save_start, data = time.perf_counter(), io.BytesIO()
                torch.save(checkpoint_state(), data)  # in memory first: a full disk is then a plain OSError
                save_file(checkpoint_path, data.getvalue())
                size_mib = os.path.getsize(checkpoint_path) / 2**20
                print(f"step {progress.global_step}: checkpoint.pt saved ({size_mib:.1f} MiB in "
                      f"{time.perf_counter() - save_start:.1f} s)", flush=True)
            if stop:
                print(f"{signal.Signals(stop[0]).name}: checkpoint saved at step {progress.global_step}; continue with "
                      f"--resume {output_dir}", flush=True)
                writer.close()
                sys.exit(128 + stop[0])
    except FloatingPointError as error:  # a NaN or infinity in a loss or from the environment
        # Mid-rollout the envs have moved past the last checkpoint, which stays as it is. The state at the failure
        # (finite: the checks come before the optimizer steps) goes to a file of its own, to inspect
        torch.save(checkpoint_state(), os.path.join(output_dir, "checkpoint_nonfinite.pt"))
        last = f"its last checkpoint is intact in {checkpoint_path}" if os.path.exists(checkpoint_path) else \
            "no checkpoint was due yet"
        fail(f"{error} at step {progress.global_step}; run stopped, {last}, the state at the failure is in "
             f"{output_dir}/checkpoint_nonfinite.pt and the labels in {output_dir}/labels", code=3)
    except OSError as error:
        fail(f"writing to {output_dir!r} failed at step {progress.global_step} ({error.strerror or error}); the last "
             "checkpoint there is intact", code=1)

    print(f"done: {progress.counts} (updates_on_learned_reward: the true reward with --ground-truth-reward), "
          f"{progress.sessions_done} feedback sessions, {progress.feedback_used} queries; outputs in {output_dir}")
    torch.save({"actor": actor.state_dict(), "critic": critic.state_dict(), "reward_model": reward_model.state_dict(),
                "obs_mean": torch.tensor(obs_stats.mean), "obs_var": torch.tensor(obs_stats.var)},
               os.path.join(output_dir, "final_model.pt"))
    writer.close()
