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
    """segments come from the last N complete episodes (reference code: 100; 0 = all so far)"""
    critic_reset_updates: int = 100
    """SAC updates on relabelled data right after the critic reset of the first reward update"""


# Paper appendix, Table of PEBBLE hyperparameters (sources of the others: docs/differences.md). Meta-World: feedback
# every 4950 steps, not the paper's 5000, so that all 200 sessions (10,000 labels) fit in 1M steps (planned_labels);
# segments of 50, not the table's 25: the reference's Meta-World scripts never set it, so its runs used 50
DMC_PRESET = dict(total_timesteps=500_000, max_feedback=1000, feedback_per_session=100, feedback_every=20_000,
                  segment_len=50, hidden_dim=1024, num_layers=2, batch_size=1024, learning_rate=5e-4, reward_epochs=50)
METAWORLD_PRESET = dict(total_timesteps=1_000_000, max_feedback=10_000, feedback_per_session=50, feedback_every=4950,
                        segment_len=50, hidden_dim=256, num_layers=3, batch_size=512, learning_rate=3e-4,
                        reward_epochs=10)
GYM_PRESET = dict(DMC_PRESET, hidden_dim=256, num_layers=2, batch_size=256, learning_rate=3e-4)
PRESETS = {"walker-walk": DMC_PRESET, "button-press": METAWORLD_PRESET, "sweep-into": METAWORLD_PRESET,
           "quadruped-walk": dict(DMC_PRESET, total_timesteps=1_000_000, feedback_every=30_000, learning_rate=1e-4)}
CPU_SCALE = ("python pebble.py --env-id walker-walk --total-timesteps 100000 --hidden-dim 256 --num-layers 2 "
             "--batch-size 256 --max-feedback 1000 --feedback-per-session 100 --feedback-every 9000")  # README


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
    """Independent streams from one run seed: query sampler, teacher, random actions of the seed steps (PEBBLE)."""
    return np.random.SeedSequence(seed).spawn(3)


def episode_seed(run_seed: int, stream: int, episode: int) -> int:
    """The reset seed of an episode of a stream, drawn from SeedSequence([run_seed, stream, episode]): any episode
    can be played again alone, and runs with different seeds share no episode (up to chance)."""
    return int(np.random.SeedSequence([run_seed, stream, episode]).generate_state(1)[0])


# Networks
def mlp(in_dim: int, out_dim: int, hidden_dim: int, num_layers: int, activation=nn.ReLU) -> nn.Sequential:
    layers = [m for i in range(num_layers) for m in (nn.Linear(hidden_dim if i else in_dim, hidden_dim), activation())]
    return nn.Sequential(*layers, nn.Linear(hidden_dim if num_layers else in_dim, out_dim))


def orthogonal_init(module: nn.Module) -> nn.Module:
    """Reference code (utils.weight_init, applied to actor and critics): orthogonal weights, zero biases."""
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


class TwinCritic(nn.Module):
    """Two Q-networks, Q(s, a) -> (q1, q2)."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers):
        super().__init__()
        self.q1, self.q2 = (mlp(obs_dim + action_dim, 1, hidden_dim, num_layers) for _ in range(2))
        orthogonal_init(self)

    def forward(self, obs, action):
        x = torch.cat([obs, action], dim=-1)
        return self.q1(x), self.q2(x)


class RewardEnsemble(nn.Module):
    """Appendix "Reward model": members of 3 x 256 LeakyReLU layers with a tanh-bounded output; (..., obs+action)
    -> each member's reward (members, ..., 1)."""

    def __init__(self, obs_dim, action_dim, size):
        super().__init__()
        self.members = nn.ModuleList(
            nn.Sequential(mlp(obs_dim + action_dim, 1, 256, 3, nn.LeakyReLU), nn.Tanh()) for _ in range(size))

    def forward(self, obs_action):
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
    """One gradient step; a non-finite loss stops the run before it (FloatingPointError): the networks stay finite.
    Backward computes the gradients of this optimizer's parameters only (the actor's loss: not the critics')."""
    if not torch.isfinite(loss).all():
        raise FloatingPointError(f"non-finite {name} ({loss.detach().flatten()[0].item()})")
    optimizer.zero_grad()
    loss.backward(inputs=[param for group in optimizer.param_groups for param in group["params"]])
    optimizer.step()


def adam(params, lr: float, eps: float = 1e-8) -> torch.optim.Adam:
    """Adam with fused kernels (PyTorch's fused=True: one kernel a step, not a loop of small ones over the
    parameters): the same update, up to float rounding."""
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)


Batch = namedtuple("Batch", "obs actions rewards next_obs terminated")  # replay-buffer rows


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
    """Transitions on the training device, the oldest overwritten when full; `rewards` holds r_hat (relabelled)."""

    def __init__(self, capacity, obs_dim, action_dim, device):
        self.capacity, self.size, self.pos, self.device = capacity, 0, 0, device
        for name, dim in zip(Batch._fields, (obs_dim, action_dim, 1, obs_dim, 1)):
            setattr(self, name, torch.zeros(capacity, dim, device=device))

    def add(self, *transition):  # obs, action, reward, next obs, terminated
        for name, value in zip(Batch._fields, transition):
            getattr(self, name)[self.pos] = torch.as_tensor(value)
        self.pos, self.size = (self.pos + 1) % self.capacity, min(self.size + 1, self.capacity)

    def sample(self, batch_size) -> Batch:
        idx = torch.randint(self.size, (batch_size,), device=self.device)
        return Batch(*(getattr(self, name)[idx] for name in Batch._fields))

    def state_dict(self) -> dict:  # the filled rows only, copied (a slice would save the whole tensor)
        return {name: getattr(self, name)[: self.size].clone() for name in Batch._fields} | {"pos": self.pos}

    def load_state_dict(self, state: dict):
        self.pos, self.size = state["pos"], len(state["obs"])
        for name in Batch._fields:
            getattr(self, name)[: self.size] = state[name]


def knn_distance(states: torch.Tensor, reference: torch.Tensor, k: int) -> torch.Tensor:
    """Eq. (8) without the log (docs): distance to the k-th nearest neighbour in `reference`, not counting the
    state itself (its zero distance): the (k+1)-th smallest. Memory: states x reference distances."""
    distances = torch.cdist(states, reference).topk(min(k + 1, len(reference)), dim=1, largest=False).values
    return distances[:, -1:].contiguous()  # topk: ~5x faster than kthvalue on a 10K-state buffer


def intrinsic_reward(batch: Batch, buffer: ReplayBuffer, k: int) -> torch.Tensor:
    """Algorithm 2's r_int(s_t) before normalisation: kNN distance of the batch's s_t (obs, not next_obs; reference
    code: agent/sac.py) among all states in the buffer (s_t is one of them: knn_distance skips its zero distance)."""
    return knn_distance(batch.obs, buffer.obs[: buffer.size], k)


class RunningMeanStd:  # of the kNN reward: Chan et al.'s parallel update (the reference code's was wrong)
    def __init__(self):
        self.mean, self.var, self.count = 0.0, 1.0, 0

    def update(self, x: torch.Tensor):
        batch_mean, batch_var, batch_count = x.mean().item(), x.var(unbiased=False).item(), x.numel()
        total = self.count + batch_count
        delta = batch_mean - self.mean
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total
        self.mean, self.var, self.count = self.mean + delta * batch_count / total, m2 / total, total


def relabel(buffer: ReplayBuffer, reward_model: RewardEnsemble, chunk: int = 16384):
    """PEBBLE's relabelling: r_hat = ensemble mean for every stored transition, the wrapped buffer's too."""
    with torch.no_grad():
        for i in range(0, buffer.size, chunk):
            obs_action = torch.cat([buffer.obs[i : i + chunk], buffer.actions[i : i + chunk]], dim=-1)
            buffer.rewards[i : i + chunk] = reward_model(obs_action).mean(0)


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


RESUME_MAY_CHANGE = ("resume", "checkpoint_every", "cuda", "track", "wandb_project_name", "capture_video")
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
    args.buffer_size = args.buffer_size or args.total_timesteps
    return args


def check_args(args: Args, episode_len: int):
    """ValueError naming the first number out of its range (tyro checks types and choices)."""
    a, pretrain = args, args.seed_steps + args.unsup_steps
    rules = [("seed", a.seed >= 0, ">= 0"), ("teacher_beta", a.teacher_beta >= 0, ">= 0 (inf = rational)"),
             *[(n, 0 < getattr(a, n) <= 1, "in (0, 1]") for n in ("teacher_gamma", "gamma", "tau")],
             *[(n, 0 <= getattr(a, n) <= 1, "in [0, 1]") for n in ("teacher_eps_mistake", "teacher_eps_skip",
                                                                   "teacher_eps_equal")],
             *[(n, getattr(a, n) >= 1, ">= 1") for n in (
                 "max_feedback", "feedback_every", "hidden_dim", "num_layers", "batch_size", "reward_batch_size",
                 "reward_ensemble_size", "eval_every", "eval_episodes", "knn_k", "candidate_multiplier",
                 "reward_epochs", "target_update_every")],
             *[(n, getattr(a, n) >= 0, ">= 0") for n in ("seed_steps", "unsup_steps", "critic_reset_updates",
                                                         "query_recent_episodes", "checkpoint_every")],
             *[(n, getattr(a, n) > 0, "> 0") for n in ("learning_rate", "alpha_lr", "reward_lr", "init_temperature")],
             ("label_smoothing", 0 <= a.label_smoothing < 1, "in [0, 1)"),
             ("feedback_per_session", 1 <= a.feedback_per_session <= a.max_feedback,
              f"in [1, --max-feedback={a.max_feedback}]"),
             ("segment_len", 1 <= a.segment_len <= episode_len, f"in [1, {episode_len}] (the episode length)"),
             ("total_timesteps", a.total_timesteps > pretrain, f"> --seed-steps + --unsup-steps ({pretrain})"),
             ("buffer_size", a.buffer_size >= max(a.batch_size, episode_len), ">= max(batch size, episode length)")]
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


def evaluate(actor, reward_model, env, seeds: list[int], device) -> dict:
    """Mean-action episodes (one per reset seed) with the true reward (B-Pref's metric), Meta-World success
    (at any step), and the Pearson correlation of learned and true per-step rewards (the paper's analysis)."""
    returns, successes, true_rewards, learned = [], [], [], []
    for seed in seeds:
        (obs, _), done, success = env.reset(seed=seed), False, False
        returns.append(0.0)
        while not done:
            with torch.no_grad():
                action = torch.tanh(actor(torch.as_tensor(obs, device=device))[0])  # the mean action
                if reward_model is not None:
                    learned.append(reward_model(torch.cat([torch.as_tensor(obs, device=device), action])).mean().item())
            obs, reward, terminated, truncated, info = env.step(action.cpu().numpy())
            done, returns[-1], success = terminated or truncated, returns[-1] + reward, success or info.get("success")
            true_rewards.append(reward)
        successes.append(bool(success))
    correlated = learned and np.std(learned) > 0 and np.std(true_rewards) > 0
    return {"episode_return": float(np.mean(returns)), "episode_return_std": float(np.std(returns)),
            "success_rate": float(np.mean(successes)),
            "reward_correlation": float(np.corrcoef(learned, true_rewards)[0, 1]) if correlated else math.nan}


def projected_cpu_hours(args: Args, obs_dim: int, action_dim: int) -> float:
    """The run's SAC updates on this CPU: 3 timed updates (after a warm-up one) of throwaway networks on random
    data, before the run seeds torch (its state is untouched)."""
    nets = [cls(obs_dim, action_dim, args.hidden_dim, args.num_layers) for cls in (Actor, TwinCritic, TwinCritic)]
    log_alpha = torch.zeros((), requires_grad=True)
    optimizers = [adam(p, 1e-4) for p in (nets[0].parameters(), nets[1].parameters(), [log_alpha])]
    batch = Batch(*(torch.rand(args.batch_size, dim) for dim in (obs_dim, action_dim, 1, obs_dim, 1)))
    times = []
    for _ in range(4):
        sac_update(batch, batch.rewards, *nets, log_alpha, *optimizers, args.gamma)
        times.append(time.perf_counter())
    return (times[-1] - times[0]) / 3 * (args.total_timesteps - args.seed_steps) / 3600


@dataclass
class Progress:
    """What the main loop carries besides networks, optimizers and buffers: a checkpoint saves asdict(progress), a
    resume restores Progress(**saved), so a field added here is checkpointed by construction."""

    global_step: int = 0
    episodes: int = 0  # training episodes before the running one (its number for episode_seed)
    current: tuple = field(default_factory=lambda: ([], [], []))  # the running episode's observations, actions, rewards
    recent_returns: list = field(default_factory=list)  # true returns of the last 10 training episodes
    sessions_done: int = 0
    feedback_used: int = 0
    next_feedback_step: int = 0
    eval_rows: list = field(default_factory=list)  # eval.csv
    reward_ready: bool = False  # SAC trains on buffer.rewards: r_hat (or the true reward), no longer the kNN reward
    overhead_seconds: float = 0.0  # PEBBLE's own parts: kNN reward, queries, reward learning, relabelling, r_hat
    wall_time: float = 0.0
    counts: dict = field(default_factory=lambda: dict.fromkeys(  # how often each phase ran, for the last line
        ("updates_on_knn_reward", "updates_on_learned_reward", "relabels", "critic_resets"), 0))

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
    if device.type == "cpu" and args.hidden_dim * args.batch_size > 256 * 256:  # beyond the CPU scale of the README
        print(f"note: this run needs about {projected_cpu_hours(args, obs_dim, action_dim):.0f} h on this CPU "
              f"(projected); use a GPU, or the CPU scale of docs/results.md: {CPU_SCALE}", flush=True)

    from torch.utils.tensorboard import SummaryWriter

    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, sync_tensorboard=True, config=config, name=run_name, save_code=True)
    checkpoint_path, eval_path = os.path.join(output_dir, "checkpoint.pt"), os.path.join(output_dir, "eval.csv")
    checkpoint = torch.load(checkpoint_path, map_location="cpu", weights_only=True) if args.resume else None
    writer = SummaryWriter(output_dir, purge_step=checkpoint["progress"]["global_step"] + 1 if checkpoint else None)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in config.items()))

    # Seeding: numpy (query sampler, teacher, seed steps' actions: independent streams), torch (networks,
    # batches), every reset (episode_seed): an env is a function of its episode's seed and actions
    sampler_seed, teacher_seed, action_seed = numpy_seeds(args.seed)
    rng, action_rng = np.random.default_rng(sampler_seed), np.random.default_rng(action_seed)
    torch.manual_seed(args.seed)
    torch.set_flush_denormal(True)  # MuJoCo's tiny float32 velocities are denormals, ~10x slower on a CPU
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
    buffer, intrinsic_stats = ReplayBuffer(args.buffer_size, obs_dim, action_dim, device), RunningMeanStd()
    teacher = make_teacher(args.teacher, seed=teacher_seed,
                           **{name: getattr(args, f"teacher_{name}") for name in TEACHER_FIELDS})
    pretrain_end = args.seed_steps + args.unsup_steps
    steps = session_steps(pretrain_end + 1, args.feedback_every, args.total_timesteps)  # t - 1: steps done before
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session, steps - 1,
                                   args.total_timesteps)
    spent = planned_labels(session_sizes, pretrain_end + 1, args.feedback_every, args.total_timesteps)
    if spent < args.max_feedback and not args.ground_truth_reward:
        print(f"note: only {spent} of the {args.max_feedback} labels of --max-feedback fit in {args.total_timesteps} "
              f"steps (sessions from step {pretrain_end + 1}, every {args.feedback_every} steps)")
    # The labelled dataset D: both segments' (observation, action) per step, and the label (--labels-from's are free)
    empty = np.zeros((0, args.segment_len, obs_dim + action_dim), np.float32)
    preferences = imported or {"inputs0": empty, "inputs1": empty, "y": np.zeros(0, np.float32)}
    preferences = {key: torch.as_tensor(value, device=device) for key, value in preferences.items()}
    if imported:
        print(f"--labels-from: {len(imported['y'])} labels from {args.labels_from}")
    # The query pool: the last query_recent_episodes complete episodes, (observations, actions, true rewards) each
    episodes = deque(maxlen=args.query_recent_episodes or None)  # (reference code: an annotation buffer of 100)
    progress = Progress(next_feedback_step=pretrain_end + 1)
    learners = {"actor": actor, "critic": critic, "critic_target": critic_target, "reward_model": reward_model,
                "actor_optimizer": actor_optimizer, "critic_optimizer": critic_optimizer,
                "alpha_optimizer": alpha_optimizer, "reward_optimizer": reward_optimizer, "buffer": buffer,
                "teacher": teacher}
    if checkpoint:  # --resume: every part back, key by key
        saved_progress = checkpoint["progress"]
        progress = Progress(**saved_progress | {"current": tree_map(unplain, saved_progress["current"])})
        print(f"resuming from the checkpoint at step {progress.global_step}")
        for name, part in learners.items():
            part.load_state_dict(checkpoint[name])
        with torch.no_grad():
            log_alpha.copy_(checkpoint["log_alpha"])
        vars(intrinsic_stats).update(checkpoint["intrinsic_stats"])
        preferences = {key: value.to(device) for key, value in checkpoint["preferences"].items()}
        rng.bit_generator.state = checkpoint["rng"]
        action_rng.bit_generator.state = checkpoint["action_rng"]
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
    # The training env at the start of its running episode (that episode's seed), then that episode's actions so far
    # again: MuJoCo is deterministic, so a resumed env is exactly where it was (a new run has no actions to replay)
    obs, _ = env.reset(seed=episode_seed(args.seed, TRAIN_STREAM, progress.episodes))
    for action in progress.current[1]:
        obs = env.step(action)[0]
    if args.capture_video:  # the first episode of each evaluation: videos/step_N-episode-M.mp4
        eval_env = gym.wrappers.RecordVideo(eval_env, os.path.join(output_dir, "videos"),
                                            episode_trigger=lambda episode: episode % args.eval_episodes == 0)
    stop = []  # SIGTERM (a cluster's time limit) or SIGINT (Ctrl-C): checkpoint at the end of this step, then exit
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    signal.signal(signal.SIGINT, lambda signum, frame: stop.append(signum))
    start_time = last_print = time.time() - progress.wall_time

    def checkpoint_state() -> dict:
        """Everything the run needs to go on exactly after this step, but the env (reset with its episode's seed,
        then the episode's actions replayed)."""
        return {"progress": tree_map(plain, asdict(progress) | {"wall_time": time.time() - start_time}),
                **{name: part.state_dict() for name, part in learners.items()}, "log_alpha": log_alpha.detach(),
                "intrinsic_stats": vars(intrinsic_stats), "preferences": preferences,
                "rng": rng.bit_generator.state, "action_rng": action_rng.bit_generator.state,
                "episodes": tree_map(plain, list(episodes)), "torch_rng": torch.get_rng_state(),
                "cuda_rng": torch.cuda.get_rng_state_all() if device.type == "cuda" else None}

    # Main loop: Algorithm 3 (PEBBLE) with Algorithm 2 (unsupervised pre-training) for the first steps
    try:
        save_file(eval_path, eval_csv(progress.eval_rows))  # a resumed run drops the rows after its checkpoint
        for global_step in range(progress.global_step + 1, args.total_timesteps + 1):
            progress.global_step = global_step
            reset_critic = args.ground_truth_reward and global_step == pretrain_end + 1  # as PEBBLE, on the true reward
            # Feedback session (Algorithm 3, reward learning): the first at the end of pre-training, then every
            # feedback_every steps. SAMPLE() queries, ask SimTeacher, save the labels, learn r_hat, relabel
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
                    # Appendix, adaptive thresholds: mean true return of the last 10 training episodes (reference code)
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
                        relabel(buffer, reward_model)
                        progress.counts["relabels"] += 1
                        writer.add_scalar("reward/loss", loss, global_step)
                        writer.add_scalar("reward/accuracy", accuracy, global_step)
                        print(f"step {global_step}: feedback session {progress.sessions_done}: {size} queries "
                              f"({skipped} skipped, {equal} equal), reward model trained on {n_labels} labels, "
                              f"accuracy {accuracy:.3f}")
                reset_critic = n_labels > 0 and not progress.reward_ready
            if reset_critic:  # PEBBLE, after the first reward update: fresh critics (not actor or temperature), then
                # critic_reset_updates SAC updates on the relabelled buffer (reference code); not counted as overhead
                progress.reward_ready, progress.counts["critic_resets"] = True, progress.counts["critic_resets"] + 1
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
            next_obs, true_reward, terminated, truncated, _ = env.step(action)
            if not (math.isfinite(true_reward) and np.isfinite(next_obs).all()):
                raise FloatingPointError(f"non-finite reward ({true_reward}) or observation from the environment")
            reward = float(true_reward) if args.ground_truth_reward else 0.0
            if progress.reward_ready and not args.ground_truth_reward:  # Algorithm 3: store r_hat(s_t, a_t)
                with progress.overhead(), torch.no_grad():  # a tensor on the device: no host sync
                    reward = reward_model(torch.as_tensor(np.concatenate([obs, action]), device=device)).mean()
            buffer.add(obs, action, reward, next_obs, terminated)
            for part, value in zip(progress.current, (obs, action, true_reward)):
                part.append(value)
            obs = next_obs
            if terminated or truncated:  # to the query pool; the next episode starts from its own seed
                episodes.append(tuple(np.array(part, dtype=np.float32) for part in progress.current))
                progress.recent_returns = (progress.recent_returns + [float(sum(progress.current[2]))])[-10:]
                writer.add_scalar("charts/episodic_return", progress.recent_returns[-1], global_step)
                progress.current, progress.episodes = ([], [], []), progress.episodes + 1
                obs, _ = env.reset(seed=episode_seed(args.seed, TRAIN_STREAM, progress.episodes))

            # Policy learning: SAC on the kNN state entropy during pre-training (and while every query was
            # skipped), then on the learned reward (or the true reward with --ground-truth-reward)
            if global_step > args.seed_steps:
                batch = buffer.sample(args.batch_size)
                rewards = batch.rewards
                if not progress.reward_ready:  # Algorithm 2: r_int(s_t) over its running standard deviation
                    with progress.overhead():
                        rewards = intrinsic_reward(batch, buffer, args.knn_k)
                        intrinsic_stats.update(rewards)
                        rewards = rewards / max(math.sqrt(intrinsic_stats.var), 1e-8)
                losses = sac_update(batch, rewards, actor, critic, critic_target, log_alpha, actor_optimizer,
                                    critic_optimizer, alpha_optimizer, args.gamma)
                progress.counts["updates_on_learned_reward" if progress.reward_ready else "updates_on_knn_reward"] += 1
                if (global_step - args.seed_steps) % args.target_update_every == 0:
                    soft_update(critic, critic_target, args.tau)
                if global_step % 1000 == 0:
                    for name, value in losses.items():
                        writer.add_scalar(f"losses/{name}", float(value), global_step)
                    writer.add_scalar("charts/SPS", int(global_step / (time.time() - start_time)), global_step)

            if global_step % args.eval_every == 0 or global_step == args.total_timesteps:
                if args.capture_video:
                    eval_env.name_prefix = f"step_{global_step}"
                seeds = [episode_seed(args.seed, EVAL_STREAM, len(progress.eval_rows) * args.eval_episodes + j)
                         for j in range(args.eval_episodes)]
                judged = reward_model if progress.reward_ready and not args.ground_truth_reward else None
                result = evaluate(actor, judged, eval_env, seeds, device)
                if args.capture_video and eval_env.recording:  # write the video now, not at the next reset
                    eval_env.stop_recording()
                progress.eval_rows.append({"step": global_step, **result, "feedback": progress.feedback_used,
                                           "wall_time": round(time.time() - start_time, 1),
                                           "overhead_seconds": round(progress.overhead_seconds, 1)})
                save_file(eval_path, eval_csv(progress.eval_rows))
                for name in ("episode_return", "success_rate", "reward_correlation"):
                    writer.add_scalar(f"eval/{name}", result[name], global_step)
            if time.time() - last_print > 10 or global_step == args.total_timesteps:
                last_print, left = time.time(), args.total_timesteps - global_step
                sps, last_eval = global_step / (last_print - start_time), (progress.eval_rows or [{}])[-1]
                print(f"step {global_step}/{args.total_timesteps} | {sps:.0f} SPS | ETA {left / sps / 60:.1f} "
                      f"min | last eval return {last_eval.get('episode_return', math.nan):.1f} | labels "
                      f"{progress.feedback_used}/{args.max_feedback}", flush=True)

            if args.checkpoint_every and global_step % args.checkpoint_every == 0 or stop:
                save_start, data = time.perf_counter(), io.BytesIO()
                torch.save(checkpoint_state(), data)  # in memory first: a full disk is then a plain OSError
                save_file(checkpoint_path, data.getvalue())
                print(f"step {global_step}: checkpoint.pt saved ({os.path.getsize(checkpoint_path) / 2**20:.1f} MiB "
                      f"in {time.perf_counter() - save_start:.1f} s)", flush=True)
            if stop:
                print(f"{signal.Signals(stop[0]).name}: checkpoint saved at step {global_step}; continue with --resume "
                      f"{output_dir}", flush=True)
                writer.close()
                sys.exit(128 + stop[0])
    except FloatingPointError as error:  # a NaN or infinity in a loss or from the environment
        # Mid-step the env and the buffer have moved past the last checkpoint, which stays as it is. The state at the
        # failure (finite: the checks come before the optimizer steps) goes to a file of its own, to inspect
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
    torch.save({"actor": actor.state_dict(), "critic": critic.state_dict(), "reward_model": reward_model.state_dict()},
               os.path.join(output_dir, "final_model.pt"))
    writer.close()
