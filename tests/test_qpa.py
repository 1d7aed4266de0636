"""qpa.py: QPA's parts on constructed inputs whose answers are known (the hybrid batch's share from the query pool's
transitions, crops that stay inside their segments and keep their pair's label, QPA's number of reward-learning
steps), the query pool of a tiny run (only the last N complete episodes), a tiny run that reaches every phase, and
a run resumed after SIGTERM and SIGKILL that equals the uninterrupted one."""

import json
import signal
import types
from collections import deque

import numpy as np
import pytest
import torch
import torch.nn as nn

import qpa
from tests.helpers import (assert_pebble_phases, eval_rows, run_in_one_interpreter, run_script, saved_labels,
                           scalars, session_lines, start_script, wait_for)
from tests.test_resume import assert_same_run


def numbered_buffer(capacity, rows):
    """A buffer whose row i holds obs = (i, ...): a batch's observations say which rows it drew."""
    buffer = qpa.ReplayBuffer(capacity, 2, 1)
    for i in range(rows):
        buffer.add(torch.tensor([float(i), 0.0]), torch.zeros(1), 0.0, torch.zeros(2), False)
    return buffer


def pool(*lengths):
    """The query pool: episodes as (obs, actions, rewards, seed) of these lengths."""
    return deque((torch.zeros(n, 2), torch.zeros(n, 1), torch.zeros(n), 0) for n in lengths)


def settings(**overrides):
    return types.SimpleNamespace(**(dict(batch_size=100, her_ratio=0.5, max_feedback=100, ground_truth_reward=False)
                                    | overrides))


def test_while_labels_remain_half_the_sac_batch_comes_from_the_pool_s_transitions_the_rest_from_all():
    torch.manual_seed(0)
    buffer = numbered_buffer(1000, 1000)
    progress = qpa.Progress(pretrained=True, feedback_used=50)
    rows = qpa.sac_batch(buffer, settings(), progress, pool(40, 20)).obs[:, 0]
    assert len(rows) == 100
    assert (rows[50:] >= 940).all()  # the last 40 + 20 transitions stored
    assert (rows[:50] < 940).sum() > 40  # the whole buffer (all 50 in the last 60 rows: p = 0.06^50)
    assert set(rows[50:].tolist()) <= set(range(940, 1000)) and len(set(rows[50:].tolist())) > 25


def test_the_pool_s_transitions_wrap_around_a_full_buffer():
    torch.manual_seed(0)
    buffer = numbered_buffer(100, 130)  # full; rows 0-29 overwritten by transitions 100-129, the newest at row 29
    progress = qpa.Progress(pretrained=True, feedback_used=0)
    rows = qpa.sac_batch(buffer, settings(her_ratio=0.8), progress, pool(50)).obs[:, 0]
    recent = set(rows[20:].tolist())  # rows 80-99 and 0-29: transitions 80-129
    assert recent <= set(range(80, 130)) and min(recent) < 100 <= max(recent)


@pytest.mark.parametrize("progress, flags", [
    (qpa.Progress(pretrained=False, feedback_used=0), {}),  # unsupervised pre-training: the whole buffer
    (qpa.Progress(pretrained=True, feedback_used=100), {}),  # every label asked: plain SAC again (QPA's code)
    (qpa.Progress(pretrained=True, feedback_used=0), {"ground_truth_reward": True}),  # SAC on the true reward
])
def test_before_pre_training_ends_after_the_last_label_and_on_the_true_reward_the_batch_is_plain(progress, flags):
    torch.manual_seed(0)
    rows = qpa.sac_batch(numbered_buffer(1000, 1000), settings(**flags), progress, pool(40, 20)).obs[:, 0]
    assert len(rows) == 100 and (rows[50:] < 940).sum() > 40


def test_a_crop_is_one_window_of_h_minus_15_to_h_minus_5_steps_inside_each_segment_of_its_pair():
    pairs, horizon, crops = 7, 50, 20
    steps = torch.arange(horizon, dtype=torch.float64).expand(pairs, horizon)[..., None]

    def crop(weights):  # the same draws for each weighting of the steps
        torch.manual_seed(1)
        return qpa.crop_returns(weights, weights, crops).view(crops, pairs, 2)

    length = crop(torch.ones_like(steps))
    first = crop(steps)
    squares = crop(steps**2)
    assert (length[..., 0] == length[..., 1]).all()  # one length for both segments of a pair
    assert length.min() >= horizon - 15 and length.max() <= horizon - 5 and len(length.unique()) > 5
    start = (first - length * (length - 1) / 2) / length  # sum of t over [s, s + L) = L s + L (L - 1) / 2
    assert torch.equal(start, start.round()) and start.min() >= 0 and (start + length).max() <= horizon
    assert not torch.equal(start[..., 0], start[..., 1])  # each segment its own start
    expected = [[sum(t**2 for t in range(int(s), int(s + n))) for s, n in zip(row_s, row_n)]
                for row_s, row_n in zip(start.flatten(0, 1).tolist(), length.flatten(0, 1).tolist())]
    assert squares.flatten(0, 1).tolist() == expected  # every step of the window, none outside it
    whole = qpa.crop_returns(steps, steps * 2, 0)  # no augmentation: the whole segments
    assert whole.tolist() == [[sum(range(horizon)), 2 * sum(range(horizon))]] * pairs


class Sign(nn.Module):
    """r_hat(s, a) = tanh(5 x_0), the same on every step of a segment of constant x_0."""

    def __init__(self):
        super().__init__()
        self.scale = nn.Parameter(torch.tensor(5.0))

    def forward(self, x):
        return torch.tanh(self.scale * x[..., :1])


def reward_args(**overrides):
    return types.SimpleNamespace(**(dict(reward_updates=2000, reward_epochs=50, reward_batch_size=128,
                                         data_aug_ratio=20, label_smoothing=0.0) | overrides))


def sign_pairs(first, second, y):
    """Pairs of 30-step segments of constant x_0 (first, second) and their labels."""
    def segments(values):
        return torch.tensor(values, dtype=torch.float32)[:, None, None].expand(-1, 30, 1)

    return {"inputs0": segments(first), "inputs1": segments(second), "y": torch.tensor(y, dtype=torch.float32)}


def counted_training(preferences, **overrides):
    """train_reward with a model that learns nothing (lr 0): (accuracy, optimizer steps taken)."""
    model = types.SimpleNamespace(members=nn.ModuleList([Sign()]), normalize=lambda x: x)
    optimizer = torch.optim.SGD(model.members.parameters(), lr=0.0)
    steps = []
    optimizer.register_step_post_hook(lambda *_: steps.append(1))
    torch.manual_seed(0)
    _, accuracy = qpa.train_reward(model, optimizer, preferences, reward_args(**overrides))
    return accuracy, len(steps)


def test_each_crop_keeps_its_pair_s_label():
    # every crop of the first segment returns more in pairs 0 and 2 (label 0: sigma0), less in pair 1 (label 1)
    preferences = sign_pairs([1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [0.0, 1.0, 0.0])
    assert counted_training(preferences) == (1.0, 1)  # all 60 crops right: 98% at the first step


def test_reward_learning_takes_ceil_reward_updates_x_labels_over_the_batch_steps_until_98_percent_so_far():
    # r_hat = 0 everywhere: the model prefers neither, so the pairs labelled 1 are wrong; accuracy 0.5 for ever
    preferences = sign_pairs([0.0] * 10, [0.0] * 10, [0.0, 1.0] * 5)
    assert counted_training(preferences) == (0.5, 157)  # ceil(2000 x 10 / 128), one batch each
    accuracy, steps = counted_training(preferences, reward_updates=100, reward_batch_size=4)
    assert steps == 250 and accuracy == pytest.approx(0.5, abs=0.01)  # ceil(100 x 10 / 4); batches of 4, 4, 2
    # --reward-updates 0: PEBBLE's epochs (Meta-World, as QPA's code), 3 batches an epoch
    assert counted_training(preferences, reward_updates=0, reward_epochs=7, reward_batch_size=4) == (0.5, 21)


def test_by_epochs_the_accuracy_is_that_of_the_last_epoch():
    # one pair of three always wrong: 2/3 per epoch, never above 97%
    preferences = sign_pairs([1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [0.0, 1.0, 1.0])
    accuracy, steps = counted_training(preferences, reward_updates=0, reward_epochs=4, reward_batch_size=2)
    assert accuracy == pytest.approx(2 / 3) and steps == 8


# A 40-step toy task: 400 steps of random actions and pre-training (10 episodes), then sessions at 401, 501 and 601
# from a pool of the last 3 complete episodes
POOL_RUN = ["--env-id", "tests.toy_envs:ConstantPenalty-v0", "--seed", "2", "--total-timesteps", "700",
            "--seed-steps", "200", "--unsup-steps", "200", "--feedback-every", "100", "--max-feedback", "30",
            "--feedback-per-session", "10", "--segment-len", "10", "--query-recent-episodes", "3", "--hidden-dim", "16",
            "--batch-size", "16", "--reward-updates", "5", "--eval-every", "700", "--eval-episodes", "1",
            "--teacher", "stoc"]


def test_queries_come_from_the_last_n_complete_episodes_only(tmp_path):
    out = tmp_path / "pool"
    result = run_script("qpa.py", out, *POOL_RUN)
    assert result.returncode == 0, result.stderr[-3000:]
    stored = torch.load(out / "checkpoint.pt", weights_only=True)["buffer"]["obs"].numpy()  # row i: step i + 1
    for session in saved_labels(out):
        step = int(session["step"])
        complete = (step - 1) // 40  # episodes ended before the session's step
        episodes = set()
        for side in (0, 1):
            for segment in session[f"obs{side}"]:
                row = int(np.flatnonzero((stored == segment[0]).all(1))[0])
                np.testing.assert_array_equal(stored[row : row + 10], segment)  # a stretch of one episode
                episodes.add(row // 40)
        assert episodes <= {complete - 3, complete - 2, complete - 1} and len(episodes) >= 2, (step, episodes)


# walker-walk: random steps to 900, pre-training to 1000, sessions at 1001, 1101, 1201 (20 labels each, 20 steps of
# reward learning per label over a batch of 32, crops of 10-step segments)
RUN = ["--env-id", "walker-walk", "--seed", "3", "--total-timesteps", "1300", "--seed-steps", "900", "--unsup-steps",
       "100", "--feedback-every", "100", "--max-feedback", "60", "--feedback-per-session", "20", "--segment-len",
       "10", "--eval-every", "650", "--hidden-dim", "32", "--num-layers", "2", "--batch-size", "32",
       "--reward-updates", "20", "--reward-batch-size", "32", "--eval-episodes", "1", "--query-recent-episodes", "1",
       "--checkpoint-every", "650"]


def test_a_tiny_run_reaches_every_phase(tmp_path):
    out = tmp_path / "qpa"
    result = run_script("qpa.py", out, *RUN)
    assert result.returncode == 0, result.stderr[-3000:]
    config = json.loads((out / "config.json").read_text())
    assert config["reward_ensemble_size"] == 1 and config["sampler"] == "uniform" and config["her_ratio"] == 0.5
    # SAC on the kNN reward, then on r_hat; the critic reset at the first session; every transition relabelled
    state = assert_pebble_phases(out, seed_steps=900, first_session=1001, total=1300)
    # reward learning: at most ceil(20 x |D| / 32) steps a session (fewer once 98% so far), one reward model
    [reward_steps] = {int(s["step"]) for s in state["reward_optimizer"]["state"].values()}
    assert 3 <= reward_steps <= sum(-(-20 * labels // 32) for labels in (20, 40, 60))
    assert {key.split(".")[1] for key in state["reward_model"] if key.startswith("members.")} == {"0"}
    assert len(session_lines(result.stdout)) == 3 and [len(s["y"]) for s in saved_labels(out)] == [20, 20, 20]
    assert {"reward/loss", "reward/accuracy", "losses/critic_loss"} <= set(scalars(out))
    assert [int(row["step"]) for row in eval_rows(out)] == [650, 1300]


QPA_RANGES = [
    ("--her-ratio", "1.5", "--her-ratio must be in [0, 1], got 1.5"),
    ("--data-aug-ratio", "-1", "--data-aug-ratio must be >= 0, got -1"),
    ("--reward-updates", "-2", "--reward-updates must be >= 0, got -2"),
]


def test_qpa_s_flags_out_of_range_are_one_line_before_any_work(tmp_path):
    outs = [tmp_path / flag / "run" for flag, _, _ in QPA_RANGES]
    runs = [(out, [flag, value]) for out, (flag, value, _) in zip(outs, QPA_RANGES)]
    results = run_in_one_interpreter("qpa.py", runs)
    for (_, _, message), result, out in zip(QPA_RANGES, results, outs):
        assert result.returncode == 2 and result.stderr == f"error: {message}\n"
        assert not out.exists()


# As tests/test_resume.py's tiny runs: a checkpoint at 1050 (mid-episode), sessions at 1001, 1101 and 1201, a teacher
# that draws its answers; the pool is the last complete episode, so the hybrid batches and the crops draw too
RESUME_RUN = ["--env-id", "walker-walk", "--total-timesteps", "1300", "--seed-steps", "700", "--unsup-steps", "300",
              "--feedback-every", "100", "--max-feedback", "30", "--feedback-per-session", "10", "--segment-len", "10",
              "--eval-every", "650", "--checkpoint-every", "1050", "--hidden-dim", "32", "--num-layers", "2",
              "--batch-size", "32", "--reward-updates", "10", "--reward-batch-size", "32", "--eval-episodes", "1",
              "--teacher", "myopic", "--teacher-beta", "1", "--teacher-eps-mistake", "0.1"]


def test_sigterm_then_sigkill_and_resumes_equal_the_uninterrupted_run(tmp_path):
    reference = tmp_path / "uninterrupted"
    result = run_script("qpa.py", reference, *RESUME_RUN)
    assert result.returncode == 0, result.stderr[-3000:]
    out = tmp_path / "run"
    process = start_script("qpa.py", out, *RESUME_RUN, "--checkpoint-every", "0")
    wait_for(out / "labels" / "session_0000.npz", process)
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    assert "SIGTERM: checkpoint saved at step" in stdout
    process = start_script("qpa.py", out, "--resume", str(out), "--checkpoint-every", "1050")
    wait_for(out / "labels" / "session_0001.npz", process)
    process.send_signal(signal.SIGKILL)
    process.communicate()
    result = run_script("qpa.py", out, "--resume", str(out))
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("resuming from the checkpoint at step") == 1
    assert_same_run(out, reference)
