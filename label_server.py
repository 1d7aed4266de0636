"""The labelling page of `--teacher human` (docs/human_teacher.md): shows a run's waiting feedback
session to a person as pairs of clips and writes each answer, as it is given, where the run reads
it."""
import concurrent.futures
import hashlib
import http.server
import io
import ipaddress
import json
import math
import os
import re
import signal
import socket
import sys
import threading
import urllib.parse
from dataclasses import dataclass
from typing import Annotated

import numpy as np
import tyro
from PIL import Image

import pebble
import sim_teacher


@dataclass
class Args:
    run_dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """the run's --output-dir (it holds config.json and queries/)"""
    host: str = "127.0.0.1"
    """address to listen on (127.0.0.1: this machine only; from elsewhere, forward the port)"""
    port: int = 8000
    """port to listen on (0: any free port)"""


LABELS = tuple(sim_teacher.ANSWER_LABELS)  # y = 0, 1, 0.5, dropped
SHEET_COLUMNS = 10  # frames a row in a clip's sprite sheet
JPEG_QUALITY = 90
SESSION_FILE = re.compile(r"session_(\d{4,})\.npz")
CLIP_URL = re.compile(r"/clips/(\d{1,6})/(\d{1,9})/([01])\.jpg")
MAX_BODY = 10_000  # bytes of a POST's JSON
METHODS = ("GET", "POST")  # every other method: 405
IDLE_TIMEOUT = 30.0  # seconds a connection may wait for a request, or a reply to go out


class RequestError(Exception):
    """A request the server refuses: HTTP status, one-line message, and the session's state where
    the page should move on (a pair answered meanwhile)."""

    def __init__(self, status: int, message: str, state: dict | None = None):
        super().__init__(message)
        self.status = status
        self.state = state


@dataclass
class Session:
    """One feedback session's queries (the protocol's queries/session_NNNN.npz): for side 0 (left)
    and 1 (right), each query's episode reset seed, segment start and the episode's actions up to
    the segment's end."""
    number: int
    step: int
    n: int
    seeds: list[np.ndarray]
    starts: list[np.ndarray]
    actions: list[np.ndarray]


def load_session(path: str, number: int, segment_len: int) -> Session:
    data = sim_teacher.load_queries(path)
    session = Session(number, int(data["step"]), len(data["seed0"]), [data["seed0"], data["seed1"]],
                      [data["start0"], data["start1"]], [data["actions0"], data["actions1"]])
    for side in (0, 1):
        if np.any(session.starts[side] + segment_len > session.actions[side].shape[1]):
            raise ValueError(f"{path}: a segment of side {side} ends after its actions")
    return session


def replay_frames(env, seed: int, start: int, actions: np.ndarray, segment_len: int) -> list:
    """The segment's frames, by replaying its episode: the reset seed and the same actions give
    the same states (MuJoCo is deterministic); frame t is the state before action start + t."""
    env.reset(seed=int(seed))
    for action in actions[:start]:
        env.step(action)
    frames = []
    for t in range(segment_len):
        frames.append(env.render())
        env.step(actions[start + t])
    return frames


def sprite_sheet(frames: list) -> bytes:
    """The frames as one JPEG, SHEET_COLUMNS a row, at the renderer's full resolution."""
    images = [Image.fromarray(np.asarray(frame, np.uint8)) for frame in frames]
    width, height = images[0].size
    columns = min(len(images), SHEET_COLUMNS)
    rows = math.ceil(len(images) / columns)
    sheet = Image.new("RGB", (columns * width, rows * height))
    for i, image in enumerate(images):
        sheet.paste(image, ((i % columns) * width, (i // columns) * height))
    data = io.BytesIO()
    sheet.save(data, "JPEG", quality=JPEG_QUALITY)
    return data.getvalue()


def is_local_address(name: str) -> bool:
    """An IP address (IPv6 in brackets) of this machine: a socket can be bound to it (nothing is
    sent), which an address of another machine refuses."""
    try:
        if name.startswith("[") and name.endswith("]"):
            address = ipaddress.IPv6Address(name[1:-1])
        else:
            address = ipaddress.IPv4Address(name)
    except ValueError:
        return False
    family = socket.AF_INET6 if address.version == 6 else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as probe:
            probe.bind((str(address), 0))
    except OSError:
        return False
    return True


class LabelServer(http.server.ThreadingHTTPServer):
    """The page, the session's state and its clips; answers go to the answers file under a lock.
    Clips render on one worker thread (one environment, one OpenGL context), when first asked."""

    daemon_threads = True
    request_queue_size = 64  # connections waiting to be accepted (the default 5 resets a burst)

    def __init__(self, run_dir: str, host: str, port: int):
        config_path = os.path.join(run_dir, "config.json")
        if not os.path.exists(config_path):
            raise FileNotFoundError(f"{config_path} does not exist: give the --output-dir of a run "
                                    "started with --teacher human")
        with open(config_path) as f:
            config = json.load(f)
        self.env_id = config["env_id"]
        self.segment_len = int(config["segment_len"])
        self.run_dir = run_dir
        self.queries_dir = os.path.join(run_dir, "queries")
        self.lock = threading.Lock()  # the answers files and the session read last
        self.loaded = None  # (number, the file's mtime, Session) of the session read last
        self.renderer = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="render")
        self.renders = {}  # clip path -> Future of its rendering
        self.renders_lock = threading.Lock()
        self.env = None  # made and used on the render thread only
        self.render_error = None  # the first failure to render: kept (OpenGL is not tried twice)
        self.closed = False
        # the Host header must name this server (a page elsewhere that rebinds a name of its own to
        # 127.0.0.1 sends its own name): 127.0.0.1, localhost, [::1], or what --host says; on every
        # interface, also this machine's names and addresses
        self.hosts = {"127.0.0.1", "localhost", "[::1]", f"[{host}]" if ":" in host else host}
        self.address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
        super().__init__((host, port), Handler)
        self.everywhere = self.server_address[0] in ("0.0.0.0", "::")
        if self.everywhere:
            self.hosts |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        self.url_file = sim_teacher.page_url_path(run_dir)
        os.makedirs(os.path.dirname(self.url_file), exist_ok=True)
        sim_teacher.save_file(self.url_file, self.url.encode())

    def names_this_server(self, name: str) -> bool:
        """A Host header's name (without its port) is one of this server's."""
        return name.lower() in self.hosts or (self.everywhere and is_local_address(name))

    def handle_error(self, request, client_address):
        if not isinstance(sys.exc_info()[1], ConnectionError):  # a page closed mid-reply: quiet
            super().handle_error(request, client_address)

    @property
    def url(self) -> str:
        """The page's address for a browser on this machine (for 0.0.0.0 or ::, its loopback)."""
        host, port = self.server_address[:2]
        host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
        return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"

    def close(self):
        """Stops serving and rendering (a second call does nothing)."""
        if self.closed:
            return
        self.closed = True
        try:
            with open(self.url_file) as f:
                if f.read() == self.url:  # not another server's, started since
                    os.remove(self.url_file)
        except OSError:
            pass
        self.shutdown()
        self.server_close()
        for future in list(self.renders.values()):
            future.cancel()  # clips not started yet
        if self.env is not None:  # frees its OpenGL context on the thread that made it, now
            self.renderer.submit(self.env.close).result()
        self.renderer.shutdown()

    # Sessions and answers (call with self.lock held)
    def session_path(self, number: int, suffix: str = ".npz") -> str:
        return sim_teacher.queries_path(self.run_dir, number, suffix)

    def session(self, number: int) -> Session:
        """The session's queries, read again if the run wrote the file again."""
        path = self.session_path(number)
        mtime = os.stat(path).st_mtime_ns
        if self.loaded is None or self.loaded[:2] != (number, mtime):
            self.loaded = (number, mtime, load_session(path, number, self.segment_len))
        return self.loaded[2]

    def read_answers(self, number: int) -> dict:
        return sim_teacher.read_answers(self.run_dir, number)

    def write_answers(self, number: int, answers: dict):
        sim_teacher.write_answers(self.run_dir, number, answers)

    def newest(self) -> Session | None:
        """The run's newest session, done or not (None before its first)."""
        names = os.listdir(self.queries_dir) if os.path.isdir(self.queries_dir) else []
        numbers = [int(match.group(1)) for match in map(SESSION_FILE.fullmatch, names) if match]
        return self.session(max(numbers)) if numbers else None

    def current(self) -> Session | None:
        """The newest session if it is not done (not every query answered). The run waits at one
        session at a time, so every older session is done."""
        session = self.newest()
        if session is None or len(self.read_answers(session.number)["answers"]) == session.n:
            return None
        return session

    def state(self) -> dict:
        """What the page shows: the task, the current session's progress, its first unanswered
        pair (next), the one after (to load ahead) and the last answered (for undo)."""
        state = {"env_id": self.env_id, "segment_len": self.segment_len,
                 "columns": min(self.segment_len, SHEET_COLUMNS), "session": None, "done": None,
                 "run_finished": os.path.exists(os.path.join(self.run_dir, "final_model.pt"))}
        session = self.current()
        if session is None:  # the last session answered (the run learns from it), or none yet
            done = self.newest()
            if done is not None:
                state["done"] = {"session": done.number, "answers": done.n}
            return state
        answers = self.read_answers(session.number)
        unanswered = [i for i in range(session.n) if str(i) not in answers["answers"]]
        state.update(session=session.number, step=session.step, n=session.n,
                     answered=session.n - len(unanswered), next=unanswered[0],
                     after=unanswered[1] if len(unanswered) > 1 else None,
                     last=answers["order"][-1] if answers["order"] else None)
        return state

    def checked_query(self, request: dict) -> Session:
        """The current session, after checking the request's session number and query id."""
        number = request.get("session")
        query = request.get("id")
        for name, value in (("session", number), ("id", query)):
            if type(value) is not int:
                raise RequestError(400, f"{name} must be an integer, not {value!r}")
        session = self.current()
        if session is None or number != session.number:
            current = "none is waiting" if session is None else f"it is {session.number}"
            raise RequestError(409, f"session {number} is not the current session ({current})",
                               self.state())
        if not 0 <= query < session.n:
            raise RequestError(404, f"session {number} has no pair {query} (its pairs are 0 to "
                               f"{session.n - 1})")
        return session

    def answer(self, request: dict) -> dict:
        with self.lock:
            if request.get("label") not in LABELS:
                raise RequestError(400, f"label {request.get('label')!r} is not one of "
                                   f"{', '.join(LABELS)}")
            session = self.checked_query(request)
            answers = self.read_answers(session.number)
            if str(request["id"]) in answers["answers"]:
                raise RequestError(409, f"pair {request['id']} was answered first in another "
                                   "browser: this answer was not taken, the first one stands",
                                   self.state())
            answers["order"].append(request["id"])
            answers["answers"][str(request["id"])] = request["label"]
            self.write_answers(session.number, answers)
            return self.state()

    def undo(self, request: dict) -> dict:
        """Removes the session's last answer; the request names it (the id the page shows as last)
        so that a page never undoes an answer given meanwhile in another browser."""
        with self.lock:
            session = self.checked_query(request)
            answers = self.read_answers(session.number)
            last = answers["order"][-1] if answers["order"] else None
            if request["id"] != last:
                raise RequestError(409, f"pair {request['id']} is not the last answer (the last "
                                   f"is {last})", self.state())
            answers["order"].pop()
            del answers["answers"][str(last)]
            self.write_answers(session.number, answers)
            return self.state()

    # Clips
    def clip(self, number: int, query: int, side: int) -> str:
        """The path of a clip of the current session, rendered and cached first if it is not."""
        with self.lock:
            session = self.checked_query({"session": number, "id": query})
        seed = session.seeds[side][query]
        start = int(session.starts[side][query])
        actions = session.actions[side][query, :start + self.segment_len]
        # named by what it shows: a session file written again with other queries gets new clips
        digest = hashlib.sha256(f"{self.env_id} {self.segment_len} {seed} {start}".encode())
        digest.update(np.ascontiguousarray(actions).tobytes())
        clips_dir = self.session_path(number, "_clips")
        path = os.path.join(clips_dir, f"{query:04d}_{side}_{digest.hexdigest()[:16]}.jpg")
        with self.renders_lock:
            if self.render_error is not None:
                raise RequestError(500, self.render_error)
            if not os.path.exists(path) and path not in self.renders:
                self.renders[path] = self.renderer.submit(self.render_clip, path, seed, start,
                                                          actions)
            future = self.renders.get(path)
        if future is not None:
            try:
                future.result()
            except concurrent.futures.CancelledError:
                raise RequestError(503, "the label server is stopping") from None
            except Exception as error:
                # kept: a second try of a failed OpenGL set-up can abort the whole process
                message = f"{type(error).__name__}: {error}".splitlines()[0]
                with self.renders_lock:
                    self.renders.pop(path, None)
                    self.render_error = self.render_error or (
                        f"could not render the clip: {message} (no display? restart "
                        "label_server.py with MUJOCO_GL=egl or osmesa: docs/human_teacher.md)")
                    raise RequestError(500, self.render_error) from None
        return path

    def render_clip(self, path: str, seed: int, start: int, actions: np.ndarray):
        if self.env is None:
            self.env, _ = pebble.make_env(self.env_id, render_mode="rgb_array")
        frames = replay_frames(self.env, seed, start, actions, self.segment_len)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        sim_teacher.save_file(path, sprite_sheet(frames))


class Handler(http.server.BaseHTTPRequestHandler):
    """Routes by exact path: nothing in a URL is ever used as a file path."""

    server: LabelServer
    timeout = IDLE_TIMEOUT  # an idle connection is closed (else it holds its thread while open)

    def allowed(self) -> bool:
        """The Host header names this server, else a 403 goes out."""
        host = self.headers.get("Host", "")
        name = host.rsplit(":", 1)[0] if re.fullmatch(r".*:\d+", host) else host
        if self.server.names_this_server(name):
            return True
        self.send_json(403, {"error": f"Host {host!r} is not this server's address (open "
                                      f"{self.server.url})"})
        return False

    def send_error(self, code, message=None, explain=None):
        """Every refusal as JSON: a method other than GET and POST (405), a bad request line..."""
        if code == 501 or self.command not in METHODS + (None,):
            code, message = 405, f"method {self.command} is not allowed here (GET and POST only)"
        self.close_connection = True
        body = json.dumps({"error": message or http.HTTPStatus(code).phrase}).encode()
        self.send_response(code, message)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        if code == 405:
            self.send_header("Allow", ", ".join(METHODS))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def do_GET(self):
        if not self.allowed():
            return
        path = urllib.parse.urlsplit(self.path).path
        clip = CLIP_URL.fullmatch(path)
        if path == "/":
            self.send(200, "text/html; charset=utf-8", PAGE.encode())
        elif path == "/api/state":
            self.respond(self.server.state)
        elif clip:
            number, query, side = map(int, clip.groups())
            self.respond(lambda: self.server.clip(number, query, side))
        else:
            self.send_json(404, {"error": f"not found: {path}"})

    def do_POST(self):
        if not self.allowed():
            return
        path = urllib.parse.urlsplit(self.path).path
        actions = {"/api/answer": self.server.answer, "/api/undo": self.server.undo}
        if path not in actions:
            self.send_json(404, {"error": f"not found: {path}"})
            return
        self.respond(lambda: actions[path](self.read_json()))

    def read_json(self) -> dict:
        # JSON only: a page from another site cannot send it without the browser asking first,
        # which this server never allows
        if self.headers.get_content_type() != "application/json":
            raise RequestError(415, "the request's body must be JSON (Content-Type: "
                               "application/json)")
        if "Transfer-Encoding" in self.headers:
            self.close_connection = True  # its body is not read
            raise RequestError(411, "send the body whole with a Content-Length (no "
                               f"Transfer-Encoding: {self.headers['Transfer-Encoding']})")
        length = self.headers.get("Content-Length", "")
        if not length.isdigit() or int(length) > MAX_BODY:
            self.close_connection = True
            raise RequestError(413, f"the request's body must have a length of at most {MAX_BODY}"
                               " bytes")
        try:
            request = json.loads(self.rfile.read(int(length)))
        except (ValueError, UnicodeDecodeError, RecursionError):
            raise RequestError(400, "the request's body is not valid JSON") from None
        if not isinstance(request, dict):
            raise RequestError(400, "the request's body must be a JSON object")
        if any(isinstance(value, (dict, list)) for value in request.values()):
            raise RequestError(400, "the request's body must be a flat JSON object (no value is "
                               "an object or a list)")
        return request

    def respond(self, action):
        """The action's state as JSON, or its clip's JPEG; a RequestError's message as JSON."""
        try:
            result = action()
        except RequestError as error:
            body = {"error": str(error)}
            if error.state is not None:
                body["state"] = error.state
            self.send_json(error.status, body)
            return
        except Exception as error:  # e.g. a session file that does not follow the protocol
            self.send_json(500, {"error": f"{type(error).__name__}: {error}".splitlines()[0]})
            return
        if isinstance(result, dict):
            self.send_json(200, result)
        else:
            with open(result, "rb") as f:
                self.send(200, "image/jpeg", f.read())

    def send_json(self, status: int, body: dict):
        self.send(status, "application/json", json.dumps(body).encode())

    def send(self, status: int, content_type: str, body: bytes):
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format, *args):
        pass  # quiet: the page shows errors


def serve(run_dir: str, host: str = "127.0.0.1", port: int = 8000) -> LabelServer:
    """The server, serving on a thread of its own; server.close() stops it."""
    server = LabelServer(run_dir, host, port)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def main():
    args = tyro.cli(Args)
    stops = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    for stop in stops:  # as Ctrl+C, also where SIGINT came ignored (a background job)
        signal.signal(stop, signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_BLOCK, stops)  # held until the server can be closed
    try:
        server = serve(args.run_dir, args.host, args.port)
    except FileNotFoundError as error:
        pebble.fail(str(error))
    except OSError as error:
        pebble.fail(f"cannot listen on {args.host}:{args.port}: {error.strerror} (choose another "
                    "--port)")
    try:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, stops)
        print(f"labelling page of {args.run_dir}: {server.url} (Ctrl+C stops it; every answer is "
              "already on disk)", flush=True)
        if server.everywhere:
            port = server.server_address[1]
            print(f"from another machine: http://{socket.gethostname()}:{port}/ (or this machine's "
                  "address)", flush=True)
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        server.close()


PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>Which is better?</title>
<style>
  body { font-family: system-ui, sans-serif; margin: 10px 16px; background: #f5f5f2; color: #222;
         max-width: 1100px; }
  header { display: flex; flex-wrap: wrap; gap: 4px 24px; align-items: baseline; }
  #task { font-size: 1.4em; font-weight: 600; }
  #progress { font-size: 1.25em; font-variant-numeric: tabular-nums; }
  #where { color: #666; }
  #question { font-size: 1.1em; margin: 6px 0 0; }
  #clips { display: grid; grid-template-columns: 1fr 1fr; gap: 14px; margin: 6px 0 4px; }
  figure { margin: 0; text-align: center; font-size: 1.05em; min-width: 0; }
  canvas { max-width: 100%; max-height: 46vh; background: #ddd; border: 2px solid #999;
           box-sizing: border-box; }  /* the frames' own size, smaller only where it must */
  #frame { color: #444; font-variant-numeric: tabular-nums; margin: 2px 0 6px; }
  #controls button { font-size: 0.9em; padding: 4px 9px; }
  button { font-size: 1em; padding: 7px 11px; margin: 0 6px 6px 0; cursor: pointer; }
  kbd { border: 1px solid #aaa; border-radius: 3px; padding: 0 4px; background: #fff;
        font-size: 0.85em; }
  #message { color: #b00020; font-weight: 600; margin: 4px 0 0; }
  #message:empty { display: none; }
</style>
</head>
<body>
<header><span id="task"></span><span id="progress"></span><span id="where"></span></header>
<p id="message"></p>
<p id="waiting" hidden></p>
<main id="pair" hidden>
  <p id="question">Which clip does the task better?</p>
  <div id="clips">
    <figure><canvas id="clip0"></canvas><figcaption>Left</figcaption></figure>
    <figure><canvas id="clip1"></canvas><figcaption>Right</figcaption></figure>
  </div>
  <div id="controls"><span id="frame"></span>
    <button id="pause">Pause <kbd>Space</kbd> <kbd>P</kbd></button>
    <button id="slow">Half speed <kbd>H</kbd></button>
    <button id="back">&#9664; frame <kbd>,</kbd></button>
    <button id="forward">frame &#9654; <kbd>.</kbd></button>
  </div>
  <div>
    <button data-label="left">Left is better <kbd>&larr;</kbd> <kbd>1</kbd></button>
    <button data-label="equal">Equally good <kbd>&darr;</kbd> <kbd>E</kbd> <kbd>3</kbd></button>
    <button data-label="skip">Can't tell <kbd>S</kbd> <kbd>0</kbd></button>
    <button data-label="right">Right is better <kbd>&rarr;</kbd> <kbd>2</kbd></button>
    <button id="undo">Undo <kbd>U</kbd> <kbd>Backspace</kbd></button>
  </div>
</main>
<script>
const KEYS = {ArrowLeft: "left", "1": "left", ArrowRight: "right", "2": "right",
              ArrowDown: "equal", e: "equal", E: "equal", "3": "equal",
              s: "skip", S: "skip", "0": "skip", u: "undo", U: "undo", Backspace: "undo"};
const PLAYBACK = {" ": "pause", p: "pause", P: "pause", h: "slow", H: "slow", ",": "back",
                  ".": "forward"};
const NO_SERVER = "the label server does not answer: is label_server.py running?";
const FPS = 20;
const HOLD = 8;  // frames the last frame stays before the clips start again
let state = null;  // the server's state (/api/state)
let shown = null;  // the pair on screen: {session, id, images}
let wanted = null;  // the pair being loaded
let busy = false;  // an answer or undo in flight
let tick = 0;  // frames of the loop so far (fractional at half speed)
let paused = false;
let speed = 1;  // 1 or 0.5
let pollTimer = null;
const clips = new Map();  // "session/id" -> Promise of the pair's two sprite sheets

function $(id) { return document.getElementById(id); }
function say(text) { $("message").textContent = text; }

async function api(path, body) {
  const init = body === undefined ? {} : {method: "POST", body: JSON.stringify(body),
                                          headers: {"Content-Type": "application/json"}};
  let response;
  try {
    response = await fetch(path, init);
  } catch (error) {
    throw new Error(NO_SERVER);
  }
  const data = await response.json();
  if (!response.ok) {
    const error = new Error(data.error);
    error.state = data.state;
    throw error;
  }
  return data;
}

async function sheet(session, id, side) {
  const response = await fetch(`/clips/${session}/${id}/${side}.jpg`);
  if (!response.ok) throw new Error((await response.json()).error);
  return createImageBitmap(await response.blob());
}

function loadPair(session, id) {
  const key = `${session}/${id}`;
  if (!clips.has(key)) {
    const pair = Promise.all([sheet(session, id, 0), sheet(session, id, 1)]);
    pair.catch(() => clips.delete(key));
    clips.set(key, pair);
  }
  return clips.get(key);
}

function updateButtons() {
  for (const button of document.querySelectorAll("button[data-label]")) {
    button.disabled = busy || shown === null;
  }
  $("undo").disabled = busy || state === null || state.session === null || state.last === null;
}

async function show(newState) {
  state = newState;
  $("task").textContent = state.env_id;
  clearTimeout(pollTimer);
  if (state.session === null) {
    shown = wanted = null;
    $("pair").hidden = true;
    $("waiting").hidden = false;
    $("progress").textContent = $("where").textContent = "";
    if (state.run_finished) {
      $("waiting").textContent = "The run has finished: it asks for no more answers. " +
        "You can close this page.";
      return;  // nothing more to wait for
    }
    $("waiting").textContent = (state.done === null ? "" :
      `Session ${state.done.session}: ${state.done.answers} answers taken, the run is learning. `) +
      "Waiting for the run's next feedback session (this page looks every 2 s).";
    pollTimer = setTimeout(refresh, 2000);
    return;
  }
  $("waiting").hidden = true;
  $("pair").hidden = false;
  $("progress").textContent = `${state.answered + 1} / ${state.n}`;
  $("where").textContent = `session ${state.session}, step ${state.step}, pair ${state.next}`;
  if (shown === null || shown.session !== state.session || shown.id !== state.next) {
    shown = null;  // nothing to answer until the next pair's clips are on screen
    for (const side of [0, 1]) {
      const canvas = $(`clip${side}`);
      canvas.getContext("2d").clearRect(0, 0, canvas.width, canvas.height);
    }
  }
  updateButtons();
  if (shown !== null) return;
  const want = wanted = {session: state.session, id: state.next};
  $("frame").textContent = "rendering the clips...";
  try {
    want.images = await loadPair(want.session, want.id);
  } catch (error) {
    if (wanted === want) say(error.message);
    return;
  }
  if (wanted !== want) return;  // a newer state came meanwhile
  shown = want;
  tick = 0;
  draw(false);  // the first frames on screen before the buttons take answers
  updateButtons();
  if (state.after !== null) loadPair(state.session, state.after).catch(() => {});
}

async function refresh() {
  try {
    const next = await api("/api/state");
    if ($("message").textContent === NO_SERVER) say("");
    await show(next);
  } catch (error) {
    say(error.message);
    pollTimer = setTimeout(refresh, 2000);
  }
}

async function act(action) {
  const undo = action === "undo";
  if (busy || (undo ? $("undo").disabled : shown === null)) return;
  busy = true;
  updateButtons();
  const body = undo ? {session: state.session, id: state.last}
                    : {session: shown.session, id: shown.id, label: action};
  let next = null;
  try {
    next = await api(undo ? "/api/undo" : "/api/answer", body);
    say("");
  } catch (error) {
    say(error.message);
    next = error.state || null;
  }
  busy = false;
  if (next !== null) await show(next);
  else updateButtons();
}

function playback(action) {
  const length = state === null ? 1 : state.segment_len;
  if (action === "pause") paused = !paused;
  if (action === "slow") speed = speed === 1 ? 0.5 : 1;
  if (action === "back" || action === "forward") {  // one frame, paused
    const frame = Math.min(Math.floor(tick) % (length + HOLD), length - 1);
    tick = Math.max(0, Math.min(length - 1, frame + (action === "back" ? -1 : 1)));
    paused = true;
  }
  $("pause").firstChild.textContent = paused ? "Play " : "Pause ";
  $("slow").firstChild.textContent = speed === 1 ? "Half speed " : "Full speed ";
  draw(false);
}

function draw(advance = true) {
  if (!shown) return;
  const length = state.segment_len;
  const frame = Math.min(Math.floor(tick) % (length + HOLD), length - 1);
  const columns = state.columns;
  const rows = Math.ceil(length / columns);
  shown.images.forEach((image, side) => {
    const canvas = $(`clip${side}`);
    const width = image.width / columns;
    const height = image.height / rows;
    if (canvas.width !== width) canvas.width = width;
    if (canvas.height !== height) canvas.height = height;
    const x = (frame % columns) * width;
    const y = Math.floor(frame / columns) * height;
    canvas.getContext("2d").drawImage(image, x, y, width, height, 0, 0, width, height);
  });
  $("frame").textContent = `frame ${frame + 1} / ${length}` + (paused ? ", paused" : "") +
    (speed === 1 ? "" : ", half speed");
  if (advance && !paused) tick += speed;
}

document.addEventListener("keydown", event => {
  if (event.ctrlKey || event.altKey || event.metaKey || event.repeat) return;
  if (PLAYBACK[event.key] !== undefined) {
    event.preventDefault();
    playback(PLAYBACK[event.key]);
    return;
  }
  const action = KEYS[event.key];
  if (action === undefined) return;
  event.preventDefault();
  act(action);
});
for (const id of ["pause", "slow", "back", "forward"]) {
  $(id).addEventListener("click", () => playback(id));
}
for (const button of document.querySelectorAll("button[data-label]")) {
  button.addEventListener("click", () => act(button.dataset.label));
}
$("undo").addEventListener("click", () => act("undo"));
setInterval(() => draw(), 1000 / FPS);
refresh();
</script>
</body>
</html>
"""

if __name__ == "__main__":
    main()
