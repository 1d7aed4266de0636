"""experiments/label_margins.py on constructed labels whose margins and learnable reward are known."""

import numpy as np
import pytest

import label_margins
from sim_teacher import save_labels


def write_session(run, session, rewards0, rewards1, obs0=None, obs1=None, keep=None):
    rewards0, rewards1 = np.asarray(rewards0, np.float32), np.asarray(rewards1, np.float32)
    n, length = rewards0.shape
    blank = np.zeros((n, length, 3), np.float32)
    save_labels(str(run), session, rewards0=rewards0, rewards1=rewards1,
                y=(rewards1.sum(1) > rewards0.sum(1)).astype(np.float64),
                keep=np.ones(n, bool) if keep is None else keep,
                obs0=blank if obs0 is None else obs0, obs1=blank if obs1 is None else obs1,
                actions0=np.zeros((n, length, 1), np.float32), actions1=np.zeros((n, length, 1), np.float32))


def test_margins_give_each_stretch_s_median_difference_and_its_near_ties(tmp_path):
    """Stretch 1: returns 10 against 10.5 (a near-tie: 0.5 < 10% of 10.5) and 10 against 20; stretch 2: 1 against
    3, 2 against 2.1 (near-tie) and 4 against 0 (a difference of 4, not a tie)."""
    write_session(tmp_path, 0, [[5, 5], [4, 6]], [[5, 5.5], [10, 10]])
    write_session(tmp_path, 1, [[1, 0], [1, 1], [2, 2]], [[1, 2], [1, 1.1], [0, 0]])
    rows = label_margins.margins(label_margins.load_labels(str(tmp_path)), stretches=2)
    assert [row["sessions"] for row in rows] == ["1-1", "2-2"]
    assert [row["pairs"] for row in rows] == [2, 3]
    assert rows[0]["median difference"] == pytest.approx(5.25)  # median of 0.5 and 10
    assert rows[0]["median return"] == pytest.approx(10.25)  # median of 10, 10, 10.5, 20
    assert rows[0]["near-ties"] == pytest.approx(0.5)
    assert rows[1]["median difference"] == pytest.approx(2.0)  # 2, 0.1, 4
    assert rows[1]["near-ties"] == pytest.approx(1 / 3)


def test_fits_learn_a_reward_the_labels_determine_and_not_one_they_do_not(tmp_path):
    """The true reward is the first observation entry: from the oracle's labels and from the rewards alike the
    ensemble learns it (per-step correlation and held-out order near 1). With the labels drawn at random instead,
    the labels' fit neither orders the held-out pairs better than chance nor finds the reward; the regression,
    which never sees the labels, still does."""
    rng = np.random.default_rng(0)
    obs0, obs1 = rng.normal(size=(2, 300, 5, 3)).astype(np.float32)
    write_session(tmp_path / "oracle", 0, obs0[..., 0], obs1[..., 0], obs0, obs1)
    oracle = label_margins.fits(str(tmp_path / "oracle"), label_margins.load_labels(str(tmp_path / "oracle")), 0, 50)
    assert oracle["labels"][0] > 0.9 and oracle["labels"][1] > 0.8
    assert oracle["true reward"][0] > 0.95 and oracle["true reward"][1] > 0.9

    write_session(tmp_path / "random", 0, obs0[..., 0], obs1[..., 0], obs0, obs1)
    path = tmp_path / "random" / "labels" / "session_0000.npz"
    saved = dict(np.load(path))
    saved["y"] = rng.integers(0, 2, 300).astype(np.float64)
    np.savez(path, **saved)
    random = label_margins.fits(str(tmp_path / "random"), label_margins.load_labels(str(tmp_path / "random")), 0, 50)
    assert random["labels"][1] < 0.7 and abs(random["labels"][0]) < 0.5
    assert random["true reward"][0] > 0.95


def test_skipped_pairs_are_left_out_of_the_fits(tmp_path):
    """Pairs the teacher skipped (keep False) carry labels the run never trained on: here their labels contradict
    the reward, and leaving them out keeps the fit right."""
    rng = np.random.default_rng(1)
    obs0, obs1 = rng.normal(size=(2, 400, 5, 3)).astype(np.float32)
    keep = np.arange(400) % 2 == 0
    write_session(tmp_path, 0, obs0[..., 0], obs1[..., 0], obs0, obs1, keep=keep)
    path = tmp_path / "labels" / "session_0000.npz"
    saved = dict(np.load(path))
    saved["y"] = np.where(keep, saved["y"], 1 - saved["y"])
    np.savez(path, **saved)
    fitted = label_margins.fits(str(tmp_path), label_margins.load_labels(str(tmp_path)), 0, 50)
    assert fitted["labels"][0] > 0.9 and fitted["labels"][1] > 0.9


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    for argv in ([str(tmp_path / "nothing")], [str(tmp_path), "--epochs", "0"]):
        with pytest.raises(SystemExit) as stopped:
            label_margins.main(label_margins.tyro.cli(label_margins.Args, args=argv))
        assert stopped.value.code == 2
        assert capsys.readouterr().err.count("\n") == 1
