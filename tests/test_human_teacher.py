"""--teacher human, the script's side: each feedback session writes its queries (reset seeds, starts and actions
of the segments' episodes) to queries/session_N.npz, checkpoints, waits for queries/session_N_answers.json (which
label_server.py's page writes) and learns from exactly those answers; a run stopped while it waits resumes with
the answers given. Here the test writes the answers file as the page would."""

import json
import os
import signal
import time

import numpy as np
import pytest
import torch

import pebble
from tests.helpers import saved_labels, start_script
from tests.test_label_server import browser, click, pair_ready, press, text, wait_for  # noqa: F401 (a fixture)

ANSWERS = ["left", "right", "equal", "skip"]
Y = {"left": 0.0, "right": 1.0, "equal": 0.5}
COMMON = ["--env-id", "Pendulum-v1", "--teacher", "human", "--segment-len", "10", "--hidden-dim", "16",
          "--num-layers", "1", "--max-feedback", "8", "--feedback-per-session", "4", "--eval-episodes", "1",
          "--reward-epochs", "2", "--sampler", "disagreement"]
FLAGS = {  # two sessions each
    "pebble.py": [*COMMON, "--total-timesteps", "900", "--seed-steps", "100", "--unsup-steps", "200",
                  "--batch-size", "16", "--feedback-every", "300", "--eval-every", "450"],
    "prefppo.py": [*COMMON, "--total-timesteps", "1200", "--unsup-steps", "200", "--num-envs", "2",
                   "--num-steps", "100", "--minibatch-size", "100", "--feedback-every", "400", "--eval-every", "600",
                   "--update-epochs", "1", "--unsup-update-epochs", "1"],
}


def wait_for_file(path, process, timeout=300):
    deadline = time.time() + timeout
    while not path.exists():
        assert process.poll() is None, process.communicate()
        assert time.time() < deadline, f"no {path}"
        time.sleep(0.2)
    time.sleep(0.5)  # written atomically; let the run reach its wait


def answer(out, session: int, answers: dict):
    """As label_server.py writes it: atomically, the ids in the order answered."""
    path = out / "queries" / f"session_{session:04d}_answers.json"
    path.with_suffix(".tmp").write_text(json.dumps({"order": [int(i) for i in answers], "answers": answers}))
    os.replace(path.with_suffix(".tmp"), path)


def replayed_segment(seed: int, start: int, actions: np.ndarray, segment_len: int) -> np.ndarray:
    """The observations of a segment, from its episode's reset seed and actions alone (what the page shows)."""
    env, _ = pebble.make_env("Pendulum-v1")
    obs, _ = env.reset(seed=int(seed))
    for action in actions[:start]:
        obs = env.step(action)[0]
    states = []
    for action in actions[start : start + segment_len]:
        states.append(obs)
        obs = env.step(action)[0]
    return np.array(states)


@pytest.mark.parametrize("script", ["pebble.py", "prefppo.py"])
def test_a_person_s_answers_are_the_labels_the_run_learns_from(script, tmp_path):
    out = tmp_path / "run"
    process = start_script(script, out, *FLAGS[script])
    try:
        queries = []
        for session in (0, 1):
            wait_for_file(out / "queries" / f"session_{session:04d}.npz", process)
            queries.append(dict(np.load(out / "queries" / f"session_{session:04d}.npz")))
            assert process.poll() is None  # it waits for the person
            time.sleep(0.5)  # a few of its polls (every 0.2 s)
            assert not (out / "labels" / f"session_{session:04d}.npz").exists()
            answer(out, session, {str(i): a for i, a in enumerate(ANSWERS if session == 0 else ANSWERS[::-1])})
        stdout, stderr = process.communicate(timeout=300)
    finally:
        process.kill()
    assert process.returncode == 0, stderr
    assert "queries wait for a person: python label_server.py" in stdout
    labels = saved_labels(out)
    assert len(labels) == 2 and stdout.splitlines()[-1].startswith("done: 2 feedback sessions")
    for session, (saved, asked) in enumerate(zip(labels, queries)):
        given = ANSWERS if session == 0 else ANSWERS[::-1]
        np.testing.assert_array_equal(saved["keep"], [a != "skip" for a in given])
        np.testing.assert_array_equal(saved["y"][saved["keep"]], [Y[a] for a in given if a != "skip"])
        for side in (0, 1):  # the page's replay from seed and actions is exactly the queried segment
            for i in range(4):
                segment = replayed_segment(asked[f"seed{side}"][i], asked[f"start{side}"][i],
                                           asked[f"actions{side}"][i], 10)
                np.testing.assert_array_equal(segment, saved[f"obs{side}"][i])
                start = asked[f"start{side}"][i]
                np.testing.assert_array_equal(asked[f"actions{side}"][i][start : start + 10], saved[f"actions{side}"][i])


def test_a_run_stopped_while_it_waits_resumes_the_session_with_the_answers_given(tmp_path):
    out = tmp_path / "run"
    process = start_script("pebble.py", out, *FLAGS["pebble.py"])
    try:
        wait_for_file(out / "queries" / "session_0000.npz", process)
        first = dict(np.load(out / "queries" / "session_0000.npz"))
        answer(out, 0, {"0": "right", "1": "left"})  # half of them, then the person stops the run
        time.sleep(0.5)
        process.send_signal(signal.SIGTERM)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == 128 + signal.SIGTERM and "Traceback" not in stderr
    assert stdout.splitlines()[-1] == f"SIGTERM: checkpoint saved before the session at step 301; continue with " \
                                      f"--resume {out}"
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    assert saved["progress"]["global_step"] == 300 and saved["progress"]["sessions_done"] == 0
    (out / "queries" / "session_0000.npz").unlink()
    resumed = start_script("pebble.py", out, "--resume", str(out))
    try:
        wait_for_file(out / "queries" / "session_0000.npz", resumed)
        again = dict(np.load(out / "queries" / "session_0000.npz"))
        assert all(np.array_equal(first[key], again[key]) for key in first)  # the same queries again
        answer(out, 0, {"0": "right", "1": "left", "2": "skip", "3": "equal"})
        wait_for_file(out / "queries" / "session_0001.npz", resumed)
        answer(out, 1, {str(i): "left" for i in range(4)})
        stdout, stderr = resumed.communicate(timeout=300)
    finally:
        resumed.kill()
    assert resumed.returncode == 0, stderr
    assert "resuming from the checkpoint at step 300" in stdout
    labels = saved_labels(out)
    np.testing.assert_array_equal(labels[0]["keep"], [True, True, False, True])
    np.testing.assert_array_equal(labels[0]["y"][labels[0]["keep"]], [1.0, 0.0, 0.5])


def test_a_person_labels_a_short_run_in_a_real_browser(tmp_path, browser):
    """End to end: pebble.py --teacher human waits; label_server.py's page, in headless Chromium, gets each session's
    answers by keys and clicks (one undo); the run finishes having learned from exactly those answers."""
    import label_server
    from selenium.webdriver.common.keys import Keys

    out = tmp_path / "run"
    flags = ["--env-id", "tests.render_envs:Frames-v0", "--teacher", "human", "--total-timesteps", "300",
             "--seed-steps", "30", "--unsup-steps", "60", "--segment-len", "5", "--max-feedback", "6",
             "--feedback-per-session", "3", "--feedback-every", "90", "--hidden-dim", "16", "--num-layers", "1",
             "--batch-size", "16", "--eval-every", "150", "--eval-episodes", "1", "--reward-epochs", "2"]
    process = start_script("pebble.py", out, *flags)
    server = None
    try:
        wait_for_file(out / "queries" / "session_0000.npz", process)
        server = label_server.serve(str(out), "127.0.0.1", 0)
        browser.get(server.url)
        sessions = [[(lambda: press(browser, Keys.ARROW_LEFT), "2 / 3"),  # 0: left
                     (lambda: click(browser, "right"), "3 / 3"),  # 1: right
                     (lambda: press(browser, "u"), "2 / 3"),  # undo 1
                     (lambda: press(browser, "s"), "3 / 3"),  # 1: skip
                     (lambda: click(browser, "equal"), "")],  # 2: equal
                    [(lambda: click(browser, "right"), "2 / 3"),
                     (lambda: press(browser, Keys.ARROW_RIGHT), "3 / 3"),
                     (lambda: click(browser, "left"), "")]]
        for session, steps in enumerate(sessions):
            wait_for(browser, lambda: text(browser, "progress") == "1 / 3" and pair_ready(browser))
            assert f"session {session}" in text(browser, "where")
            for act, progress in steps:
                act()
                wait_for(browser, lambda: text(browser, "progress") == progress)
                if progress:
                    wait_for(browser, lambda: pair_ready(browser))
        stdout, stderr = process.communicate(timeout=300)
    finally:
        process.kill()
        if server is not None:
            server.close()
    assert process.returncode == 0, stderr
    labels = saved_labels(out)
    assert len(labels) == 2 and stdout.count("reward model trained on") == 2
    np.testing.assert_array_equal(labels[0]["keep"], [True, False, True])
    np.testing.assert_array_equal(labels[0]["y"][labels[0]["keep"]], [0.0, 0.5])
    np.testing.assert_array_equal(labels[1]["keep"], [True, True, True])
    np.testing.assert_array_equal(labels[1]["y"], [1.0, 1.0, 0.0])


def test_the_run_names_the_page_s_real_address_when_label_server_py_serves_it(tmp_path, capsys):
    import sim_teacher

    episodes = [(np.zeros((20, 3)), np.zeros((20, 1)), np.zeros(20), 7)]
    teacher = sim_teacher.make_teacher("human", 0, str(tmp_path), episodes)
    (tmp_path / "queries").mkdir()
    queries = {"step": 500, "episode0": np.array([0]), "start0": np.array([2]), "episode1": np.array([0]),
               "start1": np.array([5])}
    for page, expected in ((None, f"python label_server.py {tmp_path} serves them (it prints its page's address)"),
                           ("http://[::1]:8123/", "label_server.py serves them at http://[::1]:8123/")):
        if page:
            (tmp_path / "queries" / "page_url.txt").write_text(page)
        answer(tmp_path, teacher.session, {"0": "left"})
        y, keep = teacher.label(np.zeros((1, 5)), np.zeros((1, 5)), queries)
        assert y.tolist() == [0.0] and keep.tolist() == [True]
        assert expected in capsys.readouterr().out
