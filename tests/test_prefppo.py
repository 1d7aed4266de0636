"""prefppo.py: unit tests of GAE, the PPO losses, gSDE, the episode seeds and the reward replacement; smoke runs that
reach every phase (pre-training updates on the kNN reward, feedback sessions, PPO on r_hat, evaluation), proved by
what the run writes; the reference's ways as edits of a copy (benchmarks/reference/edits.py); bad input that must end
with one line and a non-zero exit before any training."""

import json
import math
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import prefppo
from samplers import planned_labels, schedule_sizes
import tests.toy_envs  # noqa: F401  (registers ConstantPenalty-v0)
from tests.helpers import (ROOT, assert_inputs_standardised_by_labelled_states, assert_refused_by_tyro, assert_rejected, eval_curve,
                           eval_rows, run_cli, run_in_one_interpreter, run_script, saved_labels, scalars, session_lines)

TINY = ["--hidden-dim", "32", "--num-layers", "2", "--reward-epochs", "3", "--reward-batch-size", "32",
        "--eval-episodes", "1", "--update-epochs", "2", "--unsup-update-epochs", "2"]


def run_prefppo(out, *flags, timeout=600):
    return run_script("prefppo.py", out, *flags, timeout=timeout)


def run_edited(edit, out, *flags, timeout=600):
    """prefppo.py with one of benchmarks/reference/edits.py's edits (the reference's way), as a user runs it."""
    return run_cli("benchmarks/reference/edits.py", edit, "--", "prefppo.py", "--output-dir", str(out), *flags,
                   timeout=timeout)


def adam_steps(out) -> int:
    """Gradient steps of the actor-critic's Adam, from the run's final checkpoint (every parameter's count)."""
    state = torch.load(out / "checkpoint.pt", weights_only=True)["optimizer"]["state"]
    steps = {int(s["step"]) for s in state.values()}
    assert len(steps) == 1, steps
    return steps.pop()


# ---------------------------------------------------------------- unit tests


def test_gae_matches_a_hand_computed_rollout():
    gamma, lam = 0.9, 0.8
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    next_values = torch.tensor([[1.0], [1.5], [2.0]])
    d2 = 3 + 0.9 * 2.0 - 1.5  # 3.3
    d1 = 2 + 0.9 * 1.5 - 1.0  # 2.35
    d0 = 1 + 0.9 * 1.0 - 0.5  # 1.4
    a2 = d2
    a1 = d1 + gamma * lam * a2
    a0 = d0 + gamma * lam * a1
    advantages, returns = prefppo.compute_gae(rewards, values, next_values, torch.zeros(3, 1), gamma, lam)
    torch.testing.assert_close(advantages[:, 0], torch.tensor([a0, a1, a2]))
    torch.testing.assert_close(returns, advantages + values)


@pytest.mark.parametrize("terminated", [False, True])
def test_gae_stops_at_an_episode_end_and_bootstraps_only_a_time_limit(terminated):
    gamma, lam = 0.9, 0.8
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    # step 1 ends the episode: the main loop's next value is V of its last state (7) at a time limit, 0 at a
    # termination
    next_values = torch.tensor([[1.0], [0.0 if terminated else 7.0], [2.0]])
    ends = torch.tensor([[0.0], [1.0], [0.0]])
    advantages, _ = prefppo.compute_gae(rewards, values, next_values, ends, gamma, lam)
    a2 = 3 + 0.9 * 2.0 - 1.5
    a1 = 2 + (0.0 if terminated else 0.9 * 7.0) - 1.0
    a0 = (1 + 0.9 * 1.0 - 0.5) + gamma * lam * a1  # step 0 does not see step 2 (the next episode)
    torch.testing.assert_close(advantages[:, 0], torch.tensor([a0, a1, a2]))


@pytest.mark.parametrize("env_id", ["walker-walk", "button-press", "ConstantPenalty-v0"])
def test_an_episode_is_a_function_of_its_seed_and_actions(env_id):
    """What --resume relies on: an env reset with the episode's seed and given the same actions goes through
    exactly the same states, whatever the env did before (another episode, other actions)."""
    env, _ = prefppo.make_env(env_id)
    actions = np.random.default_rng(0).uniform(-1, 1, (30, env.action_space.shape[0])).astype(np.float32)
    first = [env.reset(seed=123)[0]] + [env.step(a)[0] for a in actions]
    other, _ = prefppo.make_env(env_id)  # a fresh env, first moved through another episode
    other.reset(seed=7)
    for a in actions[::-1]:
        other.step(a)
    second = [other.reset(seed=123)[0]] + [other.step(a)[0] for a in actions]
    np.testing.assert_array_equal(np.array(first), np.array(second))
    assert not np.array_equal(env.reset(seed=124)[0], first[0])  # another seed, another episode
    assert env.observation_space.dtype == np.float32 and first[-1].dtype == np.float32


def test_runs_with_different_seeds_share_no_episode_seed():
    # 32 training envs, 100 episodes each (episode j of env i: number j * 32 + i), and 3200 evaluation episodes
    seeds = {run: {prefppo.episode_seed(run, stream, n) for stream in (prefppo.TRAIN_STREAM, prefppo.EVAL_STREAM)
                   for n in range(32 * 100)} for run in (1, 2)}
    assert len(seeds[1]) == len(seeds[2]) == 2 * 32 * 100  # all different within a run, evaluation env included
    assert not seeds[1] & seeds[2]  # env i used to get seed + i: runs 1 and 2 shared 31 of 32 envs
    assert prefppo.episode_seed(1, 0, 0) == prefppo.episode_seed(1, 0, 0)  # reproducible
    assert all(0 <= s < 2**32 for s in seeds[1])  # dm_control's RandomState takes 32-bit seeds


def test_the_env_adapter_warns_about_no_float32_cast(recwarn):
    for env_id in ("quadruped-walk", "walker-walk", "Pendulum-v1"):
        env, _ = prefppo.make_env(env_id)
        env.reset(seed=0)
    assert not [w for w in recwarn if "precision lowered" in str(w.message)]


def test_rollout_reward_is_the_ensemble_mean_of_the_stored_raw_observation_and_action():  # a check of the shapes
    torch.manual_seed(0)
    model = prefppo.RewardEnsemble(obs_dim=3, action_dim=2, size=3)
    raw_obs, actions = torch.randn(4, 5, 3), torch.rand(4, 5, 2) * 2 - 1
    with torch.no_grad():  # the rollout's reward, as the main loop computes it
        rewards = model(torch.cat([raw_obs, actions], dim=-1)).mean(0)[..., 0]
    assert rewards.shape == (4, 5)
    t, n = 2, 3
    by_hand = torch.stack([m(torch.cat([raw_obs[t, n], actions[t, n]])) for m in model.members]).mean()
    assert rewards[t, n].item() == pytest.approx(by_hand.item(), rel=1e-6)
    assert rewards.abs().max() <= 1  # tanh-bounded


def test_running_mean_std_matches_numpy_and_normalises_as_vecnormalize():
    rng = np.random.default_rng(0)
    batches = [rng.normal(2.0, 3.0, size=(n, 4)).astype(np.float32) for n in (1, 32, 7)]
    running = prefppo.RunningMeanStd()
    for batch in batches:
        running.update(batch)
    everything = np.concatenate(batches)
    np.testing.assert_allclose(running.mean.numpy(), everything.mean(0), rtol=1e-4)
    np.testing.assert_allclose(running.var.numpy(), everything.var(0), rtol=1e-4)
    far = np.array([[2.0, 2.0, 1e3, -1e3]], np.float32)  # clipped to +-10 (SB3's VecNormalize)
    normalised = running.normalize(far)
    assert normalised.dtype == torch.float32 and normalised[0, 2] == 10 and normalised[0, 3] == -10
    assert abs(normalised[0, 0].item() - (2.0 - running.mean[0].item()) / math.sqrt(running.var[0].item())) < 1e-5


def assert_orthogonal(weight: torch.Tensor, gain: float):
    """W W^T = gain^2 I (rows orthonormal) or W^T W = gain^2 I (columns), whichever side is the smaller."""
    product = weight @ weight.T if weight.shape[0] <= weight.shape[1] else weight.T @ weight
    torch.testing.assert_close(product, gain**2 * torch.eye(len(product)), atol=1e-5, rtol=1e-4)


def test_networks_start_with_sb3_orthogonal_init():
    torch.manual_seed(0)
    actor, critic = prefppo.Actor(24, 6, 64, 3, use_sde=True), prefppo.make_critic(24, 64, 3)
    actor_hidden = [m for m in actor.policy[:-1] if isinstance(m, torch.nn.Linear)]
    critic_linear = [m for m in critic if isinstance(m, torch.nn.Linear)]
    assert len(actor_hidden) == len(critic_linear) - 1 == 3
    for layer in actor_hidden + critic_linear[:-1]:  # hidden layers: gain sqrt(2)
        assert_orthogonal(layer.weight.detach(), math.sqrt(2))
    assert_orthogonal(actor.policy[-1].weight.detach(), 0.01)  # policy output: 0.01
    assert_orthogonal(critic_linear[-1].weight.detach(), 1.0)  # value output: 1
    for layer in actor_hidden + critic_linear + [actor.policy[-1]]:
        assert not layer.bias.any()
    assert actor.log_std.shape == (64, 6) and not actor.log_std.any()  # gSDE: one log std 0 per feature and action
    assert prefppo.Actor(24, 6, 64, 3, use_sde=False).log_std.shape == (6,)


def test_gsde_std_of_a_hand_built_case():
    latent = torch.tensor([[1.0, 2.0]])
    log_std = torch.log(torch.tensor([[1.0, 2.0], [3.0, 1.0]]))
    # action 0: 1^2 * 1^2 + 2^2 * 3^2 = 37; action 1: 1^2 * 2^2 + 2^2 * 1^2 = 8 (+ SB3's 1e-6)
    torch.testing.assert_close(prefppo.sde_std(latent, log_std), torch.tensor([[37 + 1e-6, 8 + 1e-6]]).sqrt())


def test_gsde_log_prob_is_the_normal_of_the_latent_std():
    torch.manual_seed(0)
    actor = prefppo.Actor(5, 3, 16, 2, use_sde=True)
    with torch.no_grad():
        actor.log_std.copy_(torch.randn(16, 3) * 0.5)
    obs = torch.randn(4, 5)
    action, log_prob = actor.sample(obs, step=0, sde_freq=4)
    with torch.no_grad():  # the same by hand: latent, per-sample std, a diagonal Normal
        latent = actor.policy[:-1](obs)
        std = torch.sqrt((latent**2).unsqueeze(-1).mul(actor.log_std.exp() ** 2).sum(1) + 1e-6)  # sum over features
        direct = torch.distributions.Normal(actor.policy[-1](latent), std).log_prob(action).sum(-1)
        entropy = torch.distributions.Normal(actor.policy[-1](latent), std).entropy()
    torch.testing.assert_close(log_prob, direct)
    distribution, _ = actor.distribution(obs)  # what the PPO update evaluates
    torch.testing.assert_close(distribution.log_prob(action).sum(-1), direct)
    torch.testing.assert_close(distribution.entropy(), entropy)


def test_gsde_action_is_the_mean_plus_the_latent_times_the_env_matrix():
    torch.manual_seed(0)
    actor = prefppo.Actor(5, 3, 16, 2, use_sde=True)
    obs = torch.randn(4, 5)
    with torch.no_grad():
        action, _ = actor.sample(obs, step=0, sde_freq=4)
        latent = actor.policy[:-1](obs)
        for n in range(4):
            torch.testing.assert_close(action[n], actor.policy[-1](latent[n]) + latent[n] @ actor.exploration[n])
    # the noise that the matrices give has the std that the log-probability uses (20000 draws, 3% tolerance)
    with torch.no_grad():
        one_state = obs[:1].expand(20_000, 5)
        noise = actor.sample(one_state, step=0, sde_freq=4)[0] - actor.policy(one_state)
        expected = prefppo.sde_std(actor.policy[:-1](obs[:1]), actor.log_std)[0]
    torch.testing.assert_close(noise.std(0), expected, rtol=0.03, atol=0)


def test_gsde_noise_is_kept_for_sde_freq_steps_and_differs_between_envs():
    torch.manual_seed(0)
    actor = prefppo.Actor(5, 3, 16, 2, use_sde=True)
    obs = torch.randn(1, 5).expand(2, 5)  # two envs in the same state
    with torch.no_grad():
        noise = torch.stack([actor.sample(obs, step, sde_freq=4)[0] - actor.policy(obs) for step in range(8)])
    for step in (1, 2, 3):
        torch.testing.assert_close(noise[step], noise[0])  # steps 0-3: one matrix per env
        torch.testing.assert_close(noise[4 + step], noise[4])  # steps 4-7: the next one
    assert not torch.allclose(noise[4], noise[0], atol=1e-3)  # a new matrix at step 4
    assert not torch.allclose(noise[0, 0], noise[0, 1], atol=1e-3)  # each env its own matrix
    with torch.no_grad():  # step 0 of the next rollout draws again
        assert not torch.allclose(actor.sample(obs, 0, sde_freq=4)[0] - actor.policy(obs), noise[4], atol=1e-3)


def test_value_reset_redraws_only_the_output_layer_and_keeps_the_optimizer():
    torch.manual_seed(0)
    critic = prefppo.make_critic(5, 16, 2)
    optimizer = torch.optim.Adam(critic.parameters(), lr=1e-2, eps=1e-5)
    for _ in range(3):  # trained a little: the optimizer has moments, the output layer has moved
        optimizer.zero_grad()
        ((critic(torch.randn(32, 5))[:, 0] - 3.0) ** 2).mean().backward()
        optimizer.step()
    before = {name: p.detach().clone() for name, p in critic.named_parameters()}
    moments = {id(p): {k: v.clone() for k, v in optimizer.state[p].items()} for p in critic.parameters()}
    params_before = list(critic.parameters())
    prefppo.reset_value_head(critic)
    hidden = [name for name in before if not name.startswith(f"{len(critic) - 1}.")]
    assert len(hidden) == 4  # two hidden layers' weights and biases
    for name in hidden:
        torch.testing.assert_close(dict(critic.named_parameters())[name], before[name], rtol=0, atol=0)
    output = critic[-1]
    assert not torch.equal(output.weight, before[f"{len(critic) - 1}.weight"])
    assert_orthogonal(output.weight.detach(), 1.0)
    assert not output.bias.any()
    # the same parameter objects, still the optimizer's, with their Adam moments untouched
    assert all(a is b for a, b in zip(critic.parameters(), params_before))
    assert all(any(p is q for q in optimizer.param_groups[0]["params"]) for p in critic.parameters())
    for p in critic.parameters():
        for key, value in moments[id(p)].items():
            torch.testing.assert_close(optimizer.state[p][key], value, rtol=0, atol=0)


def test_ppo_policy_loss_is_the_clipped_surrogate_of_a_hand_computed_case():
    log_prob = torch.log(torch.tensor([1.5, 0.5, 1.1]))  # ratios 1.5, 0.5, 1.1 against old log-probs 0
    advantages = torch.tensor([1.0, -1.0, 2.0])
    loss, ratio = prefppo.ppo_policy_loss(log_prob, torch.zeros(3), advantages, clip=0.2)
    torch.testing.assert_close(ratio, torch.tensor([1.5, 0.5, 1.1]))
    # max(-A r, -A clip(r)): 0: max(-1.5, -1.2) = -1.2; 1: max(0.5, 0.8) = 0.8; 2: inside the range, -2.2
    assert loss.item() == pytest.approx((-1.2 + 0.8 - 2.2) / 3)
    # where the clip binds the gradient is zero: only sample 2 moves the policy
    log_prob.requires_grad_(True)
    prefppo.ppo_policy_loss(log_prob, torch.zeros(3), advantages, clip=0.2)[0].backward()
    torch.testing.assert_close(log_prob.grad, torch.tensor([0.0, 0.0, -2.0 * 1.1 / 3]))


def test_ppo_loss_is_the_surrogate_plus_the_weighted_value_loss_and_compiles_to_the_same_numbers():
    torch.manual_seed(0)
    actor, critic = prefppo.Actor(5, 3, 16, 2, use_sde=True), prefppo.make_critic(5, 16, 2)
    obs, actions, old_logprobs = torch.randn(32, 5), torch.randn(32, 3), torch.randn(32)
    advantages, returns, clip = torch.randn(32), torch.randn(32), torch.tensor(0.3)
    args = prefppo.Args(vf_coef=0.5, ent_coef=0.01)
    loss, stats = prefppo.ppo_loss(actor, critic, obs, actions, old_logprobs, advantages, returns, clip, args)
    distribution, _ = actor.distribution(obs)  # by hand: the parts, advantages normalised over the minibatch
    adv = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    policy_loss, ratio = prefppo.ppo_policy_loss(distribution.log_prob(actions).sum(-1), old_logprobs, adv, 0.3)
    entropy = distribution.entropy().sum(-1).mean()
    expected = policy_loss + 0.5 * F.mse_loss(critic(obs)[:, 0], returns) - 0.01 * entropy
    torch.testing.assert_close(loss, expected)
    assert stats["clipfrac"].item() == pytest.approx(((ratio - 1).abs() > 0.3).float().mean().item())
    # --compile: the same loss and gradients up to float rounding
    compiled = torch.compile(prefppo.ppo_loss)
    grads = []
    for loss_fn in (prefppo.ppo_loss, compiled):
        actor.zero_grad(), critic.zero_grad()
        loss_fn(actor, critic, obs, actions, old_logprobs, advantages, returns, clip, args)[0].backward()
        grads.append([p.grad.clone() for p in [*actor.parameters(), *critic.parameters()]])
    for eager, compiled_grad in zip(*grads):
        torch.testing.assert_close(compiled_grad, eager, rtol=1e-4, atol=1e-6)


def test_approx_kl_stays_finite_where_an_action_has_become_far_less_likely():
    # button-press seed 2 stopped at 220K on an infinite approx_kl: exp(-200) underflows to 0, log(0) = -inf
    torch.manual_seed(0)
    actor, critic = prefppo.Actor(5, 3, 16, 2, use_sde=True), prefppo.make_critic(5, 16, 2)
    obs, actions = torch.randn(4, 5), torch.randn(4, 3)
    with torch.no_grad():
        log_prob = actor.distribution(obs)[0].log_prob(actions).sum(-1)
    old_logprobs = log_prob + torch.tensor([200.0, 0.0, 0.0, 0.0])
    _, stats = prefppo.ppo_loss(actor, critic, obs, actions, old_logprobs, torch.randn(4), torch.randn(4),
                                torch.tensor(0.3), prefppo.Args())
    # (r - 1) - log r per sample: (0 - 1) + 200 for the first, 0 for the others
    assert stats["approx_kl"].item() == pytest.approx(199 / 4, rel=1e-5)


def test_the_value_loss_is_weighted_once_by_vf_coef():
    assert prefppo.Args().vf_coef == 0.5  # 0.5 x MSE in the total loss (reference code: SB3), not 0.25


def test_clip_range_decays_linearly_from_its_initial_value_to_zero():
    total = 4_000_000
    assert prefppo.clip_range(0.4, 0, total) == pytest.approx(0.4)
    assert prefppo.clip_range(0.4, 16_000, total) == pytest.approx(0.4 * (1 - 16_000 / total))  # first update
    assert prefppo.clip_range(0.4, total // 2, total) == pytest.approx(0.2)
    assert prefppo.clip_range(0.4, total, total) == 0.0
    assert prefppo.clip_range(0.4, total + 16_000, total) == 0.0  # a last rollout past the total: never negative


def test_ppo_epochs_default_to_the_reference_runs():
    args = prefppo.Args()
    assert (args.update_epochs, args.unsup_update_epochs) == (20, 50)


def test_knn_reward_scores_each_state_against_every_pretraining_state_so_far():
    knn = prefppo.KnnStateEntropy(k=1)
    first = knn(torch.tensor([[0.0], [3.0]]))  # buffer {0, 3}: each one's nearest other state is 3 away
    second = knn(torch.tensor([[1.0], [10.0]]))  # buffer {0, 3, 1, 10}: 1 is 1 from 0, 10 is 7 from 3
    # within this step alone 1 and 10 would be 9 apart; distances so far 3, 3, 1, 7: running var 19 / 4
    std = math.sqrt(19 / 4)
    np.testing.assert_allclose(second.numpy(), [1 / std, 7 / std], rtol=1e-3)
    assert first[0] == first[1] > 0 and len(knn.states) == 4


def test_knn_distance_skips_the_state_itself():
    states = torch.tensor([[0.0], [1.0], [3.0], [7.0]])
    # k = 1: nearest other state; k = 2: second nearest (by hand: 0 -> 1, 3; 1 -> 1, 2; 3 -> 2, 3; 7 -> 4, 6)
    torch.testing.assert_close(prefppo.knn_distance(states, states, 1)[:, 0], torch.tensor([1.0, 1.0, 2.0, 4.0]))
    torch.testing.assert_close(prefppo.knn_distance(states, states, 2)[:, 0], torch.tensor([3.0, 2.0, 3.0, 6.0]))


@pytest.mark.parametrize("env_id, epochs", [("walker-walk", 100), ("quadruped-walk", 100), ("cheetah-run", 100),
                                            ("button-press", 50), ("sweep-into", 50), ("Pendulum-v1", 100)])
def test_reward_model_epochs_follow_the_reference_runs(env_id, epochs):
    assert prefppo.task_defaults(env_id, "oracle").reward_epochs == epochs


def test_the_configuration_names_every_teacher_field(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["prefppo.py", "--teacher", "myopic", "--teacher-eps-mistake", "0.2"])
    myopic = prefppo.parse_args()
    assert (myopic.teacher_beta, myopic.teacher_gamma, myopic.teacher_eps_mistake, myopic.teacher_eps_skip,
            myopic.teacher_eps_equal) == (math.inf, 0.9, 0.2, 0.0, 0.0)  # the preset's gamma, the flag's eps_mistake
    assert prefppo.task_defaults("walker-walk", "stoc").teacher_beta == 1.0


def test_query_pool_keeps_every_episode_by_default():
    assert prefppo.Args().query_recent_episodes == 0  # the main loop's deque(maxlen=None): every episode


def test_query_sampler_and_teacher_draw_independent_streams():
    sampler_seed, teacher_seed, _ = prefppo.numpy_seeds(1)
    teacher = prefppo.make_teacher("stoc", seed=teacher_seed)
    # with one seed for both (the old behaviour) these draws were the same numbers
    assert not np.array_equal(np.random.default_rng(sampler_seed).random(8), teacher.rng.random(8))


@pytest.mark.parametrize("env_id", ["walker-walk", "quadruped-walk", "button-press", "sweep-into"])
def test_presets_spend_their_whole_budget_at_rollout_ends(env_id):
    args = prefppo.task_defaults(env_id, "oracle")
    sizes = schedule_sizes("uniform", args.max_feedback, args.feedback_per_session)
    rollout = args.num_envs * args.num_steps  # prefppo's sessions: at rollout ends, from the end of pre-training
    assert planned_labels(sizes, args.unsup_steps, args.feedback_every, args.total_timesteps - 1, rollout) == \
        args.max_feedback


@pytest.mark.parametrize("edit", ["no-bootstrap-time-limits", "stale-reward-inputs", "raw-reward-inputs"])
def test_the_reference_ways_fit_the_script(edit):
    sys.path.insert(0, str(ROOT / "benchmarks" / "reference"))
    import edits

    assert edits.edited_source("prefppo.py", [edit]) != (ROOT / "prefppo.py").read_text()


# ---------------------------------------------------------------- smoke runs


def check_complete_run(out, result, n_sessions: int, obs_dim: int, segment_len: int):
    assert result.returncode == 0, result.stderr[-3000:]
    assert len(session_lines(result.stdout)) == n_sessions
    rows = eval_rows(out)
    assert {"step", "episode_return", "success_rate", "feedback", "reward_correlation"} <= set(rows[0])
    assert math.isfinite(float(rows[-1]["reward_correlation"]))
    labels = saved_labels(out)
    assert len(labels) == n_sessions
    for session in labels:
        n = len(session["y"])
        assert session["obs0"].shape == session["obs1"].shape == (n, segment_len, obs_dim)
        assert session["rewards0"].shape == (n, segment_len)
        # the oracle's labels agree with the saved true rewards of the saved (raw) segments
        np.testing.assert_array_equal(session["y"], (session["rewards1"].sum(1) > session["rewards0"].sum(1)).astype(float))
    # segments hold the executed (clipped) actions: the initial gSDE policy (std = the latent's norm, over 1)
    # samples outside [-1, 1] most of the time
    actions = np.abs(np.concatenate([np.concatenate([s["actions0"], s["actions1"]]).ravel() for s in labels]))
    assert actions.max() <= 1.0 and (actions == 1.0).mean() > 0.05
    assert (out / "final_model.pt").exists()
    return rows


def test_smoke_dmc_walker_reaches_every_phase(tmp_path):
    out = tmp_path / "walker"
    result = run_prefppo(out, "--env-id", "walker-walk", "--total-timesteps", "5000", "--unsup-steps", "2000",
                         "--num-envs", "2", "--num-steps", "500", "--minibatch-size", "250", "--feedback-every", "1000",
                         "--max-feedback", "30", "--feedback-per-session", "10", "--segment-len", "10",
                         "--eval-every", "2500", *TINY, "--unsup-update-epochs", "3")
    rows = check_complete_run(out, result, n_sessions=3, obs_dim=24, segment_len=10)
    assert [int(r["step"]) for r in rows] == [3000, 5000]
    assert "done: 3 feedback sessions, 30 queries; outputs in" in result.stdout
    config = json.loads((out / "config.json").read_text())
    assert config["gae_lambda"] == 0.92 and config["learning_rate"] == 5e-5  # walker-walk preset
    assert config["teacher_gamma"] == 1.0 and config["teacher_beta"] == math.inf  # the oracle, written out
    # Pre-training: the 2 rollouts before the first session (step 2000), their kNN reward over each of their
    # 2000 states; 3 epochs of 4 minibatches each; then 3 rollouts on r_hat, 2 epochs each
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert state["progress"]["global_step"] == 5000 and state["progress"]["pretrained"]
    assert len(state["knn_reward"]["states"]) == 2000
    assert adam_steps(out) == 2 * 3 * 4 + 3 * 2 * 4
    logged = scalars(out)
    assert [step for step, _ in logged["losses/value_loss"]] == [1000, 2000, 3000, 4000, 5000]
    # r_hat against the true reward over each rollout on the learned reward (not the 2 of pre-training)
    correlations = logged["reward/rollout_correlation"]
    assert [step for step, _ in correlations] == [3000, 4000, 5000]
    assert all(-1 <= value <= 1 for _, value in correlations)


def test_smoke_metaworld_button_press_reaches_every_phase(tmp_path):
    out = tmp_path / "button"
    result = run_prefppo(out, "--env-id", "button-press", "--total-timesteps", "3000", "--unsup-steps", "1000",
                         "--num-envs", "2", "--num-steps", "250", "--minibatch-size", "125", "--feedback-every", "500",
                         "--max-feedback", "30", "--feedback-per-session", "10", "--segment-len", "10",
                         "--eval-every", "1500", *TINY)
    rows = check_complete_run(out, result, n_sessions=3, obs_dim=39, segment_len=10)
    assert all(0.0 <= float(r["success_rate"]) <= 1.0 for r in rows)


PENDULUM = ["--env-id", "Pendulum-v1", "--total-timesteps", "4800", "--unsup-steps", "1600", "--num-envs", "4",
            "--num-steps", "200", "--minibatch-size", "200", "--feedback-every", "800", "--max-feedback", "30",
            "--feedback-per-session", "10", "--segment-len", "10", "--eval-every", "4800", *TINY]


# Full schedules: every teacher's answers (stoc, mistake and myopic combined in one) and the samplers
TEACHER_RUNS = {
    "oracle": [],
    "equal": ["--teacher", "equal", "--sampler", "entropy-coverage"],
    "skip": ["--teacher", "skip", "--sampler", "uniform"],
    "stoc-mistake-myopic": ["--teacher", "myopic", "--teacher-beta", "1", "--teacher-eps-mistake", "0.1",
                            "--sampler", "entropy"],
}


@pytest.fixture(scope="module")
def teacher_runs(tmp_path_factory):
    """name -> (output dir, result) of each of TEACHER_RUNS (a repeated run gives the same run: test_resume.py)."""
    runs = {}
    for name, flags in TEACHER_RUNS.items():
        out = tmp_path_factory.mktemp("teachers") / name
        runs[name] = out, run_prefppo(out, *PENDULUM, *flags)
    return runs


@pytest.mark.parametrize("name", TEACHER_RUNS)
def test_every_teacher_and_the_samplers_run_a_full_schedule(name, teacher_runs):
    out, result = teacher_runs[name]
    assert result.returncode == 0, result.stderr[-3000:]
    assert len(session_lines(result.stdout)) == 3
    labels = saved_labels(out)
    y = np.concatenate([s["y"] for s in labels])
    keep = np.concatenate([s["keep"] for s in labels])
    assert len(y) == 30
    assert (~keep).any() == (name == "skip") and np.isnan(y[~keep]).all()
    assert (y == 0.5).any() == (name == "equal")


def test_reward_inputs_are_standardised_by_the_labelled_states(teacher_runs):
    assert_inputs_standardised_by_labelled_states(teacher_runs["oracle"][0], obs_dim=3)


def test_raw_reward_inputs_edit_gives_the_reward_model_raw_inputs(tmp_path):
    out = tmp_path / "raw"
    result = run_edited("raw-reward-inputs", out, *PENDULUM)
    assert result.returncode == 0, result.stderr[-3000:]
    assert len(session_lines(result.stdout)) == 3
    saved = torch.load(out / "final_model.pt", weights_only=True)["reward_model"]
    assert not saved["input_mean"].any() and (saved["input_std"] == 1).all()
    assert saved["input_clip"].item() == math.inf


def test_stale_reward_inputs_edit_keeps_the_normalised_observations_of_their_step(tmp_path, teacher_runs):
    ours, stale = teacher_runs["oracle"][0], tmp_path / "stale"
    result = run_edited("stale-reward-inputs", stale, *PENDULUM)
    assert result.returncode == 0, result.stderr[-3000:]
    saved = torch.load(stale / "final_model.pt", weights_only=True)["reward_model"]
    assert not saved["input_mean"].any() and saved["input_clip"].item() == math.inf  # no second normaliser
    # until the first session r_hat plays no part: the first queries are the same segments, kept as the
    # policy's observations, normalised by the running statistics of their step (clipped at 10)
    first_ours, first_stale = saved_labels(ours)[0], saved_labels(stale)[0]
    for side in ("0", "1"):
        np.testing.assert_array_equal(first_ours["actions" + side], first_stale["actions" + side])
        np.testing.assert_array_equal(first_ours["rewards" + side], first_stale["rewards" + side])
    raw_obs = np.concatenate([first_ours["obs0"], first_ours["obs1"]]).reshape(-1, 3)
    stale_obs = np.concatenate([first_stale["obs0"], first_stale["obs1"]]).reshape(-1, 3)
    assert not np.allclose(raw_obs, stale_obs) and np.abs(stale_obs).max() <= 10
    for feature in range(3):  # an affine map per feature whose statistics drift slowly
        assert np.corrcoef(raw_obs[:, feature], stale_obs[:, feature])[0, 1] > 0.9
    assert abs(stale_obs[:, 2].std() - 1) < abs(raw_obs[:, 2].std() - 1)  # the velocity, on the unit scale


def test_ground_truth_reward_runs_ppo_with_pretraining_and_no_teacher(tmp_path):
    out = tmp_path / "truth"
    result = run_prefppo(out, *PENDULUM, "--ground-truth-reward", "--unsup-update-epochs", "3")
    assert result.returncode == 0, result.stderr[-3000:]
    # 2 pre-training rollouts of 3 epochs, then 4 rollouts of --update-epochs 2 (TINY), 4 minibatches an epoch
    assert adam_steps(out) == 2 * 3 * 4 + 4 * 2 * 4
    assert len(torch.load(out / "checkpoint.pt", weights_only=True)["knn_reward"]["states"]) == 1600
    assert not session_lines(result.stdout) and not saved_labels(out)
    assert "reward/rollout_correlation" not in scalars(out)  # the true reward: no r_hat
    log_std = torch.load(out / "final_model.pt", weights_only=True)["actor"]["log_std"]
    assert log_std.shape == (32, 1) and log_std.any()  # gSDE by default: hidden 32 (TINY) x 1 action, trained


def test_no_use_sde_trains_a_state_independent_std_with_the_compiled_loss(tmp_path):
    out = tmp_path / "no_sde"  # --compile too: a whole run through the compiled ppo_loss
    result = run_prefppo(out, *PENDULUM, "--ground-truth-reward", "--total-timesteps", "2400", "--no-use-sde",
                         "--compile")
    assert result.returncode == 0, result.stderr[-3000:]
    assert adam_steps(out) == 3 * 2 * 4 and json.loads((out / "config.json").read_text())["compile"]
    log_std = torch.load(out / "final_model.pt", weights_only=True)["actor"]["log_std"]
    assert log_std.shape == (1,) and log_std.any()  # Pendulum's one action; trained away from its initial 0


def test_no_bootstrap_time_limits_gives_another_run(tmp_path, teacher_runs):
    first, result = teacher_runs["oracle"]
    # Pendulum ends every episode by its time limit: the reference's terminal ends change the updates
    terminal = run_edited("no-bootstrap-time-limits", tmp_path / "c", *PENDULUM)
    assert result.returncode == terminal.returncode == 0, terminal.stderr[-3000:]
    assert eval_curve(tmp_path / "c") != eval_curve(first)


TYRO_ERRORS = [  # tyro's own checks: its error box
    (["--teacher", "sleepy"], "invalid choice 'sleepy' for argument '--teacher'. Expected one of ('oracle', 'stoc', "
                              "'mistake', 'skip', 'equal', 'myopic', 'human')."),
    (["--sampler", "best"], "invalid choice 'best' for argument '--sampler'. Expected one of ('uniform',"),
    (["--schedule", "random"], "invalid choice 'random' for argument '--schedule'"),
    (["--num-envs", "two"], "Error parsing --num-envs"),
    (["--bogus-flag", "1"], "Unrecognized options: --bogus-flag"),
]
BAD_INPUTS = [  # our own checks: one line
    (["--env-id", "nowhere-walk"], "--env-id"),
    (["--max-feedback", "-5"], "--max-feedback must be >= 1"),
    (["--max-feedback", "100", "--feedback-per-session", "200"], "--feedback-per-session must be <= --max-feedback"),
    (["--segment-len", "5000"], "--segment-len must be in [1, 1000]"),
    (["--teacher-gamma", "1.5"], "gamma must be in (0, 1], got 1.5"),
    (["--teacher-beta", "-1"], "beta must be >= 0"),
    (["--num-envs", "2", "--num-steps", "10", "--minibatch-size", "64"], "--minibatch-size must be <= --num-envs x "
                                                                         "--num-steps (20), got 64"),
    (["--gae-lambda", "1.5"], "--gae-lambda must be in [0, 1], got 1.5"),
    (["--clip-coef", "0"], "--clip-coef must be > 0, got 0.0"),
    (["--max-grad-norm", "-1"], "--max-grad-norm must be > 0"),
    (["--seed", "-1"], "--seed must be >= 0, got -1"),
    (["--query-recent-episodes", "-1"], "--query-recent-episodes must be >= 0"),
    (["--unsup-steps", "5000000"], "--total-timesteps must be > --unsup-steps (5000000)"),
]


@pytest.fixture(scope="module")
def refused(tmp_path_factory):
    """Each command line of TYRO_ERRORS and BAD_INPUTS, run in one interpreter: flags -> (result, its output dir)."""
    cases = [flags for flags, _ in TYRO_ERRORS + BAD_INPUTS]
    outs = [tmp_path_factory.mktemp("refused") / "run" for _ in cases]
    results = run_in_one_interpreter("prefppo.py", list(zip(outs, cases)))
    return {" ".join(flags): (result, out) for flags, result, out in zip(cases, results, outs)}


@pytest.mark.parametrize("flags, message", TYRO_ERRORS, ids=[" ".join(f) for f, _ in TYRO_ERRORS])
def test_flags_tyro_cannot_parse_are_tyro_s_error_and_exit_2_before_training(flags, message, refused):
    result, out = refused[" ".join(flags)]
    assert_refused_by_tyro(result, message, out)


@pytest.mark.parametrize("flags, message", BAD_INPUTS, ids=[" ".join(f) for f, _ in BAD_INPUTS])
def test_bad_input_is_one_line_and_a_nonzero_exit_before_training(flags, message, refused):
    result, out = refused[" ".join(flags)]
    assert_rejected(result, message, out)


def test_a_bad_input_ends_the_process_itself_with_one_line(tmp_path):  # the cases above share one process
    assert_rejected(run_prefppo(tmp_path / "run", "--seed", "-1", timeout=120), "--seed must be >= 0", tmp_path / "run")


def test_help_lists_the_choices_and_the_tasks_preset(tmp_path):
    result = run_prefppo(tmp_path / "run", "--help", timeout=120)
    assert result.returncode == 0 and "disagreement-coverage" in result.stdout and "myopic" in result.stdout
    assert "(default: 4000000)" in result.stdout  # walker-walk's total steps
    result = run_prefppo(tmp_path / "run", "--env-id", "button-press", "--help", timeout=120)
    assert "(default: 3000000)" in result.stdout and "(default: 25)" in result.stdout  # Meta-World's
