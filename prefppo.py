# PrefPPO (Christiano et al. 2017, with PPO) as benchmarked by B-Pref (Lee et al. 2021);
# docs/prefppo.md
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
    """if toggled, torch.compile the PPO minibatch loss (faster after a first compilation of about
    10 s)"""
    output_dir: str | None = None
    """where the run's files go (default: runs/<run name>)"""
    checkpoint_every: int = 50000
    """environment steps between checkpoints, taken after a rollout (0 = only on SIGTERM/SIGINT)"""
    resume: str | None = None
    """continue the run in this directory from its checkpoint, with its saved configuration"""
    labels_from: str | None = None
    """seed the preference dataset with an earlier run's labels (its directory, labels/ or one .npz)
    """

    # Algorithm specific arguments; None = the task's preset (PRESETS below)
    env_id: str = "walker-walk"
    """DMC `domain-task`, Meta-World v3 task name (with or without -v3), or a Gymnasium id"""
    total_timesteps: int | None = None
    """total environment steps (all environments together)"""
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
    """PPO epochs over each rollout of unsupervised pre-training (reference code: unsuper_n_epochs
    50)"""
    minibatch_size: int | None = None
    """PPO minibatch size"""
    gamma: float = 0.99
    """discount"""
    gae_lambda: float | None = None
    """GAE lambda"""
    bootstrap_time_limits: bool = True
    """add gamma V(last state) where an episode ends by its time limit (docs/differences.md 16);
    --no-bootstrap-time-limits: every end is terminal (reference code: its vendored SB3)"""
    use_sde: bool = True
    """generalized state-dependent exploration, gSDE (reference code: use_sde 1); --no-use-sde: a
    Gaussian"""
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
    reward_input_norm: bool = True
    """the reward model sees observations standardised by D's states, clipped to +-10 (reference
    code: VecNormalize'd observations, clip 10; docs/differences.md item 17)"""
    stale_reward_inputs: bool = False
    """the reference's way, for an ablation (defect 7): queries hold the normalised observations of
    their step, r_hat sees the current ones (labels/ too; implies --no-reward-input-norm)"""
    candidate_multiplier: int = 10
    """candidate pairs per query for the uncertainty and coverage samplers"""
    query_recent_episodes: int = 0
    """segments come from the last N complete episodes (0 = all so far, pre-training's too:
    reference code)"""


# Paper appendix, table of PrefPPO hyperparameters (docs/prefppo.md lists the values the paper
# leaves open); reward_epochs: the reference's re_update (train_PrefPPO.py default, DMC scripts:
# 100; Meta-World scripts: --re-update 50)
DMC_PRESET = dict(total_timesteps=4_000_000, max_feedback=1000, feedback_per_session=100,
                  feedback_every=32_000, segment_len=50, learning_rate=5e-5, num_envs=32,
                  num_steps=500, minibatch_size=64, gae_lambda=0.92, reward_epochs=100)
METAWORLD_PRESET = dict(total_timesteps=3_000_000, max_feedback=10_000, feedback_per_session=100,
                        feedback_every=16_000, segment_len=25, learning_rate=3e-4, num_envs=8,
                        num_steps=250, minibatch_size=128, gae_lambda=0.92, reward_epochs=50)
GYM_PRESET = dict(DMC_PRESET, learning_rate=3e-4, num_envs=8, num_steps=256, minibatch_size=64,
                  gae_lambda=0.95)
PRESETS = {"walker-walk": DMC_PRESET, "button-press": METAWORLD_PRESET,
           "sweep-into": dict(METAWORLD_PRESET, num_envs=32, minibatch_size=256),
           "quadruped-walk": dict(DMC_PRESET, num_envs=16, minibatch_size=128, gae_lambda=0.9)}
CPU_SCALE = "python prefppo.py --env-id walker-walk --total-timesteps 1000000"  # docs/results.md


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
    """Independent streams from one run seed: query sampler, teacher."""
    return np.random.SeedSequence(seed).spawn(2)


def episode_seed(run_seed: int, stream: int, episode: int) -> int:
    """The reset seed of an episode of a stream, drawn from SeedSequence([run_seed, stream,
    episode]): any episode can be played again alone, and runs with different seeds share no
    episode."""
    return int(np.random.SeedSequence([run_seed, stream, episode]).generate_state(1)[0])


# Networks
def mlp(in_dim: int, out_dim: int, hidden_dim: int, num_layers: int, activation=nn.Tanh):
    layers = []
    for i in range(num_layers):
        layers += [nn.Linear(hidden_dim if i else in_dim, hidden_dim), activation()]
    return nn.Sequential(*layers, nn.Linear(hidden_dim if num_layers else in_dim, out_dim))


def orthogonal_init(module: nn.Module, gain: float) -> nn.Module:
    """Orthogonal weights with this gain, zero biases (reference code: SB3's ActorCriticPolicy init,
    gain sqrt(2) for hidden layers, 0.01 for the policy output, 1 for the value output)."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)
    return module


def sde_std(latent: torch.Tensor, log_std: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """gSDE's action std (reference code: SB3's StateDependentNoiseDistribution): latent @ W, W_ij ~
    N(0, exp(log_std_ij)^2), is Gaussian with variance sum_i latent_i^2 exp(log_std_ij)^2 for action
    j (+ SB3's eps). latent (batch, hidden), log_std (hidden, action) -> (batch, action)."""
    return torch.sqrt(latent**2 @ log_std.exp() ** 2 + eps)


class Actor(nn.Module):
    """The reference code's PPO policy (SB3's ActorCriticPolicy): a tanh MLP whose last hidden
    features, the latent, feed a linear mean; actions are clipped to [-1, 1] in the env. gSDE
    (docs): env n acts mean + latent @ W_n, W_n with entries N(0, exp(log_std)^2), i.e. N(mean,
    sde_std); without gSDE one log std per action. log std starts at 0."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers, use_sde: bool):
        super().__init__()
        self.policy = mlp(obs_dim, action_dim, hidden_dim, num_layers)
        orthogonal_init(self.policy, math.sqrt(2))
        orthogonal_init(self.policy[-1], 0.01)
        self.use_sde = use_sde
        log_std_shape = (hidden_dim, action_dim) if use_sde else (action_dim,)
        self.log_std = nn.Parameter(torch.zeros(log_std_shape))
        self.exploration = None  # gSDE: the matrices W_n in use, (envs, hidden, action)

    def mean(self, obs):
        return self.policy(obs)

    def distribution(self, obs) -> tuple[torch.distributions.Normal, torch.Tensor]:
        """pi(. | s) and the latent."""
        latent = self.policy[:-1](obs)
        mean = self.policy[-1](latent)
        if self.use_sde:
            std = sde_std(latent.detach(), self.log_std)
        else:
            std = self.log_std.exp().expand_as(mean)
        return torch.distributions.Normal(mean, std, validate_args=False), latent

    def sample(self, obs, step: int, sde_freq: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Actions and log-probabilities at step `step` of a rollout. gSDE draws each env's W_n at
        the rollout's first step and every sde_freq steps after (reference code:
        collect_rollouts)."""
        distribution, latent = self.distribution(obs)
        if not self.use_sde:
            action = distribution.sample()
        else:
            if step % sde_freq == 0:
                noise = torch.randn(len(obs), *self.log_std.shape, device=obs.device)
                self.exploration = self.log_std.exp() * noise
            noise = torch.bmm(latent.detach().unsqueeze(1), self.exploration).squeeze(1)
            action = distribution.loc + noise
        return action, distribution.log_prob(action).sum(-1)


def mean_policy(actor: Actor, obs_stats, device) -> callable:
    """The policy evaluated: an observation -> the mean action (of the normalised observation),
    clipped as the env clips it, a tensor on the device."""
    def policy(obs):
        return actor.mean(torch.as_tensor(obs_stats.normalize(obs), device=device)).clamp(-1, 1)

    return policy


def make_critic(obs_dim: int, hidden_dim: int, num_layers: int) -> nn.Sequential:
    """V(s): a tanh MLP of its own (reference code: separate pi and vf layers), SB3's init."""
    critic = orthogonal_init(mlp(obs_dim, 1, hidden_dim, num_layers), math.sqrt(2))
    orthogonal_init(critic[-1], 1.0)
    return critic


def reset_value_head(critic: nn.Sequential):
    """The value reset after the first reward update (reference code: reset_value): only the output
    layer is drawn again; the hidden layers, and the optimizer with its moments, are kept."""
    orthogonal_init(critic[-1], 1.0)


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


# Algorithm: the math a reader must trust (each unit-tested), the kNN reward, reward learning
def clip_range(clip_coef: float, global_step: int, total_timesteps: int) -> float:
    """The clip range of the update after the rollout that reached global_step (reference code:
    SB3's linear_schedule of progress_remaining = 1 - steps done / total): clip_coef, then down
    to 0."""
    return clip_coef * max(0.0, 1.0 - global_step / total_timesteps)


def ppo_policy_loss(log_prob, old_log_prob, advantages, clip: float) -> tuple:
    """Appendix Eq. (4), PPO's clipped surrogate: mean of max(-A ratio, -A clip(ratio, 1 - clip,
    1 + clip)), ratio = pi(a|s) / pi_old(a|s). Returns (loss, ratio)."""
    ratio = (log_prob - old_log_prob).exp()
    clipped = ratio.clamp(1 - clip, 1 + clip)
    return torch.max(-advantages * ratio, -advantages * clipped).mean(), ratio


def ppo_value_loss(values: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
    """Appendix Eq. (5): the MSE of V against the GAE returns, no clipping (reference code: SB3's
    PPO, which weighs it by vf_coef 0.5 in the total loss)."""
    return F.mse_loss(values, returns)


def optimize(optimizer, loss: torch.Tensor, max_grad_norm: float | None = None):
    """One gradient step of this optimizer's parameters only, the gradients clipped to
    max_grad_norm."""
    optimizer.zero_grad()
    params = [param for group in optimizer.param_groups for param in group["params"]]
    loss.backward(inputs=params)
    if max_grad_norm is not None:
        nn.utils.clip_grad_norm_(params, max_grad_norm)
    optimizer.step()


def adam(params, lr: float, eps: float = 1e-8) -> torch.optim.Adam:
    """Adam with fused kernels (one kernel a step): the same update, up to float rounding."""
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)


def ppo_loss(actor, critic, obs, actions, old_logprobs, advantages, returns, clip, args) -> tuple:
    """Appendix Eqs. (4)-(5) on a minibatch: the clipped surrogate + vf_coef x the value loss -
    ent_coef x the entropy, advantages normalised per minibatch; and the minibatch's statistics, on
    the device (no host sync)."""
    distribution, _ = actor.distribution(obs)
    adv = advantages
    if len(obs) > 1:
        adv = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    entropy = distribution.entropy().sum(-1).mean()
    log_prob = distribution.log_prob(actions).sum(-1)
    policy_loss, ratio = ppo_policy_loss(log_prob, old_logprobs, adv, clip)
    value_loss = ppo_value_loss(critic(obs)[:, 0], returns)
    stats = {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
             "approx_kl": ((ratio - 1) - ratio.log()).mean(),
             "clipfrac": ((ratio - 1).abs() > clip).float().mean()}
    return policy_loss + args.vf_coef * value_loss - args.ent_coef * entropy, stats


def ppo_update(obs, actions, logprobs, advantages, returns, actor, critic, optimizer, epochs, clip,
               args, loss_fn=ppo_loss) -> dict:
    """PPO's update of a rollout: `epochs` passes over it in shuffled minibatches, one step of
    loss_fn (ppo_loss, compiled with --compile) each. The last minibatch's statistics, the clip
    fraction over all of them."""
    clip_fractions = []
    for _ in range(epochs):
        # the rollout shuffled once an epoch, cut in minibatches
        order = torch.randperm(len(obs), device=obs.device)
        rollout = (obs, actions, logprobs, advantages, returns)
        shuffled = [x[order].split(args.minibatch_size) for x in rollout]
        for minibatch in zip(*shuffled):
            loss, stats = loss_fn(actor, critic, *minibatch, clip, args)
            optimize(optimizer, loss, args.max_grad_norm)
            clip_fractions.append(stats["clipfrac"])
    stats = {name: value.detach() for name, value in stats.items()}
    return stats | {"clipfrac": torch.stack(clip_fractions).mean()}


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


def time_limit_bootstrap(next_values, terminated, truncated, gamma, bootstrap: bool):
    """gamma * V(final observation) at the steps that end an episode by its time limit only, for
    compute_gae's rewards; zero everywhere with bootstrap False (the reference's SB3: terminal)."""
    truncated_only = torch.as_tensor(truncated & ~terminated & bootstrap, device=next_values.device)
    return gamma * next_values * truncated_only


def knn_distance(states: torch.Tensor, reference: torch.Tensor, k: int) -> torch.Tensor:
    """Eq. (8) without the log (docs): distance to the k-th nearest neighbour in `reference`, not
    counting the state itself (its zero distance): the (k+1)-th smallest. Memory: states x
    reference distances."""
    distances = torch.cdist(states, reference)
    # topk: ~5x faster than kthvalue on a 10K-state buffer
    nearest = distances.topk(min(k + 1, len(reference)), dim=1, largest=False).values
    return nearest[:, -1:].contiguous()


class RunningMeanStd:
    """Running mean and variance (Chan et al.'s parallel update), for observations and the kNN
    reward. Normalised values are clipped to [-10, 10]; segments for the teacher stay raw."""

    def __init__(self, dim):
        self.mean = np.zeros(dim)
        self.var = np.ones(dim)
        self.count = 1e-4

    def update(self, x: np.ndarray):
        batch_mean = x.mean(0)
        batch_var = x.var(0)
        batch_count = len(x)
        total = self.count + batch_count
        delta = batch_mean - self.mean
        m2 = self.var * self.count + batch_var * batch_count
        m2 += delta**2 * self.count * batch_count / total
        self.mean = self.mean + delta * batch_count / total
        self.var = m2 / total
        self.count = total

    def normalize(self, x: np.ndarray) -> np.ndarray:
        return np.clip((x - self.mean) / np.sqrt(self.var + 1e-8), -10, 10).astype(np.float32)


class KnnStateEntropy:
    """Algorithm 2's r_int(s_t): the distance from s_t to its k-th nearest neighbour among every
    state of pre-training so far, this step's included (reference code: a growing buffer of raw
    observations on the device), divided by a running standard deviation of these distances."""

    def __init__(self, obs_dim: int, k: int, device: torch.device):
        self.k = k
        self.states = torch.zeros(0, obs_dim, device=device)
        self.stats = RunningMeanStd(1)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        """Adds this step's states (one per env) to the buffer; returns their normalised rewards."""
        self.states = torch.cat([self.states, states])
        distance = knn_distance(states, self.states, self.k)[:, 0]
        self.stats.update(distance.cpu().numpy()[:, None])
        return distance / math.sqrt(self.stats.var[0] + 1e-8)

    def state_dict(self) -> dict:
        return {"states": self.states.cpu(), "stats": tree_map(plain, vars(self.stats))}

    def load_state_dict(self, state: dict):
        self.states = state["states"].to(self.states.device)
        vars(self.stats).update(tree_map(unplain, state["stats"]))


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
                     "capture_video", "compile")
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
    args.reward_input_norm &= not args.stale_reward_inputs
    return args


def check_args(args: Args, episode_len: int):
    """ValueError naming the first number out of its range (tyro checks types and choices)."""
    a = args
    rollout = a.num_envs * a.num_steps
    rules = [
        ("seed", a.seed >= 0, ">= 0"),
        ("teacher_beta", a.teacher_beta >= 0, ">= 0 (inf = rational)"),
        *[(n, 0 < getattr(a, n) <= 1, "in (0, 1]") for n in ("teacher_gamma", "gamma")],
        *[(n, 0 <= getattr(a, n) <= 1, "in [0, 1]")
          for n in ("teacher_eps_mistake", "teacher_eps_skip", "teacher_eps_equal", "gae_lambda")],
        *[(n, getattr(a, n) >= 1, ">= 1")
          for n in ("max_feedback", "feedback_every", "hidden_dim", "num_layers", "num_envs",
                    "num_steps", "update_epochs", "unsup_update_epochs", "sde_freq",
                    "reward_batch_size", "reward_ensemble_size", "eval_every", "eval_episodes",
                    "knn_k", "candidate_multiplier", "reward_epochs")],
        *[(n, getattr(a, n) >= 0, ">= 0")
          for n in ("unsup_steps", "ent_coef", "vf_coef", "query_recent_episodes",
                    "checkpoint_every")],
        *[(n, getattr(a, n) > 0, "> 0")
          for n in ("learning_rate", "reward_lr", "clip_coef", "max_grad_norm")],
        ("label_smoothing", 0 <= a.label_smoothing < 1, "in [0, 1)"),
        ("feedback_per_session", 1 <= a.feedback_per_session <= a.max_feedback,
         f"in [1, --max-feedback={a.max_feedback}]"),
        ("segment_len", 1 <= a.segment_len <= episode_len,
         f"in [1, {episode_len}] (the episode length)"),
        ("minibatch_size", 1 <= a.minibatch_size <= rollout,
         f"in [1, --num-envs x --num-steps = {rollout}]"),
        ("total_timesteps", a.total_timesteps > a.unsup_steps and a.total_timesteps >= rollout,
         f"> --unsup-steps ({a.unsup_steps}) and >= one rollout ({rollout})"),
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


def evaluate(policy, reward_model, env, seeds: list[int], device, reward_obs=None) -> dict:
    """Episodes of policy(observation) -> action (one per reset seed) with the true reward (B-Pref's
    metric), Meta-World success (at any step), and the Pearson correlation of learned and true
    per-step rewards (r_hat of reward_obs(observation), the observation itself by default)."""
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
                    reward_input = obs if reward_obs is None else reward_obs(obs)
                    obs_action = torch.cat([torch.as_tensor(reward_input, device=device), action])
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


def evaluation(args, progress, policy, reward_model, eval_env, writer, start_time: float, device,
               reward_obs=None):
    """The next eval_episodes evaluation episodes: a row of eval.csv (rewritten whole), TensorBoard.
    reward_obs: what r_hat sees of an observation (evaluate)."""
    if args.capture_video:
        eval_env.name_prefix = f"step_{progress.global_step}"
    first = len(progress.eval_rows) * args.eval_episodes
    seeds = [episode_seed(args.seed, EVAL_STREAM, first + j) for j in range(args.eval_episodes)]
    learned_reward = reward_model if progress.pretrained and not args.ground_truth_reward else None
    result = evaluate(policy, learned_reward, eval_env, seeds, device, reward_obs)
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


def restart_envs(envs, progress, seed: int) -> np.ndarray:
    """Each env at the start of its running episode (that episode's seed), then that episode's
    actions so far again: MuJoCo is deterministic, so a resumed env is where it was."""
    raw_obs = []
    for i, env in enumerate(envs):
        # episode j of env i: number j * num_envs + i of the stream
        episode = progress.episodes[i] * len(envs) + i
        obs, _ = env.reset(seed=episode_seed(seed, TRAIN_STREAM, episode))
        for action in progress.running_episodes[i][1]:
            obs = env.step(action)[0]
        raw_obs.append(obs)
    return np.stack(raw_obs)


def step_envs(envs, actions: np.ndarray, raw_obs: np.ndarray, pool_obs: np.ndarray, progress,
              episodes, writer, args, step: int) -> tuple:
    """One step of every env; an env whose episode ends hands it to the query pool (pool_obs: the
    observations it keeps) and is reset with its next episode's seed. Returns the next observations,
    the observations the step reached (an ended episode's real last state), true rewards,
    terminations and truncations. `step`: the environment steps done once this one is (an ended
    episode's step in TensorBoard)."""
    next_raw_obs = raw_obs.copy()
    final_obs = raw_obs.copy()
    true_reward = np.zeros(len(envs))
    terminated = np.zeros(len(envs), bool)
    truncated = np.zeros(len(envs), bool)
    for i, env in enumerate(envs):
        final_obs[i], true_reward[i], terminated[i], truncated[i], _ = env.step(actions[i])
        if not (np.isfinite(true_reward[i]) and np.isfinite(final_obs[i]).all()):
            raise FloatingPointError(f"non-finite reward ({true_reward[i]}) or observation from "
                                     "the environment")
        running = progress.running_episodes[i]
        for part, value in zip(running, (pool_obs[i], actions[i], true_reward[i])):
            part.append(value)
        next_raw_obs[i] = final_obs[i]
        if terminated[i] or truncated[i]:
            # the episode's arrays and its reset seed (--teacher human replays it)
            seed = episode_seed(args.seed, TRAIN_STREAM, progress.episodes[i] * len(envs) + i)
            episodes.append((*(np.array(part, np.float32) for part in running), seed))
            episode_return = float(sum(running[2]))
            progress.recent_returns = (progress.recent_returns + [episode_return])[-100:]
            writer.add_scalar("charts/episodic_return", episode_return, step)
            progress.running_episodes[i] = ([], [], [])
            progress.episodes[i] += 1
            # episode j of env i: number j * num_envs + i of the stream
            seed = episode_seed(args.seed, TRAIN_STREAM, progress.episodes[i] * len(envs) + i)
            next_raw_obs[i] = env.reset(seed=seed)[0]
    return next_raw_obs, final_obs, true_reward, terminated, truncated


@dataclass
class Progress:
    """What the main loop carries besides networks, optimizers and buffers; a checkpoint saves every
    field."""

    global_step: int = 0
    episodes: list = field(default_factory=list)  # env i runs its episode number episodes[i]
    running_episodes: list = field(default_factory=list)  # env i's: observations, actions, rewards
    recent_returns: list = field(default_factory=list)  # true returns of the last 100 episodes
    sessions_done: int = 0
    feedback_used: int = 0
    next_feedback_step: int = 0
    next_checkpoint_step: int = 0
    eval_rows: list = field(default_factory=list)  # eval.csv
    pretrained: bool = False  # pre-training is over: PPO learns from r_hat (or the true reward)
    # PrefPPO's own parts: kNN reward, queries, reward learning, r_hat
    overhead_seconds: float = 0.0
    wall_time: float = 0.0
    counts: dict = field(default_factory=lambda: dict.fromkeys(  # how often each phase ran
        ("updates_on_knn_reward", "updates_on_learned_reward", "value_resets", "ppo_epochs"), 0))

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
    if device.type == "cpu" and args.total_timesteps > 1_000_000:
        print("note: runs of this length train for days on a CPU; use a GPU, or the CPU scale of "
              f"docs/results.md: {CPU_SCALE}", flush=True)

    # Seeding: numpy (query sampler and teacher: independent streams), torch (networks, actions,
    # minibatches), every reset (episode_seed): an env is a function of its seed and actions
    sampler_seed, teacher_seed = numpy_seeds(args.seed)
    rng = np.random.default_rng(sampler_seed)
    torch.manual_seed(args.seed)
    torch.set_flush_denormal(True)  # MuJoCo's tiny float32 velocities: denormals, slow on a CPU
    envs = [env] + [make_env(args.env_id)[0] for _ in range(args.num_envs - 1)]
    actor = Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers, args.use_sde).to(device)
    critic = make_critic(obs_dim, args.hidden_dim, args.num_layers).to(device)
    # one Adam over both networks, as SB3's policy (Adam works per parameter: the same as two)
    optimizer = adam([*actor.parameters(), *critic.parameters()], args.learning_rate, eps=1e-5)
    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = adam(reward_model.parameters(), args.reward_lr)
    obs_stats = RunningMeanStd(obs_dim)
    knn_reward = KnnStateEntropy(obs_dim, args.knn_k, device)
    loss_fn = torch.compile(ppo_loss) if args.compile else ppo_loss  # the eager one: the reference
    teacher_fields = {name: getattr(args, f"teacher_{name}") for name in TEACHER_FIELDS}
    teacher_name = "oracle" if args.teacher == "human" else args.teacher  # human: not used
    teacher = make_teacher(teacher_name, seed=teacher_seed, **teacher_fields)
    # Feedback sessions at rollout ends, from the end of pre-training, every feedback_every steps
    rollout = args.num_envs * args.num_steps
    steps = session_steps(args.unsup_steps, args.feedback_every, args.total_timesteps - 1, rollout)
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session,
                                   steps, args.total_timesteps)
    planned = planned_labels(session_sizes, args.unsup_steps, args.feedback_every,
                             args.total_timesteps - 1, rollout)
    if planned < args.max_feedback and not args.ground_truth_reward:
        print(f"note: only {planned} of the {args.max_feedback} labels of --max-feedback fit in "
              f"{args.total_timesteps} steps (sessions from step {args.unsup_steps}, every "
              f"{args.feedback_every} steps, at rollout ends)")
    preferences = labelled_dataset(imported_labels, args, obs_dim, action_dim, device)
    # The query pool: the last query_recent_episodes complete episodes (reference code: all)
    episodes = deque(maxlen=args.query_recent_episodes or None)
    progress = Progress(episodes=[0] * args.num_envs,
                        running_episodes=[([], [], []) for _ in range(args.num_envs)],
                        next_feedback_step=args.unsup_steps,
                        next_checkpoint_step=args.checkpoint_every)
    parts = {"progress": progress, "actor": actor, "critic": critic, "reward_model": reward_model,
             "optimizer": optimizer, "reward_optimizer": reward_optimizer, "teacher": teacher,
             "obs_stats": obs_stats, "knn_reward": knn_reward, "preferences": preferences,
             "rng": rng, "episodes": episodes}
    checkpoint_path = os.path.join(args.output_dir, "checkpoint.pt")
    if args.resume:  # every part back (weights_only: a shared run directory runs no code)
        restore(parts, torch.load(checkpoint_path, "cpu", weights_only=True), device)
        print(f"resuming from the checkpoint at step {progress.global_step}")
        if progress.global_step >= args.total_timesteps:
            fail(f"the run in {args.output_dir!r} has already finished "
                 f"({progress.global_step} steps)")
        set_labels_aside(args.output_dir, progress)
    raw_obs = restart_envs(envs, progress, args.seed)
    if args.capture_video:  # the first episode of each evaluation: videos/step_N-episode-M.mp4
        eval_env = gym.wrappers.RecordVideo(
            eval_env, os.path.join(args.output_dir, "videos"),
            episode_trigger=lambda episode: episode % args.eval_episodes == 0)
    # The rollout, per step and env: raw and normalised observations, sampled and executed (clipped)
    # actions, log-probabilities, values, V of the state after the step, the kNN and the true
    # reward, gamma V(final state) at truncations, episode ends
    shape = (args.num_steps, args.num_envs)
    raw_obs_buf, obs_buf = torch.zeros(2, *shape, obs_dim, device=device)
    actions_buf, env_actions_buf = torch.zeros(2, *shape, action_dim, device=device)
    logprobs_buf, values_buf, next_values_buf, intrinsic_buf, true_rewards_buf, bootstrap_buf, \
        dones_buf = torch.zeros(7, *shape, device=device)
    stop = []  # SIGTERM (a time limit) or SIGINT (Ctrl-C): checkpoint after this rollout, then exit
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    signal.signal(signal.SIGINT, lambda signum, frame: stop.append(signum))
    start_time = time.time() - progress.wall_time
    last_print = start_time

    # Main loop: Algorithm 3 with PPO, after Algorithm 2 (pre-training) for the first unsup_steps
    try:
        save_file(os.path.join(args.output_dir, "eval.csv"), eval_csv(progress.eval_rows))
        while progress.global_step < args.total_timesteps:
            global_step = progress.global_step
            progress.pretrained |= args.ground_truth_reward and global_step >= args.unsup_steps
            if (not args.ground_truth_reward and global_step >= progress.next_feedback_step
                    and progress.sessions_done < len(session_sizes)
                    and any(len(episode[0]) >= args.segment_len for episode in episodes)):
                if args.teacher == "human":  # a checkpoint first: --resume asks this session again
                    progress.wall_time = time.time() - start_time
                    save_checkpoint(checkpoint_path, snapshot(parts), global_step)
                with progress.overhead():
                    size = int(session_sizes[progress.sessions_done])
                    n_labels = feedback_session(args, progress, size, episodes, preferences,
                                                reward_model, reward_optimizer, teacher, rng,
                                                writer, episode_len)
                progress.pretrained |= n_labels > 0
            if progress.pretrained and progress.counts["value_resets"] == 0:
                reset_value_head(critic)  # the end of pre-training: a new value head
                progress.counts["value_resets"] += 1

            # Rollout of num_steps in every env
            for t in range(args.num_steps):
                obs_stats.update(raw_obs)
                obs = torch.as_tensor(obs_stats.normalize(raw_obs), device=device)
                if not progress.pretrained:  # pre-training: r_int(s_t) of Algorithm 2
                    with progress.overhead():
                        intrinsic_buf[t] = knn_reward(torch.as_tensor(raw_obs, device=device))
                with torch.no_grad():
                    action, logprobs_buf[t] = actor.sample(obs, t, args.sde_freq)
                    values_buf[t] = critic(obs)[:, 0]
                env_action = action.clamp(-1, 1)  # executed and judged; PPO's ratio uses `action`
                pool_obs = obs.cpu().numpy() if args.stale_reward_inputs else raw_obs
                next_raw_obs, final_obs, true_reward, terminated, truncated = step_envs(
                    envs, env_action.cpu().numpy(), raw_obs, pool_obs, progress, episodes, writer,
                    args, global_step + (t + 1) * args.num_envs)
                raw_obs_buf[t] = torch.as_tensor(raw_obs)
                obs_buf[t] = obs
                actions_buf[t] = action
                env_actions_buf[t] = env_action
                true_rewards_buf[t] = torch.as_tensor(true_reward)
                dones_buf[t] = torch.as_tensor(terminated | truncated)
                # V of the state after this step: at a truncation, bootstrapped
                with torch.no_grad():
                    final = torch.as_tensor(obs_stats.normalize(final_obs), device=device)
                    next_values_buf[t] = critic(final)[:, 0]
                bootstrap_buf[t] = time_limit_bootstrap(next_values_buf[t], terminated, truncated,
                                                        args.gamma, args.bootstrap_time_limits)
                raw_obs = next_raw_obs
            progress.global_step += rollout

            # The reward PPO maximises: kNN state entropy (pre-training), r_hat or the true reward
            reward_kind = "learned" if progress.pretrained else "knn"
            progress.counts[f"updates_on_{reward_kind}_reward"] += 1
            rewards = true_rewards_buf if progress.pretrained else intrinsic_buf
            if progress.pretrained and not args.ground_truth_reward:
                with progress.overhead(), torch.no_grad():  # r_hat(s, a): the ensemble mean
                    reward_obs = obs_buf if args.stale_reward_inputs else raw_obs_buf
                    obs_actions = torch.cat([reward_obs, env_actions_buf], dim=-1)
                    rewards = reward_model(obs_actions).mean(0)[..., 0]
                    pair = torch.stack([rewards.flatten(), true_rewards_buf.flatten()])
                    writer.add_scalar("reward/rollout_correlation", torch.corrcoef(pair)[0, 1],
                                      progress.global_step)
            advantages, returns = compute_gae(rewards + bootstrap_buf, values_buf, next_values_buf,
                                              dones_buf, args.gamma, args.gae_lambda)

            # PPO update (appendix Eqs. (4)-(5)): clipped surrogate, value regression
            b_obs = obs_buf.reshape(-1, obs_dim)
            b_actions = actions_buf.reshape(-1, action_dim)
            b_returns = returns.reshape(-1)
            b_values = values_buf.reshape(-1)
            clip = clip_range(args.clip_coef, progress.global_step, args.total_timesteps)
            epochs = args.update_epochs if progress.pretrained else args.unsup_update_epochs
            losses = ppo_update(b_obs, b_actions, logprobs_buf.reshape(-1), advantages.reshape(-1),
                                b_returns, actor, critic, optimizer, epochs,
                                torch.tensor(clip, device=device), args, loss_fn)  # compiled once
            progress.counts["ppo_epochs"] += epochs
            explained = 1 - (b_returns - b_values).var() / b_returns.var().clamp(1e-8)
            losses["explained_variance"] = explained
            writer.add_scalar("charts/clip_range", clip, progress.global_step)
            log_losses(writer, losses, progress.global_step)

            next_eval = min((len(progress.eval_rows) + 1) * args.eval_every, args.total_timesteps)
            if progress.global_step >= next_eval:
                policy = mean_policy(actor, obs_stats, device)
                reward_obs = obs_stats.normalize if args.stale_reward_inputs else None
                evaluation(args, progress, policy, reward_model, eval_env, writer, start_time,
                           device, reward_obs)
            if time.time() - last_print > 10 or progress.global_step >= args.total_timesteps:
                last_print = time.time()
                print_progress(args, progress, start_time, writer)
            checkpoint_due = progress.global_step >= progress.next_checkpoint_step
            if args.checkpoint_every and checkpoint_due or stop:
                every = args.checkpoint_every or 1
                progress.next_checkpoint_step = (progress.global_step // every + 1) * every
                progress.wall_time = time.time() - start_time
                save_checkpoint(checkpoint_path, snapshot(parts), progress.global_step)
            if stop:
                print(f"{signal.Signals(stop[0]).name}: checkpoint saved at step "
                      f"{progress.global_step}; continue with --resume {args.output_dir}",
                      flush=True)
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
                   "reward_model": reward_model.state_dict(),
                   "obs_mean": torch.tensor(obs_stats.mean), "obs_var": torch.tensor(obs_stats.var)}
    torch.save(final_model, os.path.join(args.output_dir, "final_model.pt"))
    eval_env.close()
    writer.close()
