"""label_server.py, the labelling page of --teacher human: answers written as given (atomically,
once each), undo, the errors of bad input, clips that are exact replays, nothing else served; and
a real browser (headless Chromium) clicking through a session."""

import http.client
import io
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import label_server
import pebble
from tests.helpers import ENV, ROOT

ENV_ID = "tests.render_envs:Frames-v0"  # 30-step episodes, 120 x 160 frames, no OpenGL
SEGMENT_LEN = 5


def write_session(run_dir, number: int, n: int, seed: int = 0):
    """A session file as the run writes it (the protocol of docs/human_teacher.md): n queries of
    two segments, each from an episode given by its reset seed and actions up to its end."""
    rng = np.random.default_rng([seed, number])
    arrays = {"step": np.int64(1000 * (number + 1))}
    for side in (0, 1):
        starts = rng.integers(0, 30 - SEGMENT_LEN + 1, n)
        length = starts.max() + SEGMENT_LEN
        actions = np.zeros((n, length, 2), np.float32)
        for i, start in enumerate(starts):
            actions[i, :start + SEGMENT_LEN] = rng.uniform(-1, 1, (start + SEGMENT_LEN, 2))
        arrays[f"seed{side}"] = rng.integers(0, 2**31, n).astype(np.int64)
        arrays[f"start{side}"] = starts.astype(np.int64)
        arrays[f"actions{side}"] = actions
    path = run_dir / "queries" / f"session_{number:04d}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path.with_suffix(".tmp.npz"), **arrays)
    os.replace(path.with_suffix(".tmp.npz"), path)
    return arrays


def make_run(run_dir, n: int = 4):
    run_dir.mkdir()
    config = {"env_id": ENV_ID, "segment_len": SEGMENT_LEN, "seed": 1}
    (run_dir / "config.json").write_text(json.dumps(config))
    return write_session(run_dir, 0, n)


@pytest.fixture
def run(tmp_path):
    """A run waiting at session 0 (4 queries), and its label server on a free port."""
    run_dir = tmp_path / "run"
    arrays = make_run(run_dir)
    server = label_server.serve(str(run_dir), "127.0.0.1", 0)
    yield run_dir, server, arrays
    server.close()


def request(server, method: str, path: str, body=None, content_type="application/json"):
    """(status, the JSON reply or the raw bytes of an image)."""
    connection = http.client.HTTPConnection(*server.server_address[:2], timeout=60)
    data = body if isinstance(body, (bytes, type(None))) else json.dumps(body).encode()
    connection.request(method, path, data, {"Content-Type": content_type} if data else {})
    response = connection.getresponse()
    payload = response.read()
    connection.close()
    if response.getheader("Content-Type") == "application/json":
        return response.status, json.loads(payload)
    return response.status, payload


def answer(server, query: int, label: str, session: int = 0):
    return request(server, "POST", "/api/answer", {"session": session, "id": query, "label": label})


def answers_file(run_dir, session: int = 0) -> dict:
    return json.loads((run_dir / "queries" / f"session_{session:04d}_answers.json").read_text())


def test_each_answer_is_in_the_answers_file_as_it_is_given(run):
    run_dir, server, _ = run
    assert request(server, "GET", "/api/state")[1] == {
        "env_id": ENV_ID, "segment_len": 5, "columns": 5, "session": 0, "step": 1000, "n": 4,
        "answered": 0, "next": 0, "after": 1, "last": None, "done": None, "run_finished": False}
    status, state = answer(server, 0, "left")
    assert status == 200 and (state["answered"], state["next"], state["last"]) == (1, 1, 0)
    assert answers_file(run_dir) == {"order": [0], "answers": {"0": "left"}}
    answer(server, 2, "equal")  # any unanswered pair; the page shows the first unanswered next
    status, state = answer(server, 1, "skip")
    assert answers_file(run_dir) == {"order": [0, 2, 1],
                                     "answers": {"0": "left", "2": "equal", "1": "skip"}}
    assert (state["answered"], state["next"], state["after"], state["last"]) == (3, 3, None, 1)


def test_the_answers_file_is_replaced_whole_never_written_in_place(run, monkeypatch):
    run_dir, server, _ = run
    replaced = []
    real_replace = os.replace

    def spy(source, destination):
        replaced.append((str(source), str(destination)))
        real_replace(source, destination)

    monkeypatch.setattr(os, "replace", spy)
    answer(server, 0, "right")
    request(server, "POST", "/api/undo", {"session": 0, "id": 0})
    answers = str(run_dir / "queries" / "session_0000_answers.json")
    assert replaced == [(answers + ".tmp", answers)] * 2
    assert sorted(os.listdir(run_dir / "queries")) == ["page_url.txt", "session_0000.npz",
                                                       "session_0000_answers.json"]


def test_undo_removes_the_last_answer_only(run):
    run_dir, server, _ = run
    answer(server, 0, "left")
    answer(server, 1, "right")
    status, reply = request(server, "POST", "/api/undo", {"session": 0, "id": 0})
    assert status == 409 and reply["error"] == "pair 0 is not the last answer (the last is 1)"
    status, state = request(server, "POST", "/api/undo", {"session": 0, "id": 1})
    assert status == 200 and (state["answered"], state["next"], state["last"]) == (1, 1, 0)
    assert answers_file(run_dir) == {"order": [0], "answers": {"0": "left"}}
    answer(server, 1, "equal")  # answered again after the undo: counted once
    assert answers_file(run_dir) == {"order": [0, 1], "answers": {"0": "left", "1": "equal"}}
    request(server, "POST", "/api/undo", {"session": 0, "id": 1})
    request(server, "POST", "/api/undo", {"session": 0, "id": 0})
    status, reply = request(server, "POST", "/api/undo", {"session": 0, "id": 0})
    assert status == 409 and reply["error"] == "pair 0 is not the last answer (the last is None)"
    assert answers_file(run_dir) == {"order": [], "answers": {}}


def test_a_second_answer_to_a_pair_is_a_409_and_the_first_one_stands(run):
    run_dir, server, _ = run
    answer(server, 0, "left")
    status, reply = answer(server, 0, "right")  # a second browser, showing pair 0 still
    assert status == 409 and reply["error"] == ("pair 0 was answered first in another browser: this answer was "
                                                "not taken, the first one stands")
    assert reply["state"]["next"] == 1  # where that page goes
    assert answers_file(run_dir) == {"order": [0], "answers": {"0": "left"}}


def test_simultaneous_answers_to_one_pair_count_once(run):
    run_dir, server, _ = run
    statuses = []
    threads = [threading.Thread(target=lambda label=label: statuses.append(
        answer(server, 3, label)[0])) for label in ("left", "right", "equal", "skip") * 4]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(statuses) == [200] + [409] * 15
    saved = answers_file(run_dir)
    assert saved["order"] == [3] and list(saved["answers"]) == ["3"]


@pytest.mark.parametrize("body, status, message", [
    ({"session": 0, "id": 1, "label": "better"}, 400,
     "label 'better' is not one of left, right, equal, skip"),
    ({"session": 0, "id": 1}, 400, "label None is not one of left, right, equal, skip"),
    ({"session": 0, "id": "1", "label": "left"}, 400, "id must be an integer, not '1'"),
    ({"session": 0, "id": True, "label": "left"}, 400, "id must be an integer, not True"),
    ({"session": 0, "id": 4, "label": "left"}, 404,
     "session 0 has no pair 4 (its pairs are 0 to 3)"),
    ({"session": 0, "id": -1, "label": "left"}, 404,
     "session 0 has no pair -1 (its pairs are 0 to 3)"),
    ({"session": 1, "id": 0, "label": "left"}, 409,
     "session 1 is not the current session (it is 0)"),
    ([0, 1, "left"], 400, "the request's body must be a JSON object"),
    (b"{session: 0", 400, "the request's body is not valid JSON"),
])
def test_bad_answers_are_refused_with_a_one_line_message_and_change_nothing(run, body, status,
                                                                             message):
    run_dir, server, _ = run
    answer(server, 0, "left")
    reply_status, reply = request(server, "POST", "/api/answer", body)
    assert (reply_status, reply["error"]) == (status, message)
    assert answers_file(run_dir) == {"order": [0], "answers": {"0": "left"}}


def test_a_form_post_from_another_site_is_refused(run):
    run_dir, server, _ = run
    body = json.dumps({"session": 0, "id": 0, "label": "left"}).encode()
    status, reply = request(server, "POST", "/api/answer", body, content_type="text/plain")
    assert status == 415 and "application/json" in reply["error"]
    assert not (run_dir / "queries" / "session_0000_answers.json").exists()


def test_a_done_session_gives_way_to_waiting_then_to_the_next_session(run):
    run_dir, server, _ = run
    for query in range(4):
        status, state = answer(server, query, "right")
    assert status == 200 and state["session"] is None  # the page waits for the run
    status, reply = request(server, "POST", "/api/undo", {"session": 0, "id": 3})
    assert status == 409 and reply["error"] == (
        "session 0 is not the current session (none is waiting)")
    assert request(server, "GET", "/clips/0/0/0.jpg")[0] == 409  # the run has taken its labels
    write_session(run_dir, 1, 3)
    state = request(server, "GET", "/api/state")[1]
    assert (state["session"], state["n"], state["answered"], state["next"]) == (1, 3, 0, 0)
    assert answer(server, 0, "left", session=0)[0] == 409
    assert answer(server, 0, "left", session=1)[0] == 200
    assert answers_file(run_dir, 1) == {"order": [0], "answers": {"0": "left"}}


def test_a_new_server_resumes_at_the_first_unanswered_pair(run):
    run_dir, server, _ = run
    answer(server, 1, "left")
    answer(server, 0, "skip")
    server.close()
    again = label_server.serve(str(run_dir), "127.0.0.1", 0)
    try:
        state = request(again, "GET", "/api/state")[1]
        assert (state["answered"], state["next"], state["last"]) == (2, 2, 0)
    finally:
        again.close()


def replay(seed: int, start: int, actions: np.ndarray) -> list:
    """The protocol's replay, written out here: what the run's segment looked like."""
    env, _ = pebble.make_env(ENV_ID, render_mode="rgb_array")
    env.reset(seed=int(seed))
    for t in range(start):
        env.step(actions[t])
    frames = []
    for t in range(SEGMENT_LEN):
        frames.append(env.render())
        env.step(actions[start + t])
    return frames


def test_a_clip_shows_the_segment_the_run_drew_frame_by_frame(run):
    run_dir, server, arrays = run
    for query, side in [(2, 1), (0, 0), (2, 0)]:  # one environment renders them all, in any order
        status, jpeg = request(server, "GET", f"/clips/0/{query}/{side}.jpg")
        assert status == 200
        sheet = np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB"), np.float32)
        assert sheet.shape == (120, 5 * 160, 3)  # 5 frames a row, no scaling under 160 px
        shown = [sheet[:, 160 * t:160 * (t + 1)] for t in range(SEGMENT_LEN)]
        expected = replay(arrays[f"seed{side}"][query], arrays[f"start{side}"][query],
                          arrays[f"actions{side}"][query])
        for t, frame in enumerate(shown):
            errors = [np.abs(frame - other).mean() for other in expected]
            assert errors[t] < 2.0  # JPEG's loss only
            assert np.argmin(errors) == t  # and not a neighbouring frame
    clips = sorted(os.listdir(run_dir / "queries" / "session_0000_clips"))
    assert [name[:6] for name in clips] == ["0000_0", "0002_0", "0002_1"]
    assert request(server, "GET", "/clips/0/2/1.jpg")[1] == jpeg_of(run_dir, clips[2])  # cached


def jpeg_of(run_dir, name: str) -> bytes:
    return (run_dir / "queries" / "session_0000_clips" / name).read_bytes()


def test_a_clip_keeps_the_renderer_s_full_resolution():
    frames = [np.full((480, 640, 3), 10 * t, np.uint8) for t in range(12)]
    sheet = Image.open(io.BytesIO(label_server.sprite_sheet(frames)))
    assert sheet.size == (10 * 640, 2 * 480)  # 10 frames a row, each as rendered


@pytest.mark.parametrize("path", [
    "/../config.json", "/config.json", "/etc/passwd", "/../../../../etc/passwd",
    "/queries/session_0000.npz", "/%2e%2e/config.json", "/clips/0/0/../../../config.json",
    "/api/state/../../config.json", "/index.html", "/queries/"])
def test_nothing_but_the_page_its_state_and_clips_is_served(run, path):
    status, reply = request(run[1], "GET", path)
    assert status == 404 and reply == {"error": f"not found: {path}"}


@pytest.mark.parametrize("path, status", [("/clips/0/4/0.jpg", 404), ("/clips/0/0/2.jpg", 404),
                                          ("/clips/1/0/0.jpg", 409), ("/clips/0/-1/0.jpg", 404)])
def test_a_clip_outside_the_session_is_refused(run, path, status):
    assert request(run[1], "GET", path)[0] == status
    assert not (run[0] / "queries" / "session_0000_clips").exists()


def test_the_page_is_served_at_the_root(run):
    status, page = request(run[1], "GET", "/")
    assert status == 200 and b"Left is better" in page and b"Can't tell" in page


def test_without_a_config_the_server_says_which_run_to_give(tmp_path):
    with pytest.raises(FileNotFoundError, match="--teacher human"):
        label_server.serve(str(tmp_path), "127.0.0.1", 0)
    command = [sys.executable, "label_server.py", str(tmp_path / "nowhere")]
    result = subprocess.run(command, capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=120)
    assert result.returncode == 2 and result.stderr == (
        f"error: {tmp_path / 'nowhere' / 'config.json'} does not exist: give the --output-dir of "
        "a run started with --teacher human\n")


def raw_request(server, lines: list[str], body: bytes = b"") -> tuple[int, dict, dict]:
    """(status, headers, JSON body) of a request sent byte for byte."""
    import socket

    with socket.create_connection(server.server_address[:2], timeout=60) as connection:
        connection.sendall("\r\n".join(lines + ["", ""]).encode() + body)
        reply = b""
        while chunk := connection.recv(65536):
            reply += chunk
    head, _, payload = reply.partition(b"\r\n\r\n")
    status_line, *header_lines = head.decode().split("\r\n")
    headers = dict(line.split(": ", 1) for line in header_lines)
    return int(status_line.split()[1]), headers, json.loads(payload) if payload else {}


@pytest.mark.parametrize("host", ["evil.example", "evil.example:8000", "127.0.0.1.evil.example", ""])
def test_a_host_header_that_does_not_name_the_server_is_a_403(run, host):
    run_dir, server, _ = run
    port = server.server_address[1]
    body = json.dumps({"session": 0, "id": 0, "label": "left"}).encode()
    headers = [f"Host: {host}"] if host else []
    status, _, reply = raw_request(server, ["POST /api/answer HTTP/1.1", *headers, "Content-Type: application/json",
                                            f"Content-Length: {len(body)}", "Connection: close"], body)
    assert status == 403 and "is not this server's address" in reply["error"]
    assert not (run_dir / "queries" / "session_0000_answers.json").exists()
    for good in (f"127.0.0.1:{port}", f"localhost:{port}", "LOCALHOST", "127.0.0.1"):
        status, _, _ = raw_request(server, ["GET /api/state HTTP/1.1", f"Host: {good}", "Connection: close"])
        assert status == 200, good


def this_machine_s_address() -> str | None:
    """A non-loopback IPv4 address of this machine, or None: the source address of the route to a
    documentation address (connect() on a UDP socket picks it and sends nothing)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("203.0.113.1", 9))
        except OSError:  # no route
            return None
        address = probe.getsockname()[0]
    return None if address.startswith("127.") else address


def test_on_every_interface_the_machine_s_own_names_and_addresses_are_its_host(tmp_path):
    """--host 0.0.0.0: a browser elsewhere sends this machine's name or address as Host. Every
    request goes to 127.0.0.1, only its Host header differs."""
    import socket

    run_dir = tmp_path / "run"
    make_run(run_dir)
    server = label_server.serve(str(run_dir), "0.0.0.0", 0)
    port = server.server_address[1]
    loopback = type("Address", (), {"server_address": ("127.0.0.1", port)})
    ours = [socket.gethostname(), f"{socket.gethostname().upper()}:{port}", socket.getfqdn(),
            f"127.0.0.2:{port}"]  # all of 127/8 is this machine, though not named 127.0.0.1
    ours += [f"{address}:{port}" for address in [this_machine_s_address()] if address]
    foreign = ["evil.example", f"{socket.gethostname()}.evil.example:{port}", f"203.0.113.9:{port}",
               "[2001:db8::1]", "0x7f000001"]
    try:
        for host in ours + foreign:
            status, _, reply = raw_request(loopback, ["GET /api/state HTTP/1.1", f"Host: {host}",
                                                      "Connection: close"])
            assert status == (200 if host in ours else 403), (host, reply)
    finally:
        server.close()


def test_bound_to_one_address_no_other_host_is_accepted(run):
    """127.0.0.1: its own forms only (127.0.0.2 reaches this machine but not this socket)."""
    port = run[1].server_address[1]
    for host in (f"127.0.0.2:{port}", "203.0.113.9"):
        status, _, _ = raw_request(run[1], ["GET /api/state HTTP/1.1", f"Host: {host}",
                                            "Connection: close"])
        assert status == 403, host


@pytest.mark.parametrize("method", ["HEAD", "PUT", "DELETE", "PATCH", "OPTIONS", "TRACE", "FOO"])
def test_a_method_other_than_get_and_post_is_a_json_405(run, method):
    status, headers, reply = raw_request(run[1], [f"{method} /api/state HTTP/1.1", "Host: 127.0.0.1",
                                                  "Connection: close"])
    assert status == 405 and headers["Allow"] == "GET, POST" and headers["Content-Type"] == "application/json"
    if method != "HEAD":  # a HEAD reply has no body
        assert reply == {"error": f"method {method} is not allowed here (GET and POST only)"}


def test_a_chunked_body_is_refused_for_what_it_is(run):
    run_dir, server, _ = run
    body = json.dumps({"session": 0, "id": 0, "label": "left"}).encode()
    chunked = f"{len(body):x}\r\n".encode() + body + b"\r\n0\r\n\r\n"
    status, _, reply = raw_request(server, ["POST /api/answer HTTP/1.1", "Host: 127.0.0.1",
                                            "Content-Type: application/json", "Transfer-Encoding: chunked",
                                            "Connection: close"], chunked)
    assert status == 411 and "Content-Length" in reply["error"] and "chunked" in reply["error"]
    assert not (run_dir / "queries" / "session_0000_answers.json").exists()


@pytest.mark.parametrize("body", [b"[" * 4000 + b"]" * 4000, b'{"session": ' + b"[" * 3000 + b"]" * 3000 + b"}",
                                  b'{"session": 0, "id": 0, "label": {"a": "left"}}',
                                  b'{"session": [0], "id": 0, "label": "left"}'])
def test_a_nested_body_is_a_400_not_a_crash(run, body):
    run_dir, server, _ = run
    status, reply = request(server, "POST", "/api/answer", body)
    assert status == 400 and ("not valid JSON" in reply["error"] or "flat JSON object" in reply["error"]
                              or "must be a JSON object" in reply["error"])
    assert request(server, "GET", "/api/state")[0] == 200  # still serving


def test_the_server_writes_its_address_in_the_run_while_it_serves(tmp_path):
    run_dir = tmp_path / "run"
    make_run(run_dir)
    server = label_server.serve(str(run_dir), "0.0.0.0", 0)
    try:
        port = server.server_address[1]
        assert server.url == f"http://127.0.0.1:{port}/"  # an address a browser here can open
        assert (run_dir / "queries" / "page_url.txt").read_text() == server.url
    finally:
        server.close()
    assert not (run_dir / "queries" / "page_url.txt").exists()


def start_server_process(run_dir, **popen) -> subprocess.Popen:
    """label_server.py RUN_DIR --port 0 as a user starts it, once it serves (page_url.txt)."""
    process = subprocess.Popen([sys.executable, "label_server.py", str(run_dir), "--port", "0"],
                               cwd=ROOT, env=ENV, stderr=subprocess.PIPE, text=True, **popen)
    deadline = time.time() + 120
    while not (run_dir / "queries" / "page_url.txt").exists():
        assert process.poll() is None and time.time() < deadline, process.communicate()
        time.sleep(0.1)
    return process


@pytest.mark.parametrize("stop", ["SIGTERM", "SIGINT", "SIGHUP"])
def test_a_server_stopped_by_a_signal_removes_its_address_from_the_run(tmp_path, stop):
    """Else the run prints an address where nothing serves."""
    import signal

    run_dir = tmp_path / "run"
    make_run(run_dir)
    ignore_sigint = lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)  # as a background job starts it
    process = start_server_process(run_dir, stdout=subprocess.DEVNULL, preexec_fn=ignore_sigint)
    process.send_signal(getattr(signal, stop))
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 0 and "Traceback" not in stderr, stderr
    assert not (run_dir / "queries" / "page_url.txt").exists()


def test_a_server_that_fails_after_it_started_removes_its_address_from_the_run(tmp_path):
    """Its first line goes to a closed pipe (as to `| head -0`): a BrokenPipeError, after the server
    started and wrote page_url.txt, and before it waits."""
    run_dir = tmp_path / "run"
    make_run(run_dir)
    process = subprocess.Popen([sys.executable, "label_server.py", str(run_dir), "--port", "0"],
                               cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    process.stdout.close()  # long before it prints (it imports torch first)
    stderr = process.communicate(timeout=120)[1]
    assert process.returncode != 0 and "BrokenPipeError" in stderr, stderr
    assert not (run_dir / "queries" / "page_url.txt").exists()


def test_an_idle_connection_is_closed_after_the_timeout(run, monkeypatch):
    """Connections that send nothing, or half a request, are closed (each holds a thread while it
    is open); the server goes on serving."""
    import socket

    assert 0 < label_server.Handler.timeout <= 60  # idle for a minute at most
    monkeypatch.setattr(label_server.Handler, "timeout", 0.5)  # shortened for the test
    server = run[1]
    idle = [socket.create_connection(server.server_address[:2], timeout=10) for _ in range(20)]
    idle[0].sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # no end of headers
    start = time.time()
    for connection in idle:
        with connection:
            assert connection.recv(65536) == b""  # closed by the server (a timeout raises)
    assert time.time() - start < 5
    assert request(server, "GET", "/api/state")[0] == 200


def test_an_ipv6_host_is_served():
    import socket

    if not socket.has_ipv6:
        pytest.skip("no IPv6 on this machine")
    try:
        socket.socket(socket.AF_INET6).bind(("::1", 0))
    except OSError:
        pytest.skip("no IPv6 loopback on this machine")
    run_dir = Path(tempfile.mkdtemp()) / "run"
    make_run(run_dir)
    server = label_server.serve(str(run_dir), "::1", 0)
    try:
        port = server.server_address[1]
        assert server.url == f"http://[::1]:{port}/"
        connection = http.client.HTTPConnection("::1", port, timeout=60)
        connection.request("GET", "/api/state", headers={"Host": f"[::1]:{port}"})
        response = connection.getresponse()
        assert response.status == 200 and json.loads(response.read())["session"] == 0
    finally:
        server.close()


def test_a_rendering_failure_answers_every_clip_request_and_the_server_keeps_serving(tmp_path):
    """Without an OpenGL backend (MUJOCO_GL=glfw and no display), a DMC task's clip cannot render: each request gets
    the error with its hint, and the server answers the next requests (a second OpenGL set-up used to abort it)."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text(json.dumps({"env_id": "walker-walk", "segment_len": 5, "seed": 1}))
    arrays = {"step": np.int64(1000)}
    for side in (0, 1):
        arrays.update({f"seed{side}": np.array([1, 2]), f"start{side}": np.array([0, 3]),
                       f"actions{side}": np.zeros((2, 8, 6), np.float32)})
    (run_dir / "queries").mkdir()
    np.savez(run_dir / "queries" / "session_0000.npz", **arrays)
    env = {key: value for key, value in ENV.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    process = subprocess.Popen([sys.executable, "label_server.py", str(run_dir), "--port", "0"], cwd=ROOT,
                               env=env | {"MUJOCO_GL": "glfw"}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        while not (run_dir / "queries" / "page_url.txt").exists():
            assert process.poll() is None and time.time() < deadline, process.communicate()
            time.sleep(0.2)
        url = (run_dir / "queries" / "page_url.txt").read_text()
        host, port = url.removeprefix("http://").rstrip("/").rsplit(":", 1)
        server = type("Address", (), {"server_address": (host, int(port))})
        for path in ("/clips/0/0/0.jpg", "/clips/0/1/1.jpg", "/clips/0/0/0.jpg"):
            status, reply = request(server, "GET", path)
            assert status == 500 and "could not render the clip" in reply["error"] and "MUJOCO_GL=egl" in reply["error"]
        assert request(server, "GET", "/api/state")[0] == 200 and process.poll() is None
    finally:
        process.terminate()
        process.communicate(timeout=60)


def test_a_stopped_server_frees_its_opengl_context_without_a_traceback(tmp_path):
    """A DMC clip rendered with osmesa, then the server closed: the environment frees its context on the render
    thread, so nothing is left for the interpreter's exit to free (it printed tracebacks)."""
    import ctypes.util

    if ctypes.util.find_library("OSMesa") is None:
        pytest.skip("no osmesa (Debian: apt-get install libosmesa6)")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text(json.dumps({"env_id": "walker-walk", "segment_len": 3, "seed": 1}))
    arrays = {"step": np.int64(1000)}
    for side in (0, 1):
        arrays.update({f"seed{side}": np.array([1]), f"start{side}": np.array([0]),
                       f"actions{side}": np.zeros((1, 3, 6), np.float32)})
    (run_dir / "queries").mkdir()
    np.savez(run_dir / "queries" / "session_0000.npz", **arrays)
    script = ("import sys, http.client, label_server\n"
              f"server = label_server.serve({str(run_dir)!r}, '127.0.0.1', 0)\n"
              "connection = http.client.HTTPConnection(*server.server_address[:2], timeout=120)\n"
              "connection.request('GET', '/clips/0/0/0.jpg')\n"
              "print(connection.getresponse().status)\n"
              "server.close()\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=300,
                            env=ENV | {"MUJOCO_GL": "osmesa"})
    assert result.returncode == 0 and result.stdout.strip() == "200", result.stderr[-2000:]
    assert "Traceback" not in result.stderr and "Exception ignored" not in result.stderr, result.stderr[-2000:]


# A real browser: headless Chromium (Debian's chromium and chromium-driver) driven by selenium
def chromium() -> tuple[str | None, str | None]:
    """The paths of the browser and its driver, or None."""
    binary = shutil.which("chromium") or shutil.which("chromium-browser")
    return binary, shutil.which("chromedriver")


NO_BROWSER = ("headless Chromium not found: install Debian's chromium and chromium-driver "
              "(apt-get install chromium chromium-driver) and selenium (requirements.txt)")


@pytest.fixture
def browser():
    binary, driver_path = chromium()
    try:
        from selenium import webdriver
    except ImportError:
        binary = None
    if binary is None or driver_path is None:
        pytest.skip(NO_BROWSER)
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                 "--window-size=1000,760"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=webdriver.ChromeService(driver_path))
    yield driver
    driver.quit()


def wait_for(driver, condition, timeout: float = 60):
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, timeout).until(lambda _: condition())


def text(driver, element_id: str) -> str:
    return driver.find_element("id", element_id).text


def pair_ready(driver) -> bool:
    """The pair's clips are drawn and its buttons take answers."""
    button = driver.find_element("css selector", "button[data-label=left]")
    return button.is_displayed() and button.is_enabled()


def press(driver, key: str):
    from selenium.webdriver.common.action_chains import ActionChains

    ActionChains(driver).send_keys(key).perform()


def click(driver, label: str):
    driver.find_element("css selector", f"button[data-label={label}]").click()


def shoot(driver, name: str):
    """LABEL_PAGE_SCREENSHOTS=docs saves the page's states as docs/<name>."""
    if os.environ.get("LABEL_PAGE_SCREENSHOTS"):
        driver.save_screenshot(os.path.join(os.environ["LABEL_PAGE_SCREENSHOTS"], name))


def frame_number(driver) -> int:
    return int(text(driver, "frame").split()[1])


def test_the_page_fits_800_by_600_and_its_playback_pauses_slows_and_steps(run, browser):
    run_dir, server, _ = run
    browser.set_window_size(800, 600)
    browser.get(server.url)
    wait_for(browser, lambda: pair_ready(browser))
    layout = browser.execute_script(
        "const r = id => document.getElementById(id).getBoundingClientRect();"
        "const buttons = [...document.querySelectorAll('button')].map(b => b.getBoundingClientRect());"
        "return {width: innerWidth, height: innerHeight, scroll: document.documentElement.scrollWidth,"
        " right: r('clip1').right, bottom: Math.max(...buttons.map(b => b.bottom)),"
        " canvas: document.getElementById('clip0').width}")
    assert layout["width"] <= 800 and layout["height"] <= 600
    assert layout["scroll"] <= layout["width"] and layout["right"] <= layout["width"]  # no sideways scrolling
    assert layout["bottom"] <= layout["height"]  # every button above the fold
    assert layout["canvas"] == 160  # the toy renderer's frames are 160 x 120: drawn at that resolution
    shoot(browser, "label_page.png")
    press(browser, "p")  # pause
    wait_for(browser, lambda: "paused" in text(browser, "frame"))
    held = frame_number(browser)
    time.sleep(0.6)
    assert frame_number(browser) == held and text(browser, "pause").startswith("Play")
    press(browser, ".")
    wait_for(browser, lambda: frame_number(browser) == min(held + 1, SEGMENT_LEN))
    press(browser, ",")
    press(browser, ",")
    wait_for(browser, lambda: frame_number(browser) == max(min(held + 1, SEGMENT_LEN) - 2, 1))
    browser.find_element("id", "slow").click()
    wait_for(browser, lambda: "half speed" in text(browser, "frame"))
    press(browser, " ")  # play again, at half speed
    wait_for(browser, lambda: "paused" not in text(browser, "frame"))
    seen = set()
    deadline = time.time() + 5
    while len(seen) < 2 and time.time() < deadline:
        seen.add(frame_number(browser))
        time.sleep(0.05)
    assert len(seen) >= 2  # it plays


def test_the_page_says_when_a_session_is_taken_and_when_the_run_has_finished(run, browser):
    run_dir, server, _ = run
    browser.set_window_size(800, 600)
    browser.get(server.url)
    wait_for(browser, lambda: pair_ready(browser))
    for query in (1, 2, 3):
        answer(server, query, "left")
    press(browser, "1")  # the last pair (0), in the page
    wait_for(browser, lambda: text(browser, "waiting").startswith(
        "Session 0: 4 answers taken, the run is learning."))
    shoot(browser, "label_page_session_done.png")
    (run_dir / "final_model.pt").write_bytes(b"")  # what a run writes at its end
    wait_for(browser, lambda: text(browser, "waiting").startswith("The run has finished"))
    shoot(browser, "label_page_run_finished.png")


def test_a_person_labels_a_session_in_a_browser(tmp_path, browser):
    from selenium.webdriver.common.keys import Keys

    run_dir = tmp_path / "run"
    make_run(run_dir)
    server = label_server.serve(str(run_dir), "127.0.0.1", 0)
    try:
        browser.get(server.url)
        wait_for(browser, lambda: pair_ready(browser))
        assert text(browser, "task") == ENV_ID
        assert text(browser, "progress") == "1 / 4"
        time.sleep(0.5)  # a few frames into the loop
        drawn = browser.execute_script(
            "return [0, 1].map(s => document.getElementById('clip' + s).toDataURL())")
        blank = browser.execute_script(
            "const c = document.createElement('canvas'); c.width = 160; c.height = 120;"
            "return c.toDataURL()")
        assert blank not in drawn and drawn[0] != drawn[1]  # two different clips on screen
        screenshot = tmp_path / "label_page.png"
        browser.save_screenshot(str(screenshot))
        if os.environ.get("LABEL_PAGE_SCREENSHOT"):  # e.g. docs/label_page.png
            shutil.copy(screenshot, os.environ["LABEL_PAGE_SCREENSHOT"])

        steps = [(lambda: press(browser, Keys.ARROW_LEFT), "2 / 4"),  # 0: left
                 (lambda: click(browser, "equal"), "3 / 4"),  # 1: equal
                 (lambda: press(browser, "s"), "4 / 4"),  # 2: skip
                 (lambda: press(browser, "u"), "3 / 4"),  # undo 2
                 (lambda: click(browser, "right"), "4 / 4"),  # 2: right
                 (lambda: press(browser, "0"), "")]  # 3: skip; the session is done
        for act, progress in steps:
            act()
            wait_for(browser, lambda: text(browser, "progress") == progress)
            if progress:
                wait_for(browser, lambda: pair_ready(browser))
        wait_for(browser, lambda: browser.find_element("id", "waiting").is_displayed())
        assert answers_file(run_dir) == {"order": [0, 1, 2, 3], "answers": {
            "0": "left", "1": "equal", "2": "right", "3": "skip"}}
        assert text(browser, "message") == ""
        write_session(run_dir, 1, 3)  # the run's next session: the waiting page finds it
        wait_for(browser, lambda: text(browser, "progress") == "1 / 3" and pair_ready(browser))
        assert "session 1" in text(browser, "where")
    finally:
        server.close()


def test_the_page_moves_on_when_another_browser_answered_its_pair(tmp_path, browser):
    run_dir = tmp_path / "run"
    make_run(run_dir)
    server = label_server.serve(str(run_dir), "127.0.0.1", 0)
    try:
        browser.get(server.url)
        wait_for(browser, lambda: pair_ready(browser))
        assert answer(server, 0, "equal")[0] == 200  # the other browser
        press(browser, "1")  # this page still shows pair 0
        wait_for(browser, lambda: text(browser, "message").startswith(
            "pair 0 was answered first in another browser: this answer was not taken"))
        shoot(browser, "label_page_other_browser.png")
        wait_for(browser, lambda: text(browser, "progress") == "2 / 4" and pair_ready(browser))
        assert "pair 1" in text(browser, "where")
        browser.refresh()  # a reload resumes at the first unanswered pair
        wait_for(browser, lambda: pair_ready(browser))
        assert "pair 1" in text(browser, "where")
        assert answers_file(run_dir) == {"order": [0], "answers": {"0": "equal"}}
    finally:
        server.close()
