"""pebble.py: unit tests of the parts that can be wrong quietly, smoke runs that reach every phase
(pre-training updates, feedback sessions, reward learning, relabelling, critic reset, evaluation),
and bad input that must end with one line and a non-zero exit before any training."""

import importlib
import json
import math
import re
import types
import typing
import warnings

import numpy as np
import pytest
import torch

import pebble
from samplers import SAMPLERS, SCHEDULES, planned_labels, schedule_sizes, session_steps
from sim_teacher import TEACHERS, make_teacher
from tests.helpers import (assert_inputs_standardised_by_labelled_states, assert_refused_by_tyro, assert_rejected, eval_rows,
                           assert_pebble_phases, run_in_one_interpreter, run_script, scalars, saved_labels, session_lines)

TINY = ["--hidden-dim", "32", "--num-layers", "2", "--batch-size", "32", "--reward-epochs", "3",
        "--reward-batch-size", "32", "--eval-episodes", "1"]


def run_pebble(out, *flags, timeout=600):
    return run_script("pebble.py", out, *flags, timeout=timeout)


# ---------------------------------------------------------------- unit tests of the quiet parts


def test_tanh_gaussian_log_prob_matches_torch_distributions():
    torch.manual_seed(0)
    mean, log_std = torch.randn(64, 3), torch.rand(64, 3) * 4 - 3
    pre_tanh = mean + log_std.exp() * torch.randn(64, 3) * 2  # far into the tails too, where tanh saturates
    squashed = torch.distributions.TransformedDistribution(
        torch.distributions.Normal(mean.double(), log_std.exp().double()), torch.distributions.TanhTransform())
    expected = squashed.log_prob(torch.tanh(pre_tanh.double()).clamp(-1 + 1e-12, 1 - 1e-12)).sum(-1, keepdim=True)
    got = pebble.tanh_gaussian_log_prob(mean, log_std, pre_tanh)
    moderate = pre_tanh.abs().max(-1).values < 3  # float64 tanh is exact enough there to invert
    torch.testing.assert_close(got[moderate].double(), expected[moderate], rtol=1e-4, atol=1e-4)
    # by hand, one dimension, u = 0, std 1: log N(0; 0, 1) - log(1 - tanh(0)^2) = -log(2 pi) / 2
    assert pebble.tanh_gaussian_log_prob(torch.zeros(1, 1), torch.zeros(1, 1), torch.zeros(1, 1)).item() == \
        pytest.approx(-0.5 * math.log(2 * math.pi))


def test_sac_critic_loss_by_hand():
    q1, q2 = torch.tensor([[1.0], [0.0]]), torch.tensor([[2.0], [0.0]])
    rewards, terminated = torch.tensor([[1.0], [1.0]]), torch.tensor([[0.0], [1.0]])
    next_q, next_log_prob = torch.tensor([[3.0], [100.0]]), torch.tensor([[-1.0], [5.0]])
    # targets: 1 + 0.5 * (3 - 0.2 * -1) = 2.6; the second terminated: 1 (nothing bootstrapped)
    # q1 errors 1.6, 1 -> mean 1.78; q2 errors 0.6, 1 -> mean 0.68
    loss = pebble.sac_critic_loss(q1, q2, rewards, terminated, next_q, next_log_prob, alpha=0.2, gamma=0.5)
    assert loss.item() == pytest.approx((1.6**2 + 1) / 2 + (0.6**2 + 1) / 2)


def test_sac_actor_loss_uses_the_smaller_critic():
    log_prob = torch.tensor([[-1.0], [2.0]])
    q1, q2 = torch.tensor([[5.0], [0.0]]), torch.tensor([[3.0], [4.0]])
    # (0.5 * -1 - 3 + 0.5 * 2 - 0) / 2 = -1.25
    assert pebble.sac_actor_loss(log_prob, q1, q2, alpha=0.5).item() == pytest.approx(-1.25)


def test_temperature_loss_raises_alpha_when_entropy_is_below_target():
    log_alpha = torch.tensor(math.log(0.1), requires_grad=True)
    log_prob = torch.tensor([[1.0], [3.0]])  # entropy estimate -2, below the target -1 (one action dimension)
    loss = pebble.temperature_loss(log_alpha, log_prob, target_entropy=-1.0)
    assert loss.item() == pytest.approx(0.1 * (-2 + 1))  # alpha * mean(-log pi - target)
    loss.backward()
    assert log_alpha.grad.item() == pytest.approx(-0.1)  # gradient descent raises log alpha
    high_entropy = pebble.temperature_loss(log_alpha, torch.tensor([[-3.0]]), target_entropy=-1.0)
    assert high_entropy.item() == pytest.approx(0.1 * 4)  # entropy 3 above -1: descent lowers alpha


def test_sac_update_steps_each_network_on_its_own_loss_only():
    """The actor's loss backpropagates through the critics to the actions but computes no gradient for the critics'
    weights (optimize's backward inputs); the temperature's loss reaches neither network."""
    torch.manual_seed(0)
    actor, critic = pebble.Actor(3, 2, 16, 2), pebble.TwinCritic(3, 2, 16, 2)
    log_alpha = torch.zeros((), requires_grad=True)
    actor_opt, critic_opt, alpha_opt = (pebble.adam(p, 1e-3) for p in (actor.parameters(), critic.parameters(),
                                                                       [log_alpha]))
    batch = pebble.Batch(torch.randn(8, 3), torch.rand(8, 2) * 2 - 1, torch.randn(8, 1), torch.randn(8, 3),
                         torch.zeros(8, 1))
    critic_before = [p.clone() for p in critic.parameters()]
    actions, log_prob = actor.sample(batch.obs)
    pebble.optimize(actor_opt, pebble.sac_actor_loss(log_prob, *critic(batch.obs, actions), 0.1))
    assert all(p.grad is None for p in critic.parameters())  # no critic gradient was computed
    assert all(torch.equal(p, q) for p, q in zip(critic.parameters(), critic_before))
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor.parameters())
    losses = pebble.sac_update(batch, batch.rewards, actor, critic, pebble.TwinCritic(3, 2, 16, 2), log_alpha,
                               actor_opt, critic_opt, alpha_opt, 0.99)
    assert log_alpha.item() != 0 and all(torch.isfinite(v) for v in losses.values())
    assert all(isinstance(opt, torch.optim.Adam) and opt.defaults["fused"] for opt in (actor_opt, critic_opt, alpha_opt))


def test_the_compiled_sac_update_is_the_eager_one_traced():
    """--compile wraps sac_update itself. Traced by torch.compile with the aot_eager backend (the same kernels, so
    the same random draws; on a GPU inductor's kernels and CUDA graphs run the same graphs), five updates from the
    same start give the eager run's losses and weights."""
    import torch._dynamo

    def five_updates(update):
        torch.manual_seed(0)
        actor, critic, target = pebble.Actor(3, 2, 16, 2), *(pebble.TwinCritic(3, 2, 16, 2) for _ in range(2))
        log_alpha = torch.zeros((), requires_grad=True)
        optimizers = [pebble.adam(p, 1e-3) for p in (actor.parameters(), critic.parameters(), [log_alpha])]
        batch = pebble.Batch(torch.randn(8, 3), torch.rand(8, 2) * 2 - 1, torch.randn(8, 1), torch.randn(8, 3),
                             torch.zeros(8, 1))
        losses = [update(batch, batch.rewards, actor, critic, target, log_alpha, *optimizers, 0.99)
                  for _ in range(5)]
        return losses, [*actor.parameters(), *critic.parameters(), log_alpha]

    torch._dynamo.reset()
    eager_losses, eager_weights = five_updates(pebble.sac_update)
    losses, weights = five_updates(torch.compile(pebble.sac_update, backend="aot_eager"))
    for eager, compiled in zip(eager_losses, losses):
        assert {name: pytest.approx(value.item(), rel=1e-5, abs=1e-6) for name, value in eager.items()} == {
            name: value.item() for name, value in compiled.items()}
    assert all(torch.allclose(a, b, rtol=1e-5, atol=1e-6) for a, b in zip(eager_weights, weights))
    torch.manual_seed(0)
    assert not torch.allclose(eager_weights[0], pebble.Actor(3, 2, 16, 2).net[0].weight)  # the updates moved it


def test_choices_are_the_modules_names():
    annotations = pebble.Args.__annotations__
    assert typing.get_args(annotations["teacher"]) == (*TEACHERS, "human")  # human: a person, label_server.py
    assert typing.get_args(annotations["sampler"]) == tuple(SAMPLERS)
    assert typing.get_args(annotations["schedule"]) == tuple(SCHEDULES)


@pytest.mark.parametrize("env_id", ["quadruped-walk", "button-press", "Pendulum-v1"])
def test_env_adapter_has_float32_spaces_and_warns_nothing(env_id):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env, _ = pebble.make_env(env_id)
        obs, _ = env.reset(seed=0)
    assert not [str(w.message) for w in caught if "gymnasium" in w.filename or "Box" in str(w.message)]
    assert env.observation_space.dtype == env.action_space.dtype == obs.dtype == np.float32
    assert np.all(env.action_space.low == -1) and np.all(env.action_space.high == 1)


def test_knn_distance_is_kth_neighbour_not_counting_the_state_itself():
    points = torch.tensor([[0.0], [1.0], [3.0], [6.0], [10.0]])
    # from 0: others at 1, 3, 6, 10 -> 2nd neighbour at 3; from 6: others at 4, 3, 5, 6 -> 2nd is 4
    distances = pebble.knn_distance(points, points, k=2)
    assert distances[:, 0].tolist() == [3.0, 2.0, 3.0, 4.0, 7.0]


def test_intrinsic_reward_scores_the_batch_state_s_t_not_the_next_state():
    buffer = pebble.ReplayBuffer(capacity=8, obs_dim=1, action_dim=1)
    trajectory = [0.0, 1.0, 3.0, 6.0, 10.0, 15.0]  # s_0 .. s_5: transitions (s_t, s_t+1), s_5 never stored as obs
    for s, s_next in zip(trajectory, trajectory[1:]):
        buffer.add(np.array([s], np.float32), np.zeros(1, np.float32), 0.0, np.array([s_next], np.float32), False)
    # k = 2 among the stored states {0, 1, 3, 6, 10}, the state's own zero distance skipped (as in the test above)
    expected = {0.0: 3.0, 1.0: 2.0, 3.0: 3.0, 6.0: 4.0, 10.0: 7.0}
    # scoring next_obs would give 2, 3, 4, 7 for these states and 12 for s_4 (s_5 = 15 is not in the buffer)
    torch.manual_seed(0)
    batch = buffer.sample(20)
    rewards = pebble.intrinsic_reward(batch, buffer, k=2)
    assert rewards[:, 0].tolist() == [expected[s] for s in batch.obs[:, 0].tolist()]
    assert not torch.equal(rewards, pebble.knn_distance(batch.next_obs, buffer.obs[: buffer.size], k=2))


def test_running_mean_std_matches_numpy_over_all_batches():
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, size=n) for n in (5, 100, 1, 37)]
    stats = pebble.RunningMeanStd()
    for batch in batches:
        stats.update(torch.tensor(batch))
    everything = np.concatenate(batches)
    assert stats.mean == pytest.approx(everything.mean(), rel=1e-9)
    assert stats.var == pytest.approx(everything.var(), rel=1e-9)
    assert stats.count == len(everything)


def assert_orthogonal_with_zero_biases(state_dict: dict, atol: float = 1e-5, bias_atol: float = 0.0):
    """Every Linear weight W (out x in) has orthonormal rows (W W^T = I, out <= in) or columns (W^T W = I),
    and every bias is zero (within bias_atol)."""
    weights = {k: v for k, v in state_dict.items() if k.endswith(".weight")}
    assert weights
    for name, w in weights.items():
        gram = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
        torch.testing.assert_close(gram, torch.eye(len(gram)), atol=atol, rtol=0, msg=name)
        assert state_dict[name.removesuffix("weight") + "bias"].abs().max() <= bias_atol, name


@pytest.mark.parametrize("obs_dim, action_dim, hidden_dim, num_layers", [(24, 6, 64, 2), (100, 4, 32, 3)])
def test_actor_and_critic_start_orthogonal_with_zero_biases(obs_dim, action_dim, hidden_dim, num_layers):
    torch.manual_seed(0)  # (100, 4, 32, 3): first layers wider in than out, so both Gram forms are checked
    assert_orthogonal_with_zero_biases(pebble.Actor(obs_dim, action_dim, hidden_dim, num_layers).state_dict())
    assert_orthogonal_with_zero_biases(pebble.TwinCritic(obs_dim, action_dim, hidden_dim, num_layers).state_dict())
    default = torch.nn.Linear(hidden_dim, hidden_dim)  # PyTorch's own init is far from orthogonal
    assert not torch.allclose(default.weight @ default.weight.T, torch.eye(hidden_dim), atol=1e-2)


def test_query_sampler_teacher_and_random_actions_draw_independent_streams_from_one_seed():
    sampler_seed, teacher_seed, action_seed = pebble.numpy_seeds(1)
    sampler_draws = np.random.default_rng(sampler_seed).random(5)
    teacher_draws = make_teacher("stoc", seed=teacher_seed).rng.random(5)
    action_draws = np.random.default_rng(action_seed).random(5)
    assert not np.any(sampler_draws == teacher_draws) and not np.any(action_draws == sampler_draws)
    assert not np.any(action_draws == teacher_draws)
    # one seed for both, as before, gave the teacher the sampler's very numbers
    np.testing.assert_array_equal(np.random.default_rng(1).random(5), make_teacher("stoc", seed=1).rng.random(5))
    again = pebble.numpy_seeds(1)  # reproducible from the run seed, and another seed gives other streams
    np.testing.assert_array_equal(np.random.default_rng(again[0]).random(5), sampler_draws)
    np.testing.assert_array_equal(make_teacher("stoc", seed=again[1]).rng.random(5), teacher_draws)
    assert not np.any(np.random.default_rng(pebble.numpy_seeds(2)[0]).random(5) == sampler_draws)


def test_episode_seeds_differ_between_run_seeds_streams_and_episodes():
    def seeds(run_seed):
        return {pebble.episode_seed(run_seed, stream, n) for stream in (pebble.TRAIN_STREAM, pebble.EVAL_STREAM)
                for n in range(2000)}

    first, second = seeds(1), seeds(2)
    assert len(first) == len(second) == 4000  # no two episodes of a run (training or evaluation) share a seed
    assert not first & second  # runs with different seeds share none (seed + i schemes shared nearly all)
    assert pebble.episode_seed(1, 0, 7) == pebble.episode_seed(1, 0, 7)  # reproducible


def test_metaworld_segments_are_those_of_the_reference_runs_not_the_table():
    # the reference's Meta-World scripts never set `segment`: its runs used the default 50, the table says 25
    for env_id in ("button-press", "sweep-into", "walker-walk", "quadruped-walk"):
        assert pebble.task_defaults(env_id, "oracle").segment_len == 50
    assert pebble.task_defaults("button-press", "oracle").hidden_dim == 256  # the Meta-World preset
    assert pebble.task_defaults("button-press-v3", "oracle").feedback_every == 4950
    assert pebble.task_defaults("quadruped-walk", "oracle").learning_rate == 1e-4


@pytest.mark.parametrize("schedule", ["uniform", "decay", "increase"])
def test_presets_spend_their_whole_budget(schedule):
    first = pebble.Args.seed_steps + pebble.Args.unsup_steps + 1  # pebble's first session: right after pre-training
    for env_id in ("button-press", "walker-walk", "quadruped-walk"):
        preset = vars(pebble.task_defaults(env_id, "oracle"))
        steps = session_steps(first, preset["feedback_every"], preset["total_timesteps"])
        sizes = schedule_sizes(schedule, preset["max_feedback"], preset["feedback_per_session"], steps - 1,
                               preset["total_timesteps"])
        spent = planned_labels(sizes, first, preset["feedback_every"], preset["total_timesteps"])
        if env_id == "button-press" and schedule == "decay":  # as the reference's: sessions shrink
            assert spent == 9852  # linearly to ~1 query at 1M steps, 200 sessions ask 98.5% of the budget
        else:  # Meta-World: 10,000 in 200 sessions; walker-walk: 1000
            assert spent == preset["max_feedback"]
    # the paper's (and reference code's) every 5000 steps on Meta-World: 198 sessions of 50 fit in 1M steps
    assert planned_labels(schedule_sizes("uniform", 10_000, 50), first, 5000, 1_000_000) == 9900


def reset_draws(env, n: int, seed: int = 1, stream: int = pebble.TRAIN_STREAM) -> np.ndarray:
    """The random vector of n seeded resets: Meta-World's task variation (object and goal positions; MT1's 50 tasks
    are 50 fixed ones). Button-press moves its goal with it, sweep-into only its object."""
    draws = []
    for episode in range(n):
        obs, _ = env.reset(seed=pebble.episode_seed(seed, stream, episode))
        draws.append(env.unwrapped._last_rand_vec.copy())
        assert np.all(obs[-3:] == 0) and np.any(env.unwrapped._target_pos != 0)  # the goal is hidden (reference)
    return np.array(draws)


@pytest.mark.parametrize("env_id", ["button-press", "sweep-into"])
def test_metaworld_train_and_eval_goals_are_fresh_draws_from_the_whole_range(env_id):
    from scipy import stats

    n = 100
    train = reset_draws(pebble.make_env(env_id)[0], n)
    evaluation = reset_draws(pebble.make_env(env_id)[0], n, stream=pebble.EVAL_STREAM)  # the run's evaluation env
    # a fresh draw at every reset: MT1 alone draws from 50 fixed vectors, other ones for the eval env's seed
    assert len(np.unique(train, axis=0)) == len(np.unique(evaluation, axis=0)) == n
    space = pebble.make_env(env_id)[0].unwrapped._random_reset_space
    for draws in (train, evaluation):
        assert np.all((space.low <= draws) & (draws <= space.high))
    for i in np.flatnonzero(space.high > space.low):  # each coordinate that varies: uniform over its whole range
        # (sweep-into redraws objects within 0.15 of its goal, about 1% of the range: within the tolerance)
        uniform = stats.uniform(space.low[i], space.high[i] - space.low[i]).cdf
        assert stats.kstest(train[:, i], uniform).pvalue > 0.001
        assert stats.kstest(evaluation[:, i], uniform).pvalue > 0.001
        assert stats.ks_2samp(train[:, i], evaluation[:, i]).pvalue > 0.001  # one distribution for both envs
        width = space.high[i] - space.low[i]  # and both samples span nearly all of it
        assert train[:, i].max() - train[:, i].min() > 0.9 * width
        assert evaluation[:, i].max() - evaluation[:, i].min() > 0.9 * width


@pytest.mark.parametrize("env_id", ["button-press", "sweep-into"])
def test_metaworld_object_moves_between_resets_repeats_for_a_seed_and_episodes_last_500_steps(env_id):
    """What the agent sees: the object's position (observation 4:7) changes from one reset to the next and is the
    same again for the same episode seed; an episode is 500 steps, ended by the time limit only (the reference's
    v2 set-up: no termination on success)."""
    env, episode_len = pebble.make_env(env_id)
    seeds = [pebble.episode_seed(1, pebble.TRAIN_STREAM, episode) for episode in range(3)]
    objects = [env.reset(seed=seed)[0][4:7] for seed in seeds]
    assert not np.allclose(objects[0], objects[1]) and not np.allclose(objects[1], objects[2])
    np.testing.assert_array_equal(env.reset(seed=seeds[1])[0][4:7], objects[1])
    assert episode_len == 500
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        terminated, truncated = env.step(env.action_space.sample())[2:4]
        steps += 1
    assert steps == 500 and truncated and not terminated


def test_metaworld_goals_are_reproducible_from_the_seed():
    env = pebble.make_env("button-press")[0]
    first, again, other = (reset_draws(env, 5, seed) for seed in (3, 3, 4))
    np.testing.assert_array_equal(first, again)
    assert not np.any(np.all(first == other, axis=1))


def test_relabel_covers_the_whole_wrapped_buffer():
    torch.manual_seed(0)
    buffer = pebble.ReplayBuffer(capacity=10, obs_dim=3, action_dim=2)
    for i in range(25):  # wraps twice; the write position ends at 5
        buffer.add(np.full(3, i, np.float32), np.full(2, -i, np.float32), 123.0, np.zeros(3, np.float32), False)
    model = pebble.RewardEnsemble(3, 2, size=3)
    pebble.relabel(buffer, model, chunk=4)
    expected = model(torch.cat([buffer.obs, buffer.actions], dim=-1)).mean(0)
    assert buffer.pos == 5 and buffer.size == 10
    torch.testing.assert_close(buffer.rewards, expected)  # slots 5..9 too, not only the prefix before pos
    assert not (buffer.rewards == 123.0).any()


def test_a_checkpoint_holds_the_filled_part_of_the_replay_buffer_and_restores_it_exactly(tmp_path):
    """1,000 of 100,000 transitions: the saved buffer is 1% of the full one (a slice would save the whole tensor);
    a fresh buffer loaded from it samples what the original samples. Once wrapped, all of it, with its write
    position."""
    buffer = pebble.ReplayBuffer(capacity=100_000, obs_dim=24, action_dim=6)
    rng = np.random.default_rng(0)
    for _ in range(1000):
        buffer.add(rng.normal(size=24), rng.uniform(-1, 1, 6), rng.normal(), rng.normal(size=24), False)
    state = buffer.state_dict()
    assert state["size"] == state["pos"] == 1000 and {len(state[name]) for name in pebble.Batch._fields} == {1000}
    pebble.save_whole(str(tmp_path / "part.pt"), state)
    full = {name: getattr(buffer, name) for name in pebble.Batch._fields}
    pebble.save_whole(str(tmp_path / "full.pt"), full)
    assert (tmp_path / "part.pt").stat().st_size < 0.02 * (tmp_path / "full.pt").stat().st_size
    restored = pebble.ReplayBuffer(capacity=100_000, obs_dim=24, action_dim=6)
    restored.load_state_dict(torch.load(tmp_path / "part.pt", weights_only=True))
    for name in pebble.Batch._fields:
        assert torch.equal(getattr(restored, name), getattr(buffer, name))  # the rest zeros in both
    torch.manual_seed(1)
    sampled = buffer.sample(64)
    torch.manual_seed(1)
    assert all(torch.equal(a, b) for a, b in zip(sampled, restored.sample(64)))

    wrapped = pebble.ReplayBuffer(capacity=8, obs_dim=1, action_dim=1)
    for i in range(13):
        wrapped.add(np.array([i]), np.array([-i]), float(i), np.array([i + 1]), i % 2)
    again = pebble.ReplayBuffer(capacity=8, obs_dim=1, action_dim=1)
    again.load_state_dict(wrapped.state_dict())
    assert (again.size, again.pos) == (8, 5)
    assert again.obs[:, 0].tolist() == [8, 9, 10, 11, 12, 5, 6, 7]
    again.add(np.array([13]), np.array([-13]), 13.0, np.array([14]), False)  # overwrites the oldest, 5
    assert again.obs[5, 0] == 13


def test_the_critic_reset_draws_the_weights_a_new_twin_critic_draws():
    """In place (a CUDA graph holds the critic's tensors), with what the reference's new critic would have: under the
    same random state, the weights of TwinCritic(...)."""
    critic, target = pebble.TwinCritic(3, 2, 8, 2), pebble.TwinCritic(3, 2, 8, 2)
    held = list(critic.parameters())
    optimizer = pebble.adam(critic.parameters(), 1e-3)
    torch.manual_seed(7)
    pebble.reset_critic(critic, target, optimizer)
    torch.manual_seed(7)
    fresh = pebble.TwinCritic(3, 2, 8, 2)
    assert list(critic.parameters()) == held
    assert all(torch.equal(a, b) for a, b in zip(critic.state_dict().values(), fresh.state_dict().values()))
    assert all(torch.equal(a, b) for a, b in zip(target.state_dict().values(), fresh.state_dict().values()))


def test_preference_loss_is_cross_entropy_of_eq3():
    returns = torch.tensor([[0.0, 10.0], [2.0, 2.0]])
    # y = 1 (second preferred): -log sigmoid(10); y = 0 on equal returns: -log 0.5
    loss = pebble.preference_loss(returns, torch.tensor([1.0, 0.0]))
    assert loss.item() == pytest.approx((math.log1p(math.exp(-10)) + math.log(2)) / 2, rel=1e-6)


def test_equal_label_is_the_uniform_target_and_is_minimised_by_equal_returns():
    returns = torch.tensor([[1.0, 3.0]], requires_grad=True)
    loss = pebble.preference_loss(returns, torch.tensor([0.5]))
    p_second = 1 / (1 + math.exp(-2.0))
    assert loss.item() == pytest.approx(-0.5 * (math.log(1 - p_second) + math.log(p_second)), rel=1e-6)
    loss.backward()
    assert returns.grad[0, 1] > 0 > returns.grad[0, 0]  # pushes the two returns together
    balanced = torch.tensor([[2.0, 2.0]], requires_grad=True)
    pebble.preference_loss(balanced, torch.tensor([0.5])).backward()
    assert balanced.grad.abs().max() < 1e-7


def test_label_smoothing_softens_the_target_as_in_the_appendix():
    returns = torch.tensor([[0.0, math.log(19.0)]])  # P[second] = 0.95
    smoothed = pebble.preference_loss(returns, torch.tensor([1.0]), label_smoothing=0.1)
    entropy_095 = -(0.95 * math.log(0.95) + 0.05 * math.log(0.05))
    assert smoothed.item() == pytest.approx(entropy_095, rel=1e-6)  # target 0.95 matches P exactly


def test_accuracy_does_not_count_equal_labels():
    torch.manual_seed(0)
    model = pebble.RewardEnsemble(1, 1, 1)
    inputs0, inputs1 = torch.randn(2, 4, 3, 2).unbind()
    with torch.no_grad():
        first = model(inputs1).sum(2)[0, :, 0] < model(inputs0).sum(2)[0, :, 0]  # predicted "first"
    y = torch.tensor([0.5, 0.5, 0.0, 0.0])
    y[2:] = torch.where(first[2:], 0.0, 1.0)  # pair 2 as predicted
    y[3] = 1.0 - y[3]  # pair 3 against it
    args = types.SimpleNamespace(reward_epochs=1, reward_batch_size=4, label_smoothing=0.0)
    preferences = {"inputs0": inputs0, "inputs1": inputs1, "y": y}
    _, accuracy = pebble.train_reward(model, torch.optim.SGD(model.parameters(), lr=0.0), preferences, args)
    assert accuracy == 0.5  # 1 of the 2 strict labels; counting the equal ones would say 1 or 3 of 4


@pytest.mark.parametrize("script", ["pebble", "prefppo"])  # the same class in both
def test_reward_inputs_pass_unchanged_until_d_has_states_then_standardised_and_clipped(script):
    torch.manual_seed(0)
    model = importlib.import_module(script).RewardEnsemble(obs_dim=2, action_dim=1, size=2)
    far = torch.tensor([[1e3, -40.0, 0.5]])
    assert torch.equal(model.normalize(far), far)  # before the first session: nothing to standardise by
    states = torch.tensor([[1.0, 10.0], [3.0, 30.0]])  # mean (2, 20), std (1, 10)
    model.set_input_stats(states)
    x = torch.tensor([[2.0, 40.0, 0.5], [1e3, 20.0, -0.7]])
    torch.testing.assert_close(model.normalize(x), torch.tensor([[0.0, 2.0, 0.5], [10.0, 0.0, -0.7]]))
    by_hand = torch.stack([member(model.normalize(x)) for member in model.members])
    torch.testing.assert_close(model(x), by_hand)


def test_train_reward_learns_a_separable_preference():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    inputs0, inputs1 = (torch.tensor(rng.normal(size=(128, 5, 4)), dtype=torch.float32) for _ in range(2))
    y = (inputs1[..., 0].sum(1) > inputs0[..., 0].sum(1)).float()  # true reward: the first feature
    model = pebble.RewardEnsemble(obs_dim=2, action_dim=2, size=3)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    args = pebble.Args(reward_batch_size=64, reward_epochs=30)
    preferences = {"inputs0": inputs0, "inputs1": inputs1, "y": y}
    _, accuracy = pebble.train_reward(model, optimizer, preferences, args)
    assert accuracy > 0.9
    with torch.no_grad():
        held_out = torch.tensor(rng.normal(size=(200, 1, 4)), dtype=torch.float32)
        learned = model(held_out).mean(0)[:, 0, 0]
    assert np.corrcoef(learned.numpy(), held_out[:, 0, 0].numpy())[0, 1] > 0.8


def test_train_reward_feeds_the_members_the_normalised_inputs_the_model_predicts_on():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    scale = torch.tensor([50.0, 50.0, 1.0, 1.0])  # observations far from unit scale, actions in [-1, 1]
    inputs0, inputs1 = (torch.tensor(rng.normal(size=(128, 5, 4)), dtype=torch.float32) * scale + 200 for _ in "01")
    y = (inputs1[..., 0].sum(1) > inputs0[..., 0].sum(1)).float()  # true reward: the first feature
    model = pebble.RewardEnsemble(obs_dim=2, action_dim=2, size=3)
    model.set_input_stats(torch.cat([inputs0, inputs1], 1)[..., :2].flatten(0, 1))
    seen = []
    model.members[0].register_forward_hook(lambda module, args, output: seen.append(args[0].abs().max().item()))
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    preferences = {"inputs0": inputs0, "inputs1": inputs1, "y": y}
    _, accuracy = pebble.train_reward(model, optimizer, preferences, pebble.Args(reward_batch_size=64,
                                                                                reward_epochs=30))
    assert seen and max(seen) <= 10  # raw inputs reach ~400
    assert accuracy > 0.75  # chance: 0.5


def test_configuration_records_every_field_of_the_teacher(schedule_runs):
    myopic = pebble.task_defaults("Pendulum-v1", "myopic")
    resolved = {name: getattr(myopic, name) for name in vars(myopic) if name.startswith("teacher_")}
    assert resolved == {"teacher_beta": math.inf, "teacher_gamma": 0.9, "teacher_eps_mistake": 0.0,
                        "teacher_eps_skip": 0.0, "teacher_eps_equal": 0.0, "teacher_bias": 0.0}
    assert pebble.task_defaults("Pendulum-v1", "skip").teacher_eps_skip == 0.1
    config = json.loads((schedule_runs["stoc-mistake-myopic"][0] / "config.json").read_text())
    assert {k: config[f"teacher_{k}"] for k in ("beta", "gamma", "eps_mistake", "eps_skip", "eps_equal")} == \
        {"beta": 1.0, "gamma": 0.9, "eps_mistake": 0.1, "eps_skip": 0.0, "eps_equal": 0.0}


# ---------------------------------------------------------------- smoke runs that reach every phase


def check_complete_run(out, result, n_sessions: int, obs_dim: int, segment_len: int):
    assert result.returncode == 0, result.stderr[-3000:]
    config = json.loads((out / "config.json").read_text())
    first_session = config["seed_steps"] + config["unsup_steps"] + 1
    assert_pebble_phases(out, config["seed_steps"], first_session, config["total_timesteps"])
    assert len(session_lines(result.stdout)) == n_sessions
    rows = eval_rows(out)
    assert {"step", "episode_return", "success_rate", "feedback", "reward_correlation"} <= set(rows[0])
    assert [int(r["feedback"]) for r in rows] == sorted(int(r["feedback"]) for r in rows)
    assert math.isfinite(float(rows[-1]["reward_correlation"]))
    labels = saved_labels(out)
    assert len(labels) == n_sessions
    for session in labels:
        n = len(session["y"])
        assert session["obs0"].shape == session["obs1"].shape == (n, segment_len, obs_dim)
        assert session["rewards0"].shape == (n, segment_len) and session["keep"].dtype == bool
    config = json.loads((out / "config.json").read_text())
    assert config["segment_len"] == segment_len
    assert list(out.glob("events.out.tfevents.*"))
    return rows, labels


def test_smoke_dmc_walker_reaches_every_phase(tmp_path):
    out = tmp_path / "walker"
    result = run_pebble(out, "--env-id", "walker-walk", "--total-timesteps", "1300", "--seed-steps", "800",
                        "--unsup-steps", "200", "--feedback-every", "100", "--max-feedback", "30",
                        "--feedback-per-session", "10", "--segment-len", "10", "--eval-every", "1100", *TINY)
    rows, labels = check_complete_run(out, result, n_sessions=3, obs_dim=24, segment_len=10)
    assert [int(r["step"]) for r in rows] == [1100, 1300]  # every 1100 and the last step
    assert [int(r["feedback"]) for r in rows] == [10, 30]
    for session in labels:  # the oracle's labels agree with the saved true rewards of the saved segments
        np.testing.assert_array_equal(session["y"], (session["rewards1"].sum(1) > session["rewards0"].sum(1)).astype(float))
    config = json.loads((out / "config.json").read_text())
    assert config["learning_rate"] == 5e-4  # walker-walk preset fills what was not given
    assert config["teacher_beta"] == math.inf and config["teacher_gamma"] == 1.0  # the oracle's, resolved


def test_smoke_metaworld_button_press_reaches_every_phase(tmp_path):
    out = tmp_path / "button"
    result = run_pebble(out, "--env-id", "button-press", "--total-timesteps", "1600", "--seed-steps", "1000",
                        "--unsup-steps", "300", "--feedback-every", "100", "--max-feedback", "30",
                        "--feedback-per-session", "10", "--segment-len", "10", "--eval-every", "800",
                        "--sampler", "entropy", *TINY)
    rows, _ = check_complete_run(out, result, n_sessions=3, obs_dim=39, segment_len=10)
    assert all(0.0 <= float(r["success_rate"]) <= 1.0 for r in rows)
    assert json.loads((out / "config.json").read_text())["reward_epochs"] == 3


PENDULUM = ["--env-id", "Pendulum-v1", "--total-timesteps", "900", "--seed-steps", "100", "--unsup-steps", "100",
            "--feedback-every", "300", "--max-feedback", "30", "--feedback-per-session", "10", "--segment-len", "10",
            "--eval-every", "900", *TINY]


# Three full schedules cover every teacher's answers (the irrationalities combined in one), every sampler that a
# smoke run does not (uniform starts each run, walker's uses the default disagreement, button-press's entropy) and
# both non-uniform schedules. Sessions after 200, 500, 800 of T = 900 steps, 10 per session: decay int(20 (T - t) / T) =
# 15, 8, 2 (25 of the 30 labels); increase int(5 T / (T - t + 1)) = 6, 11, then 44 capped at the 13 left. skip: with
# eps_skip = 0.1, delta_skip (~ -6) is above nearly every 10-step Pendulum return, so whole sessions can be skipped
# by chance and the sampler never runs; 0.5 (~ -30) keeps about half
SCHEDULE_RUNS = {
    "equal": ["--teacher", "equal", "--sampler", "disagreement-coverage", "--schedule", "increase"],
    "skip": ["--teacher", "skip", "--teacher-eps-skip", "0.5", "--sampler", "entropy-coverage", "--schedule", "decay"],
    "stoc-mistake-myopic": ["--teacher", "myopic", "--teacher-beta", "1", "--teacher-eps-mistake", "0.1",
                            "--sampler", "coverage"],
}


@pytest.fixture(scope="module")
def schedule_runs(tmp_path_factory):
    """name -> (output dir, result) of each of SCHEDULE_RUNS (a repeated run gives the same run: test_resume.py)."""
    runs = {}
    for name, flags in SCHEDULE_RUNS.items():
        out = tmp_path_factory.mktemp("schedules") / name
        runs[name] = out, run_pebble(out, *PENDULUM, *flags, "--no-cuda")
    return runs


@pytest.mark.parametrize("name", SCHEDULE_RUNS)
def test_every_teacher_and_sampler_runs_a_full_schedule(name, schedule_runs):
    out, result = schedule_runs[name]
    assert result.returncode == 0, result.stderr[-3000:]
    assert len(session_lines(result.stdout)) == 3  # each session trains r_hat, then relabels
    labels = saved_labels(out)
    assert sum(len(s["y"]) for s in labels) == (25 if name == "skip" else 30)
    y = np.concatenate([s["y"] for s in labels])
    keep = np.concatenate([s["keep"] for s in labels])
    if name == "skip":  # Pendulum's returns are negative: many segments fall under delta_skip
        assert (~keep).any() and np.isnan(y[~keep]).all()
    else:
        assert keep.all()
    assert (y == 0.5).any() == (name == "equal")


@pytest.mark.parametrize("schedule, name, sizes", [("decay", "skip", [15, 8, 2]), ("increase", "equal", [6, 11, 13])])
def test_decay_and_increase_sessions_ask_the_reference_codes_numbers(schedule, name, sizes, schedule_runs):
    out, result = schedule_runs[name]
    assert [len(s["y"]) for s in saved_labels(out)] == sizes
    assert schedule_sizes(schedule, 30, 10, np.array([200, 500, 800]), 900).tolist() == sizes
    assert ("note: only 25 of the 30 labels" in result.stdout) == (schedule == "decay")


def test_all_queries_skipped_keeps_exploring_without_training_on_nothing(tmp_path):
    out = tmp_path / "skipped"
    result = run_pebble(out, "--env-id", "tests.toy_envs:ConstantPenalty-v0", "--total-timesteps", "600",
                        "--seed-steps", "100", "--unsup-steps", "100", "--feedback-every", "150",
                        "--max-feedback", "20", "--feedback-per-session", "10", "--segment-len", "10",
                        "--eval-every", "600", "--teacher", "skip", "--teacher-eps-skip", "0.5", *TINY)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("queries skipped, the reward model stays as it is") == 2
    # pre-training goes on while nothing is learned: every update on the kNN reward, nothing relabelled
    assert all(value > 0 for _, value in scalars(out)["losses/batch_reward"])
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert not state["progress"]["pretrained"] and not state["buffer"]["rewards"].any()
    assert not np.concatenate([s["keep"] for s in saved_labels(out)]).any()
    assert eval_rows(out)[-1]["reward_correlation"] in ("", "nan")


def test_ground_truth_reward_runs_sac_with_pretraining_and_no_teacher(tmp_path):
    out = tmp_path / "truth"
    result = run_pebble(out, *PENDULUM, "--ground-truth-reward")
    assert result.returncode == 0, result.stderr[-3000:]
    rewards = dict(scalars(out)["losses/batch_reward"])
    assert rewards[200] > 0  # the normalised kNN reward in pre-training
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    true_rewards = state["buffer"]["rewards"]  # Pendulum's: <= 0, never relabelled
    assert (true_rewards <= 0).all() and true_rewards.min() < -1
    assert rewards[900] == pytest.approx(true_rewards.mean().item(), abs=2)  # batch means of the true reward
    adam_steps = {int(s["step"]) for s in state["critic_optimizer"]["state"].values()}
    assert adam_steps == {900 - 201 + 1 + 100}  # the critic reset where the first session would be
    assert not session_lines(result.stdout) and not saved_labels(out)
    assert int(eval_rows(out)[-1]["feedback"]) == 0


def test_reward_inputs_are_standardised_by_the_labelled_states(schedule_runs):
    assert_inputs_standardised_by_labelled_states(schedule_runs["stoc-mistake-myopic"][0], obs_dim=3)


def test_reset_critic_is_orthogonal_and_the_temperature_has_its_own_learning_rate(tmp_path):
    out = tmp_path / "run"  # a learning rate of 1e-12 leaves actor and critic where their init put them
    result = run_pebble(out, *PENDULUM, "--learning-rate", "1e-12", "--checkpoint-every", "900")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "feedback session 1:" in result.stdout  # the checkpoint's critic is the reset one
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    for name in ("actor", "critic", "critic_target"):
        assert_orthogonal_with_zero_biases(saved[name], atol=1e-6, bias_atol=1e-6)
    lrs = {name: saved[f"{name}_optimizer"]["param_groups"][0]["lr"] for name in ("actor", "critic", "alpha")}
    assert lrs == {"actor": 1e-12, "critic": 1e-12, "alpha": 1e-4}  # --alpha-lr's default, reference code
    assert abs(saved["log_alpha"].item() - math.log(0.1)) > 1e-3  # the temperature did learn at 1e-4
    assert json.loads((out / "config.json").read_text())["alpha_lr"] == 1e-4


# ---------------------------------------------------------------- bad input: one line, non-zero exit, nothing run

TYRO_ERRORS = [  # tyro's own checks: its error box
    (["--teacher", "sleepy"], "invalid choice 'sleepy' for argument '--teacher'. Expected one of ('oracle', 'stoc', "
                              "'mistake', 'skip', 'equal', 'myopic', 'human')"),
    (["--sampler", "best"], "invalid choice 'best' for argument '--sampler'. Expected one of ('uniform', "),
    (["--schedule", "random"], "invalid choice 'random' for argument '--schedule'. Expected one of ('uniform', "
                               "'decay', 'increase')"),
    (["--seed", "abc"], "Error parsing --seed: invalid literal for int() with base 10: 'abc'"),
    (["--max-feedback", "many"], "Error parsing --max-feedback:"),
    (["--no-such-flag"], "Unrecognized options: --no-such-flag"),
]
BAD_INPUTS = [  # our own checks: one line
    (["--env-id", "nowhere-walk"], "--env-id"),
    (["--env-id", "nomodule_xyz:Thing-v0"], "--env-id"),
    (["--seed", "-1"], "--seed must be >= 0"),
    (["--max-feedback", "-5"], "--max-feedback must be >= 1"),
    (["--max-feedback", "100", "--feedback-per-session", "200"], "--feedback-per-session must be <= --max-feedback"),
    (["--feedback-per-session", "0"], "--feedback-per-session must be >= 1"),
    (["--segment-len", "5000"], "--segment-len must be in [1, 1000]"),
    (["--buffer-size", "10"], "--buffer-size must be 0 or >= the batch size and T"),
    # the teacher's fields: SimTeacher's own checks
    (["--teacher-gamma", "1.5"], "gamma must be in (0, 1], got 1.5"),
    (["--teacher-gamma", "0"], "gamma must be in (0, 1]"),
    (["--teacher-beta", "-1"], "beta must be >= 0"),
    (["--teacher-eps-mistake", "1.5"], "eps_mistake must be in [0, 1]"),
    (["--teacher-eps-skip", "-0.1"], "eps_skip must be in [0, 1]"),
    (["--total-timesteps", "500"], "--total-timesteps must be > --seed-steps + --unsup-steps (10000), got 500"),
    (["--feedback-every", "0"], "--feedback-every must be >= 1"),
    (["--label-smoothing", "1"], "--label-smoothing must be in [0, 1)"),
    (["--learning-rate", "0"], "--learning-rate must be > 0, got 0.0"),
    (["--alpha-lr", "-1e-4"], "--alpha-lr must be > 0, got -0.0001"),
]


@pytest.fixture(scope="module")
def refused(tmp_path_factory):
    """Each command line of TYRO_ERRORS and BAD_INPUTS, run in one interpreter: flags -> (result, its output dir)."""
    cases = [flags for flags, _ in TYRO_ERRORS + BAD_INPUTS]
    outs = [tmp_path_factory.mktemp("refused") / "run" for _ in cases]
    results = run_in_one_interpreter("pebble.py", list(zip(outs, cases)))
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
    assert_rejected(run_pebble(tmp_path / "run", "--seed", "-1", timeout=120), "--seed must be >= 0", tmp_path / "run")


def test_existing_run_directory_is_not_overwritten(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "eval.csv").write_text("precious\n")
    result = run_pebble(out, *PENDULUM, timeout=120)
    assert result.returncode != 0 and "already holds a run" in result.stderr and "Traceback" not in result.stderr
    assert (out / "eval.csv").read_text() == "precious\n"


def test_help_lists_the_choices():
    result = run_script("pebble.py", "unused", "--help", timeout=120)
    assert result.returncode == 0 and "{oracle,stoc,mistake,skip,equal,myopic,human}" in result.stdout
    assert "--cuda, --no-cuda" in result.stdout


def test_help_names_the_flags_whose_defaults_come_from_the_task_s_preset():
    result = run_script("pebble.py", "unused", "--env-id", "button-press", "--teacher", "myopic", "--help",
                        timeout=120)
    description = " ".join(re.sub("[│╭╰╮╯─]", " ", result.stdout).split())  # the help box, unwrapped
    assert result.returncode == 0
    assert ("Defaults of --env-id button-press --teacher myopic; from their preset: --total-timesteps "
            "--teacher-gamma --max-feedback --feedback-per-session --feedback-every --hidden-dim --num-layers "
            "--batch-size --learning-rate --reward-epochs") in description
    assert "from their preset: none" in " ".join(run_script("pebble.py", "unused", "--help").stdout.split())
    assert "--output-dir STR where the run's files go (default: runs/<run name>) --checkpoint-every" in description
