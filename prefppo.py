# PrefPPO (Christiano et al. 2017 with PPO) as benchmarked by B-Pref (Lee et al. 2021); docs and choices: README.md
import csv
import importlib
import json
import math
import os
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass

import gymnasium as gym
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
    """if toggled, save a video of the first episode of each evaluation (needs moviepy)"""
    output_dir: str | None = None
    """where the run's files go (default: runs/<run name>)"""

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
    update_epochs: int = 10
    """PPO epochs over each rollout"""
    minibatch_size: int | None = None
    """PPO minibatch size"""
    gamma: float = 0.99
    """discount"""
    gae_lambda: float | None = None
    """GAE lambda"""
    clip_coef: float = 0.4
    """PPO clip range (paper: 0.4)"""
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
    query_recent_episodes: int = 100
    """segments are drawn from the last N complete episodes"""


# Paper appendix, table of PrefPPO hyperparameters (README lists the values the paper leaves open).
DMC_PRESET = dict(total_timesteps=4_000_000, max_feedback=1000, feedback_per_session=100, feedback_every=32_000,
                  segment_len=50, learning_rate=5e-5, num_envs=32, num_steps=500, minibatch_size=64, gae_lambda=0.92,
                  reward_epochs=50)
METAWORLD_PRESET = dict(total_timesteps=3_000_000, max_feedback=10_000, feedback_per_session=100, feedback_every=16_000,
                        segment_len=25, learning_rate=3e-4, num_envs=8, num_steps=250, minibatch_size=128,
                        gae_lambda=0.92, reward_epochs=10)
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
    from dm_control import suite
    import metaworld

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


def make_env(env_id: str, seed: int, render_mode: str | None = None) -> tuple[gym.Env, int]:
    """Returns (env, episode length T); actions rescaled to [-1, 1], observations flat float32."""
    kind = env_kind(env_id)
    if kind == "dmc":
        env = DMCEnv(*env_id.split("-", 1), seed, render_mode)
        episode_len = env.max_episode_steps
    elif kind == "metaworld":
        env = gym.make("Meta-World/MT1", env_name=f"{env_id.removesuffix('-v3')}-v3", seed=seed, render_mode=render_mode)
        env.get_wrapper_attr("toggle_terminate_on_success")(False)  # B-Pref: fixed 500-step episodes
        episode_len = env.spec.max_episode_steps or 500
    else:
        env = gym.make(env_id, **({"render_mode": render_mode} if render_mode else {}))
        episode_len = env.spec.max_episode_steps
        if not isinstance(env.action_space, gym.spaces.Box) or not isinstance(env.observation_space, gym.spaces.Box):
            raise ValueError(f"--env-id {env_id!r} must have Box observation and action spaces")
        if episode_len is None:
            raise ValueError(f"--env-id {env_id!r} has no time limit (max_episode_steps), needed for the thresholds")
    env = gym.wrappers.RescaleAction(env, -1.0, 1.0)
    env = gym.wrappers.TransformObservation(env, lambda o: np.asarray(o, dtype=np.float32), env.observation_space)
    env.reset(seed=seed)  # seeds the env's generator once; later resets continue its sequence
    env.action_space.seed(seed)
    return env, episode_len


def mlp(in_dim: int, out_dim: int, hidden_dim: int, num_layers: int, activation=nn.Tanh) -> nn.Sequential:
    layers, dim = [], in_dim
    for _ in range(num_layers):
        layers += [nn.Linear(dim, hidden_dim), activation()]
        dim = hidden_dim
    return nn.Sequential(*layers, nn.Linear(dim, out_dim))


class Actor(nn.Module):
    """Gaussian policy with a state-independent log std; actions are clipped to [-1, 1] in the env."""

    def __init__(self, obs_dim, action_dim, hidden_dim, num_layers):
        super().__init__()
        self.mean = mlp(obs_dim, action_dim, hidden_dim, num_layers)
        self.log_std = nn.Parameter(torch.zeros(action_dim))

    def distribution(self, obs):
        return torch.distributions.Normal(self.mean(obs), self.log_std.exp())


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
    """Fill every field left None from the task's preset; a flag the user gave wins."""
    family = {"dmc": DMC_PRESET, "metaworld": METAWORLD_PRESET, "gym": GYM_PRESET}[env_kind(args.env_id)]
    preset = PRESETS.get(args.env_id.removesuffix("-v3"), family)
    for key, value in preset.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
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
        (min(args.num_envs, args.num_steps, args.update_epochs) >= 1, "--num-envs, --num-steps and --update-epochs must be >= 1"),
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
        (args.query_recent_episodes >= 1, f"--query-recent-episodes must be >= 1, got {args.query_recent_episodes}"),
        (not args.cuda or torch.cuda.is_available(), "--cuda was given but torch sees no GPU"),
    ]
    return next((message for ok, message in checks if not ok), None)


def fail(message: str):
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def write_atomic_npz(path: str, **arrays):
    """Write then rename, so that a kill never leaves a half-written file."""
    tmp = f"{path}.tmp.npz"
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def evaluate(actor, obs_stats, reward_model, env, episodes, device, video_env=None) -> dict:
    """Mean-action episodes with the true reward (B-Pref's metric), Meta-World success (success at any
    step), and the Pearson correlation of learned and true per-step rewards (the paper's reward analysis)."""
    returns, successes, true_rewards, learned = [], [], [], []
    for episode in range(episodes):
        run_env = video_env if (video_env is not None and episode == 0) else env
        obs, _ = run_env.reset()
        done, episode_return, success = False, 0.0, False
        while not done:
            with torch.no_grad():
                action = actor.mean(torch.as_tensor(obs_stats.normalize(obs), device=device)).clamp(-1, 1)
                if reward_model is not None:
                    learned.append(reward_model(torch.cat([torch.as_tensor(obs, device=device), action])).mean().item())
            obs, reward, terminated, truncated, info = run_env.step(action.cpu().numpy())
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


if __name__ == "__main__":
    args = tyro.cli(Args)
    try:
        args = resolve(args)
        env, episode_len = make_env(args.env_id, args.seed)
    except ValueError as error:
        fail(str(error))
    env.close()
    problem = check_args(args, episode_len)
    if problem:
        fail(problem)
    if args.capture_video:
        try:
            import moviepy  # noqa: F401
        except ImportError:
            fail("--capture-video needs moviepy (pip install moviepy) and a renderer (MUJOCO_GL=egl or osmesa)")
    run_name = f"{args.env_id}__{args.exp_name}__{args.teacher}__{args.seed}__{int(time.time())}"
    output_dir = args.output_dir or os.path.join("runs", run_name)
    if os.path.isdir(output_dir) and os.listdir(output_dir):
        fail(f"--output-dir {output_dir!r} already holds a run; choose another directory")
    try:
        os.makedirs(os.path.join(output_dir, "labels"), exist_ok=True)
    except OSError as error:
        fail(f"cannot create --output-dir {output_dir!r}: {error.strerror}")
    config = asdict(args)
    with open(os.path.join(output_dir, "config.json"), "w") as f:
        json.dump(config, f, indent=2)
    print("configuration:", json.dumps(config))

    from torch.utils.tensorboard import SummaryWriter

    if args.track:
        import wandb

        wandb.init(project=args.wandb_project_name, sync_tensorboard=True, config=config, name=run_name, save_code=True)
    writer = SummaryWriter(output_dir)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in config.items()))

    # Seeding: numpy (pairs, teacher via its own seed), torch (networks, actions), environments
    rng = np.random.default_rng(args.seed)
    torch.manual_seed(args.seed)
    # MuJoCo's float64 states cast to float32 give denormal numbers (tiny velocities), which make
    # CPU matrix products ~10x slower; flushing them to zero changes nothing measurable
    torch.set_flush_denormal(True)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if args.cuda else "cpu")
    envs = gym.vector.SyncVectorEnv(
        [lambda i=i: make_env(args.env_id, args.seed + i)[0] for i in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
    eval_env, _ = make_env(args.env_id, args.seed + 10_000)
    video_env = None
    if args.capture_video:
        video_env, _ = make_env(args.env_id, args.seed + 20_000, render_mode="rgb_array")
        video_env = gym.wrappers.RecordVideo(video_env, os.path.join(output_dir, "videos"), episode_trigger=lambda e: True)
    obs_dim, action_dim = envs.single_observation_space.shape[0], envs.single_action_space.shape[0]

    actor = Actor(obs_dim, action_dim, args.hidden_dim, args.num_layers).to(device)
    critic = mlp(obs_dim, 1, args.hidden_dim, args.num_layers).to(device)
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=args.learning_rate, eps=1e-5)
    critic_optimizer = torch.optim.Adam(critic.parameters(), lr=args.learning_rate, eps=1e-5)
    obs_stats, intrinsic_stats = RunningMeanStd(obs_dim), RunningMeanStd(1)

    reward_model = RewardEnsemble(obs_dim, action_dim, args.reward_ensemble_size).to(device)
    reward_optimizer = torch.optim.Adam(reward_model.parameters(), lr=args.reward_lr)
    teacher = make_teacher(args.teacher, seed=args.seed, **{k: v for k, v in {
        "beta": args.teacher_beta, "gamma": args.teacher_gamma, "eps_mistake": args.teacher_eps_mistake,
        "eps_skip": args.teacher_eps_skip, "eps_equal": args.teacher_eps_equal}.items() if v is not None})
    session_sizes = schedule_sizes(args.schedule, args.max_feedback, args.feedback_per_session)
    preference_inputs0, preference_inputs1, preference_y, labelled_features = [], [], [], []
    feedback_used = sessions_done = 0
    # Annotation buffer: the last complete episodes in raw observations (obs, actions, true rewards)
    episodes = deque(maxlen=args.query_recent_episodes)

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
    with open(eval_path, "w", newline="") as f:
        csv.DictWriter(f, eval_fields).writeheader()
    counts = dict(updates_on_knn_reward=0, updates_on_learned_reward=0, value_resets=0)
    overhead_seconds = 0.0  # time in the preference-learning parts: kNN reward, queries, reward learning
    rollout_shape = (args.num_steps, args.num_envs)
    raw_obs_buf = torch.zeros(*rollout_shape, obs_dim, device=device)
    obs_buf = torch.zeros(*rollout_shape, obs_dim, device=device)
    actions_buf, env_actions_buf = (torch.zeros(*rollout_shape, action_dim, device=device) for _ in range(2))
    logprobs_buf, values_buf, next_values_buf = (torch.zeros(rollout_shape, device=device) for _ in range(3))
    true_rewards_buf, bootstrap_buf, dones_buf = (torch.zeros(rollout_shape, device=device) for _ in range(3))
    next_raw_obs_buf = torch.zeros(*rollout_shape, obs_dim, device=device)
    current = [([], [], []) for _ in range(args.num_envs)]  # the running episode of each env
    recent_returns = deque(maxlen=100)
    episode_returns = np.zeros(args.num_envs)
    raw_obs, _ = envs.reset(seed=args.seed)
    next_feedback_step = args.unsup_steps
    next_eval_step, last_eval = args.eval_every, float("nan")
    reward_ready = False  # PPO trains on r_hat (or the true reward) instead of the kNN reward
    global_step, start_time, last_print = 0, time.time(), time.time()
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
        if reward_ready and counts["value_resets"] == 0:  # the end of pre-training: a fresh value function
            critic = mlp(obs_dim, 1, args.hidden_dim, args.num_layers).to(device)
            critic_optimizer = torch.optim.Adam(critic.parameters(), lr=args.learning_rate, eps=1e-5)
            counts["value_resets"] += 1

        # Rollout of num_steps in every environment
        for step in range(args.num_steps):
            obs_stats.update(raw_obs)
            obs = torch.as_tensor(obs_stats.normalize(raw_obs), device=device)
            with torch.no_grad():
                distribution = actor.distribution(obs)
                action = distribution.sample()
                logprobs_buf[step] = distribution.log_prob(action).sum(-1)
                values_buf[step] = critic(obs)[:, 0]
            env_action = action.clamp(-1, 1)  # executed and judged; PPO's ratio uses the sampled `action`
            env_action_np = env_action.cpu().numpy()
            next_raw_obs, true_reward, terminated, truncated, infos = envs.step(env_action_np)
            done = terminated | truncated
            real_next = true_next_observations(next_raw_obs, infos, done)
            raw_obs_buf[step], obs_buf[step], actions_buf[step] = torch.as_tensor(raw_obs), obs, action
            env_actions_buf[step] = env_action
            next_raw_obs_buf[step] = torch.as_tensor(real_next)
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
            knn_start = time.perf_counter()
            flat_next = next_raw_obs_buf.reshape(-1, obs_dim)
            intrinsic = knn_distance(flat_next, flat_next, args.knn_k)
            intrinsic_stats.update(intrinsic.cpu().numpy())
            rewards = (intrinsic / math.sqrt(intrinsic_stats.var[0] + 1e-8)).reshape(rollout_shape)
            overhead_seconds += time.perf_counter() - knn_start
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
        for epoch in range(args.update_epochs):
            order = torch.randperm(batch_size, device=device)
            for start in range(0, batch_size, args.minibatch_size):
                idx = order[start : start + args.minibatch_size]
                distribution = actor.distribution(b_obs[idx])
                log_ratio = distribution.log_prob(b_actions[idx]).sum(-1) - b_logprobs[idx]
                ratio = log_ratio.exp()
                with torch.no_grad():
                    approx_kl = ((ratio - 1) - log_ratio).mean()
                    clip_fractions.append(((ratio - 1).abs() > args.clip_coef).float().mean().item())
                adv = b_advantages[idx]
                adv = (adv - adv.mean()) / (adv.std() + 1e-8) if len(idx) > 1 else adv
                policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
                value_loss = 0.5 * ((critic(b_obs[idx])[:, 0] - b_returns[idx]) ** 2).mean()
                entropy = distribution.entropy().sum(-1).mean()
                loss = policy_loss - args.ent_coef * entropy + args.vf_coef * value_loss
                actor_optimizer.zero_grad()
                critic_optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_([*actor.parameters(), *critic.parameters()], args.max_grad_norm)
                actor_optimizer.step()
                critic_optimizer.step()
        explained_variance = 1 - (b_returns - b_values).var() / b_returns.var().clamp(min=1e-8)
        for name, value in {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy, "approx_kl": approx_kl,
                            "clipfrac": np.mean(clip_fractions), "explained_variance": explained_variance}.items():
            writer.add_scalar(f"losses/{name}", float(value), global_step)
        writer.add_scalar("charts/SPS", int(global_step / (time.time() - start_time)), global_step)

        if global_step >= next_eval_step or global_step >= args.total_timesteps:
            next_eval_step += args.eval_every
            result = evaluate(actor, obs_stats, reward_model if reward_ready and not args.ground_truth_reward else None,
                              eval_env, args.eval_episodes, device, video_env)
            last_eval = result["episode_return"]
            row = {"step": global_step, **result, "feedback": feedback_used, "wall_time": round(time.time() - start_time, 1),
                   "overhead_seconds": round(overhead_seconds, 1)}
            with open(eval_path, "a", newline="") as f:
                csv.DictWriter(f, eval_fields).writerow(row)
            for name in ("episode_return", "success_rate", "reward_correlation"):
                writer.add_scalar(f"eval/{name}", result[name], global_step)
        if time.time() - last_print > 10 or global_step >= args.total_timesteps:
            last_print = time.time()
            sps = global_step / (last_print - start_time)
            print(f"step {global_step}/{args.total_timesteps} | {sps:.0f} SPS | ETA {(args.total_timesteps - global_step) / sps / 60:.1f} min"
                  f" | last eval return {last_eval:.1f} | labels {feedback_used}/{args.max_feedback}", flush=True)

    print(f"done: {counts} (updates_on_learned_reward: the true reward with --ground-truth-reward), "
          f"{sessions_done} feedback sessions, {feedback_used} queries; outputs in {output_dir}")
    torch.save({"actor": actor.state_dict(), "critic": critic.state_dict(), "reward_model": reward_model.state_dict(),
                "obs_mean": obs_stats.mean, "obs_var": obs_stats.var}, os.path.join(output_dir, "final_model.pt"))
    envs.close()
    eval_env.close()
    writer.close()
