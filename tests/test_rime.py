"""rime.py: RIME's denoising discriminator on constructed KL values and predictions whose classes are known, the
bound's schedule and statistics, the warm start's target (the scaled kNN reward), and a tiny run that reaches every
phase (warm start, sessions with the discriminator's record, relabelling, evaluation); test_resume.py resumes it."""

import json
import math
import types

import numpy as np
import pytest
import torch
import torch.nn as nn

import rime
from tests.helpers import eval_rows, run_in_one_interpreter, run_script, saved_labels, scalars, session_lines

ARGS = dict(rime_alpha=0.5, rime_beta_max=3.0, rime_beta_min=1.0, rime_decay_epochs=60, rime_flip_eps=0.001)


def args(**overrides):
    return types.SimpleNamespace(**(ARGS | overrides))


def test_trusted_below_the_lower_bound_flipped_above_the_upper_one_the_rest_dropped():
    discriminator = rime.Discriminator(rho=1.0, var=0.5)  # tau_lower = -ln 1 + 0.5 * 1 + min(3 * 0.5, 3) = 2.0
    kl = torch.tensor([0.1, 1.9, 2.1, 5.0, 7.0])  # tau_upper = -ln 0.001 = 6.908
    trusted, flipped = discriminator.split(kl, args())
    assert trusted.tolist() == [True, True, False, False, False]
    assert flipped.tolist() == [False, False, False, False, True]
    assert discriminator.rho == pytest.approx(1.0 + 0.1 * (1.9 - 1.0))  # EMA of the largest trusted KL
    assert discriminator.mean == pytest.approx(0.1 * 1.0)  # EMA of their mean, from 0
    assert discriminator.var == pytest.approx(np.var([0.1, 1.9]))  # the pooled variance of the trusted so far


def test_the_first_epoch_trusts_all_and_still_flips_what_is_above_the_upper_bound():
    discriminator = rime.Discriminator()  # rho = 0: tau_lower = -ln(1e-8) + 3 = 21.4 (RIME's code)
    trusted, flipped = discriminator.split(torch.tensor([0.5, 8.0, 30.0]), args())
    assert trusted.tolist() == [True, True, False] and flipped.tolist() == [False, True, True]


@pytest.mark.parametrize("epochs, beta", [(0, 3.0), (30, 2.0), (60, 1.0), (600, 1.0)])
def test_beta_falls_linearly_over_the_decay_epochs_then_stays_at_its_minimum(epochs, beta):
    discriminator = rime.Discriminator(rho=1.0, var=0.2, epochs=epochs)  # beta * var < 3: not capped
    kl = torch.tensor([0.5 + beta * 0.2 - 1e-4, 0.5 + beta * 0.2 + 1e-4])  # just below and above tau_lower
    trusted, _ = discriminator.split(kl, args())
    assert trusted.tolist() == [True, False]


def test_the_uncertainty_term_is_capped_at_three():
    discriminator = rime.Discriminator(rho=1.0, var=10.0)
    trusted, _ = discriminator.split(torch.tensor([3.49, 3.51]), args())
    assert trusted.tolist() == [True, False]


class SignMember(nn.Module):
    """r_hat(s, a) = tanh(5 x_0): a confident, known prediction."""

    def __init__(self):
        super().__init__()
        self.scale = nn.Parameter(torch.tensor(5.0))

    def forward(self, x):
        return torch.tanh(self.scale * x[..., :1])


def test_train_reward_learns_from_the_trusted_and_flipped_labels_only():
    # Pairs of 10-step segments with x_0 = +1 or -1: P[second] of the model is 1e-9 or 1 - 1e-9, or
    # about 0.2 (x_0 = 0.0 against -0.028)
    x0 = torch.tensor([1.0, -1.0, 1.0, 0.0]).repeat_interleave(10).view(4, 10, 1)
    x1 = torch.tensor([-1.0, 1.0, -1.0, -0.028]).repeat_interleave(10).view(4, 10, 1)
    y = torch.tensor([0.0, 1.0, 1.0, 1.0])  # right, right, wrong (KL ~ 20 > tau_upper), unsure (KL ~ 1.6)
    model = types.SimpleNamespace(members=nn.ModuleList([SignMember()]), normalize=lambda x: x)
    optimizer = torch.optim.SGD(model.members.parameters(), lr=0.0)
    preferences = {"inputs0": x0, "inputs1": x1, "y": y}
    discriminator = rime.Discriminator(rho=0.5, var=0.0)  # tau_lower = -ln 0.5 + 0.25 = 0.94
    settings = args(reward_epochs=1, reward_batch_size=8, label_smoothing=0.0, reward_lr=0.0, max_feedback=10,
                    feedback_per_session=10, rime_min_epochs=0)
    loss, accuracy, trusted, flipped = rime.train_reward(model, optimizer, preferences, discriminator, settings)
    assert trusted.tolist() == [True, True, False, False] and flipped.tolist() == [False, False, True, False]
    returns = torch.cat([model.members[0](x0).sum(1), model.members[0](x1).sum(1)], -1).detach()
    expected = rime.preference_loss(returns[:3], torch.tensor([0.0, 1.0, 0.0]))  # the wrong label flipped
    assert loss == pytest.approx(expected.item(), rel=1e-5)
    assert accuracy == 1.0 and discriminator.epochs == 1


def test_the_learning_rate_warms_up_linearly_over_the_code_s_epochs():
    model = types.SimpleNamespace(members=nn.ModuleList([SignMember()]), normalize=lambda x: x)
    optimizer = torch.optim.SGD(model.members.parameters(), lr=1.0)
    preferences = {"inputs0": torch.ones(2, 3, 1), "inputs1": -torch.ones(2, 3, 1), "y": torch.zeros(2)}
    settings = args(reward_epochs=1, reward_batch_size=8, label_smoothing=0.0, reward_lr=0.3, max_feedback=100,
                    feedback_per_session=10, rime_min_epochs=15)  # 10 sessions x 15 / 3 = 50 epochs
    lrs = []
    for _ in range(3):
        rime.train_reward(model, optimizer, preferences, rime.Discriminator(epochs=len(lrs) * 25), settings)
        lrs.append(optimizer.param_groups[0]["lr"])
    assert lrs == pytest.approx([0.0, 0.15, 0.3])


def test_the_warm_start_fits_r_hat_to_the_kNN_reward_scaled_into_minus_one_one():
    torch.manual_seed(0)
    buffer = rime.ReplayBuffer(500, 3, 1)
    for _ in range(500):
        buffer.add(torch.randn(3) * torch.tensor([1.0, 5.0, 0.2]), torch.rand(1), 0.0, torch.randn(3), False)
    stats = rime.RunningMeanStd()
    for _ in range(20):  # the SAC side's batches set the statistics and extremes
        stats.update(rime.intrinsic_reward(buffer.sample(64), buffer, 5))
    reward_model = rime.RewardEnsemble(3, 1, 2)
    optimizer = torch.optim.Adam(reward_model.parameters(), lr=1e-3)
    rime.warm_start(reward_model, optimizer, buffer, stats, types.SimpleNamespace(rime_warm_updates=300,
                                                                                  batch_size=64, knn_k=5))
    assert reward_model.input_clip.item() == 10.0  # standardised by the buffer's states
    batch = buffer.sample(200)
    distance = rime.intrinsic_reward(batch, buffer, 5)
    std = math.sqrt(stats.var)
    target = (distance - stats.mean) / max(abs(stats.low - stats.mean), abs(stats.high - stats.mean))
    with torch.no_grad():
        r_hat = reward_model(torch.cat([batch.obs, batch.actions], -1))
    assert target.abs().max() <= 1.05 and std > 0
    for member in r_hat:  # each member fits the scaled kNN reward, not the raw distance (up to ~10 here)
        assert (member - target).abs().mean() < 0.1
        assert np.corrcoef(member[:, 0], target[:, 0])[0, 1] > 0.9


# random steps to 900, pre-training (the warm start) to 1000, then a session every 100 steps
RUN = ["--env-id", "walker-walk", "--seed", "3", "--total-timesteps", "1300", "--seed-steps", "900", "--unsup-steps",
       "100", "--feedback-every", "100", "--max-feedback", "60", "--feedback-per-session", "20", "--segment-len",
       "10", "--eval-every", "650", "--hidden-dim", "32", "--num-layers", "2", "--batch-size", "32",
       "--reward-epochs", "20", "--reward-batch-size", "32", "--eval-episodes", "1", "--rime-min-epochs", "2",
       "--teacher", "mistake", "--teacher-eps-mistake", "0.3", "--checkpoint-every", "650"]


def test_a_tiny_run_reaches_every_phase(tmp_path):
    out = tmp_path / "rime"
    result = run_script("rime.py", out, *RUN)
    assert result.returncode == 0, result.stderr[-3000:]
    config = json.loads((out / "config.json").read_text())
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    # Warm start: 5 reward-model updates per pre-training step; then each session's epochs (at least 4: the early
    # stop waits for epoch index > --rime-min-epochs), each of 1 to 4 batches (|D| <= 60, the first epoch's
    # trusted-and-flipped pairs twice)
    [reward_steps] = {int(s["step"]) for s in state["reward_optimizer"]["state"].values()}
    epochs = state["discriminator"]["epochs"]
    assert 3 * 4 <= epochs <= 3 * 20
    assert 5 * config["unsup_steps"] + epochs <= reward_steps <= 5 * config["unsup_steps"] + 4 * epochs
    # No critic reset: the critics' Adam counts every SAC update since the seed steps, plus the 100 after the first
    # reward update
    adam_steps = {int(s["step"]) for s in state["critic_optimizer"]["state"].values()}
    assert adam_steps == {config["total_timesteps"] - config["seed_steps"] + 100}
    # Pre-training: SAC's kNN reward in RIME's scale, [-1, 1]; then r_hat's
    rewards = scalars(out)["losses/batch_reward"]
    assert all(-1 <= value <= 1 for step, value in rewards)
    # Every transition relabelled with the final r_hat
    buffer = state["buffer"]
    reward_model = rime.RewardEnsemble(buffer["obs"].shape[1], buffer["actions"].shape[1], 3)
    reward_model.load_state_dict(state["reward_model"])
    with torch.no_grad():
        r_hat = reward_model(torch.cat([buffer["obs"], buffer["actions"]], -1)).mean(0)
    torch.testing.assert_close(buffer["rewards"], r_hat)
    # Sessions: each label file holds the discriminator's record over D; TensorBoard has it too
    assert len(session_lines(result.stdout)) == 3
    labels = saved_labels(out)
    for number, session in enumerate(labels):
        assert int(session["trusted"]) + int(session["dropped"]) + int(session["flipped"]) >= 20 * (number + 1)
        assert int(session["trusted"]) + int(session["dropped"]) <= 20 * (number + 1)
        assert 0 <= float(session["precision"]) <= 1 or math.isnan(float(session["precision"]))
    wrong = sum(int((s["y"] != (np.sign(s["rewards1"].sum(1) - s["rewards0"].sum(1)) + 1) / 2).sum()) for s in labels)
    assert wrong > 0  # the mistake teacher at 0.3 made mistakes for the discriminator to find
    assert {"rime/trusted", "rime/flipped", "rime/dropped", "rime/precision", "rime/recall"} <= set(scalars(out))
    assert [int(row["step"]) for row in eval_rows(out)] == [650, 1300]


RIME_RANGES = [
    ("--rime-decay-epochs", "0", "--rime-decay-epochs must be >= 1, got 0"),
    ("--rime-flip-eps", "1.5", "--rime-flip-eps must be in (0, 1), got 1.5"),
    ("--rime-alpha", "-1", "--rime-alpha must be >= 0, got -1.0"),
]


def test_rime_s_flags_out_of_range_are_one_line_before_any_work(tmp_path):
    outs = [tmp_path / flag / "run" for flag, _, _ in RIME_RANGES]
    results = run_in_one_interpreter("rime.py", [(out, [flag, value]) for out, (flag, value, _) in zip(outs, RIME_RANGES)])
    for (_, _, message), result, out in zip(RIME_RANGES, results, outs):
        assert result.returncode == 2 and result.stderr == f"error: {message}\n"
        assert not out.exists()
