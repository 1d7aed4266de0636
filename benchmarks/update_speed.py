"""The update of pebble.py (SAC) and of prefppo.py (PPO) against a plain eager PyTorch implementation of the same
math written here (the reference to beat), timed side by side in one process: rounds alternate between the two, and
the table gives the median time of each and their ratio (plain / script: above 1 means the script is faster).

    python benchmarks/update_speed.py                  # CPU: SAC 256 x 2 / batch 256 (whole training step: env
                                                       # step, buffer, update), SAC 1024 x 2 / batch 1024, PPO preset
    python benchmarks/update_speed.py --device cuda    # the same on a GPU
    python benchmarks/update_speed.py --rounds 3 --quick   # a short check (fewer updates per round)

SAC: one training step = one walker-walk env step with a random action, one buffer add, one batch sampled, one
SAC update (critic, actor, temperature) and, every second step, the target critics' EMA, as in pebble.py.
PPO: one epoch of minibatch updates over a rollout of the walker-walk PrefPPO preset (32 envs x 500 steps, minibatch
64: 250 updates), with gSDE, as in prefppo.py. Targets (issue 14): SAC 2x on CPU at 256 x 2, 3x on a GPU at the
paper's sizes; PPO 1.5x on CPU.
"""

import argparse
import copy
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import pebble  # noqa: E402
import prefppo  # noqa: E402


def plain_mlp(in_dim, out_dim, hidden, layers, activation):
    dims = [in_dim] + [hidden] * layers
    modules = []
    for a, b in zip(dims, dims[1:]):
        modules += [nn.Linear(a, b), activation()]
    return nn.Sequential(*modules, nn.Linear(dims[-1], out_dim))


class PlainSAC:
    """SAC as a plain eager implementation writes it: two separate Q-networks, three Adam optimizers, a
    tanh-Gaussian actor with torch.distributions, the same losses as pebble.sac_update."""

    def __init__(self, obs_dim, action_dim, hidden, layers, device):
        self.actor = plain_mlp(obs_dim, 2 * action_dim, hidden, layers, nn.ReLU).to(device)
        self.q1, self.q2 = (plain_mlp(obs_dim + action_dim, 1, hidden, layers, nn.ReLU).to(device) for _ in range(2))
        self.q1_target, self.q2_target = copy.deepcopy(self.q1), copy.deepcopy(self.q2)
        self.log_alpha = torch.zeros((), device=device, requires_grad=True)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=3e-4)
        self.q_opt = torch.optim.Adam([*self.q1.parameters(), *self.q2.parameters()], lr=3e-4)
        self.alpha_opt = torch.optim.Adam([self.log_alpha], lr=1e-4)
        self.target_entropy = -action_dim

    def sample(self, obs):
        mean, log_std = self.actor(obs).chunk(2, dim=-1)
        log_std = -5 + 0.5 * 7 * (torch.tanh(log_std) + 1)
        normal = torch.distributions.Normal(mean, log_std.exp())
        u = normal.rsample()
        action = torch.tanh(u)
        return action, (normal.log_prob(u) - torch.log(1 - action.pow(2) + 1e-6)).sum(-1, keepdim=True)

    def update(self, obs, actions, rewards, next_obs, terminated, step, gamma=0.99, tau=0.005):
        alpha = self.log_alpha.exp().detach()
        with torch.no_grad():
            next_actions, next_log_prob = self.sample(next_obs)
            x = torch.cat([next_obs, next_actions], -1)
            next_q = torch.min(self.q1_target(x), self.q2_target(x)) - alpha * next_log_prob
            target = rewards + gamma * (1 - terminated) * next_q
        x = torch.cat([obs, actions], -1)
        q_loss = F.mse_loss(self.q1(x), target) + F.mse_loss(self.q2(x), target)
        self.q_opt.zero_grad()
        q_loss.backward()
        self.q_opt.step()
        new_actions, log_prob = self.sample(obs)
        x = torch.cat([obs, new_actions], -1)
        actor_loss = (alpha * log_prob - torch.min(self.q1(x), self.q2(x))).mean()
        self.actor_opt.zero_grad()
        actor_loss.backward()
        self.actor_opt.step()
        alpha_loss = (self.log_alpha.exp() * (-log_prob.detach() - self.target_entropy)).mean()
        self.alpha_opt.zero_grad()
        alpha_loss.backward()
        self.alpha_opt.step()
        if step % 2 == 0:
            with torch.no_grad():
                for net, target_net in ((self.q1, self.q1_target), (self.q2, self.q2_target)):
                    for p, tp in zip(net.parameters(), target_net.parameters()):
                        tp.mul_(1 - tau).add_(tau * p)


def sac_variants(hidden, layers, batch, device, env_steps: bool):
    """Two step functions (script, plain) on a walker-walk buffer of 10,000 random transitions."""
    env, _ = pebble.make_env("walker-walk")
    obs_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    torch.manual_seed(0)
    buffer = pebble.ReplayBuffer(100_000, obs_dim, action_dim, device)
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(0)

    def env_step():
        nonlocal obs
        action = rng.uniform(-1, 1, action_dim).astype(np.float32)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        buffer.add(obs, action, reward, next_obs, terminated)
        obs = env.reset(seed=int(rng.integers(2**31)))[0] if terminated or truncated else next_obs

    for _ in range(10_000):
        env_step()
    actor = pebble.Actor(obs_dim, action_dim, hidden, layers).to(device)
    critic = pebble.TwinCritic(obs_dim, action_dim, hidden, layers).to(device)
    critic_target = copy.deepcopy(critic)
    log_alpha = torch.tensor(math.log(0.1), device=device, requires_grad=True)
    optimizers = (pebble.adam(actor.parameters(), 3e-4), pebble.adam(critic.parameters(), 3e-4),
                  pebble.adam([log_alpha], 1e-4))  # as pebble.py makes them
    plain = PlainSAC(obs_dim, action_dim, hidden, layers, device)
    counter = {"script": 0, "plain": 0}

    def script_step():
        if env_steps:
            env_step()
        b = buffer.sample(batch)
        pebble.sac_update(b, b.rewards, actor, critic, critic_target, log_alpha, *optimizers, 0.99)
        counter["script"] += 1
        if counter["script"] % 2 == 0:
            pebble.soft_update(critic, critic_target, 0.005)

    def plain_step():
        if env_steps:
            env_step()
        b = buffer.sample(batch)
        counter["plain"] += 1
        plain.update(b.obs, b.actions, b.rewards, b.next_obs, b.terminated, counter["plain"])

    return script_step, plain_step


def ppo_variants(device, updates: int):
    """One epoch of minibatch updates over a walker-walk rollout of the PrefPPO DMC preset (script, script with
    --compile, plain)."""
    preset = prefppo.task_defaults("walker-walk", "oracle")
    obs_dim, action_dim, hidden, layers = 24, 6, preset.hidden_dim, preset.num_layers
    rollout, minibatch = preset.num_envs * preset.num_steps, preset.minibatch_size
    torch.manual_seed(0)
    obs, actions = torch.randn(rollout, obs_dim, device=device), torch.randn(rollout, action_dim, device=device)
    logprobs, advantages, returns = (torch.randn(rollout, device=device) for _ in range(3))
    args = argparse.Namespace(minibatch_size=minibatch, vf_coef=0.5, ent_coef=0.0, max_grad_norm=0.5)
    actor = prefppo.Actor(obs_dim, action_dim, hidden, layers, use_sde=True).to(device)
    critic = prefppo.make_critic(obs_dim, hidden, layers).to(device)
    optimizer = prefppo.adam([*actor.parameters(), *critic.parameters()], 5e-5, eps=1e-5)  # as prefppo.py
    plain_policy = plain_mlp(obs_dim, action_dim, hidden, layers, nn.Tanh).to(device)
    plain_log_std = nn.Parameter(torch.zeros(hidden, action_dim, device=device))
    plain_value = plain_mlp(obs_dim, 1, hidden, layers, nn.Tanh).to(device)
    params = [*plain_policy.parameters(), plain_log_std, *plain_value.parameters()]
    plain_optimizer = torch.optim.Adam(params, lr=5e-5, eps=1e-5)
    n = min(rollout, updates * minibatch)  # the first `updates` minibatches of the epoch

    clip = torch.tensor(0.4, device=device)
    eager_loss, compiled_loss = prefppo.ppo_loss, torch.compile(prefppo.ppo_loss)

    def script_epoch(loss_fn=eager_loss):
        prefppo.ppo_loss = loss_fn  # as prefppo.py's main block with --compile: ppo_update calls it by this name
        prefppo.ppo_update(obs[:n], actions[:n], logprobs[:n], advantages[:n], returns[:n], actor, critic,
                           optimizer, 1, clip, args)
        prefppo.ppo_loss = eager_loss

    def plain_epoch():
        order = torch.randperm(n, device=device)
        for start in range(0, n, minibatch):
            idx = order[start : start + minibatch]
            latent = plain_policy[:-1](obs[idx])
            std = torch.sqrt(latent.detach() ** 2 @ plain_log_std.exp() ** 2 + 1e-6)
            distribution = torch.distributions.Normal(plain_policy[-1](latent), std)
            adv = (advantages[idx] - advantages[idx].mean()) / (advantages[idx].std() + 1e-8)
            ratio = (distribution.log_prob(actions[idx]).sum(-1) - logprobs[idx]).exp()
            policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(0.6, 1.4)).mean()
            value_loss = F.mse_loss(plain_value(obs[idx])[:, 0], returns[idx])
            loss = policy_loss + 0.5 * value_loss
            plain_optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(params, 0.5)
            plain_optimizer.step()
            ((ratio - 1).abs() > 0.4).float().mean().item()  # the clip fraction, as the script logs it

    return script_epoch, lambda: script_epoch(compiled_loss), plain_epoch, n // minibatch


def timed(fn, calls: int) -> float:
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / calls


def compare(script, plain, calls: int, rounds: int) -> tuple[float, float]:
    """Median seconds per call of each, over `rounds` alternating rounds of `calls` calls (one warm-up round)."""
    timed(script, max(1, calls // 4))
    timed(plain, max(1, calls // 4))
    times = {"script": [], "plain": []}
    for _ in range(rounds):
        times["script"].append(timed(script, calls))
        times["plain"].append(timed(plain, calls))
    return statistics.median(times["script"]), statistics.median(times["plain"])


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="fewer calls per round (a check, not a measurement)")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        sys.exit("error: --device cuda, but torch sees no GPU")
    torch.set_flush_denormal(True)
    device = torch.device(args.device)
    cases = [("SAC training step (env + update), 256 x 2, batch 256", *sac_variants(256, 2, 256, device, True),
              20 if args.quick else 200, "step"),
             ("SAC update, 1024 x 2, batch 1024 (paper, DMC)", *sac_variants(1024, 2, 1024, device, False),
              2 if args.quick else (10 if args.device == "cpu" else 200), "update")]
    script_epoch, compiled_epoch, plain_epoch, minibatches = ppo_variants(device, 10 if args.quick else 250)
    cases.append((f"PPO epoch, PrefPPO DMC preset ({minibatches} minibatches of 64, 256 x 3, gSDE)", script_epoch,
                  plain_epoch, 1, "epoch"))
    cases.append(("the same, prefppo.py --compile (ppo_loss compiled; first call not timed)", compiled_epoch,
                  plain_epoch, 1, "epoch"))
    print(f"device: {torch.cuda.get_device_name() if args.device == 'cuda' else 'cpu'}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, median of {args.rounds} alternating rounds")
    print("| case | script (ms per call) | plain eager (ms per call) | plain / script |")
    print("|---|---|---|---|")
    for name, script, plain, calls, unit in cases:
        script_s, plain_s = compare(script, plain, calls, args.rounds)
        print(f"| {name} | {1e3 * script_s:.2f} | {1e3 * plain_s:.2f} | {plain_s / script_s:.2f}x |", flush=True)
