"""The labelling page: a local Flask app that shows queued pairs side by side and records people's choices.

    sb3-dipper-label --run RUN_OR_LABELS_DIR [--port 5000] [--host 127.0.0.1] [--show-skipped]

``--run`` is a label queue directory (what ``preference_source="people:DIRECTORY"`` names) or a folder holding one
as ``labels/``. The page shows one waiting pair at a time: the left (first) and right (second) trajectory, both
toward the pair's goal (see :mod:`sb3_dipper.labelling.render`), and buttons, with keys, for left (Left arrow or
``a``), right (Right arrow or ``d``), equal (Down arrow or ``e``) and skip (``s``), and counts of labelled and waiting
pairs. A pair is handed to one tab at a time (each tab has its own client id), and the first answer for a pair is the
only one recorded: a second, from another tab, is refused. Answers go to ``labels.npz`` at once, so a restarted page
goes on with the pairs nobody answered; skipped pairs are not shown again unless ``--show-skipped``. An answer is
recorded only for a pair whose two pictures this server sent: a picture it cannot draw is an error the page shows in
place of the answer buttons, never a pair answered unseen.

The page is for the person at this machine. It listens on 127.0.0.1 unless ``--host`` says otherwise; it answers only
requests whose ``Host`` header names the address it serves on, ``localhost`` or an IP address (so a web page whose
domain was made to point at this machine, DNS rebinding, is refused); its API answers only the page itself (``Origin``
and ``Sec-Fetch-Site`` must say same-origin, where a browser sends them), and a pair is claimed by a POST, so another
site's links and images cannot claim or label pairs. Request bodies are limited to :data:`MAX_BODY_BYTES`. Flask's
debug mode and its ``.env`` / ``.flaskenv`` loading are never used, whatever the environment says. To label from
another machine, forward the port over SSH (``ssh -L 5000:127.0.0.1:5000 host``) rather than serving on ``0.0.0.0``.
"""

from __future__ import annotations

import argparse
import ipaddress
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from flask import Flask, Response, abort, jsonify, request
from werkzeug.exceptions import HTTPException
from werkzeug.serving import BaseWSGIServer, make_server

from sb3_dipper.common.files import write_bytes_atomically
from sb3_dipper.labelling.queue import ANSWERS, LabelQueue
from sb3_dipper.labelling.render import SIDES, PairRenderer

# A pair handed to a tab is kept for it this long; after that (a closed tab) another tab may have it.
CLAIM_SECONDS = 600.0
# The largest request body read: the page's own requests are a few hundred bytes.
MAX_BODY_BYTES = 16 * 1024
# Host names that are this machine whatever the page is served on.
LOCAL_HOST_NAMES = ("localhost", "127.0.0.1", "::1")

PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>sb3-dipper: which trajectory is better?</title>
<style>
  body { font-family: sans-serif; margin: 1.5em; background: #fafafa; color: #222; font-size: 16px; }
  h1 { font-size: 1.5em; margin: 0 0 .3em; }
  #layout { display: grid; grid-template-columns: minmax(0, 1fr) 21rem; gap: 1.5em; align-items: start; }
  @media (max-width: 1000px) { #layout { grid-template-columns: minmax(0, 1fr); } }
  #pair { display: flex; gap: 1.5em; align-items: flex-start; }
  .side { flex: 1 1 0; min-width: 0; background: white; padding: .5em; border: 1px solid #ccc; border-radius: 6px;
    text-align: center; font-size: 1.1em; font-weight: bold; }
  .side img { display: block; max-width: 100%; margin: .3em auto 0; }
  #starts { color: #444; margin: .6em 0 0; }
  #buttons { margin: 1em 0; display: flex; flex-wrap: wrap; gap: .8em; }
  button { font-size: 1.1em; padding: .5em 1.2em; cursor: pointer; }
  #counts { color: #444; margin: 0 0 1em; }
  #message { color: #a00; min-height: 1.2em; }
  #how-to { background: white; border: 1px solid #ccc; border-radius: 6px; padding: .2em 1em; line-height: 1.4; }
  #how-to summary { font-weight: bold; font-size: 1.15em; cursor: pointer; padding: .5em 0; }
  #how-to p { margin: .5em 0 .8em; }
  kbd { border: 1px solid #aaa; border-radius: 3px; padding: 0 .3em; background: #f3f3f3; font-size: .9em; }
  .subgoal { color: #d62728; font-weight: bold; }
  .goal { color: #b8860b; }
</style>
</head>
<body>
<h1>Which trajectory gets to the goal better?</h1>
<p id="counts">labelled <b id="labelled">0</b> &middot; waiting <b id="waiting">0</b>
  &middot; pair <span id="pair-id">-</span></p>
<div id="layout">
<main>
<div id="pair">
  <div class="side">Left<img id="left-img" alt="left trajectory"></div>
  <div class="side">Right<img id="right-img" alt="right trajectory"></div>
</div>
<p id="starts">The two trajectories are drawn separately from the agent's recent episodes, so they may start at
  different places: judge how well each gets from its own start to the goal.</p>
<div id="buttons">
  <button id="btn-left" data-answer="left">&larr; Left is better (a)</button>
  <button id="btn-equal" data-answer="equal">Equal (&darr; / e)</button>
  <button id="btn-right" data-answer="right">Right is better &rarr; (d)</button>
  <button id="btn-skip" data-answer="skip">Skip (s)</button>
</div>
<p id="message"></p>
</main>
<details id="how-to" open>
<summary>How to label</summary>
<p><b>A pair</b> is two trajectories of the agent. Pick the one that gets to the
  <span class="goal">goal (&#9733;; inside its yellow circle counts)</span> better: it gets there, gets there sooner,
  or ends nearer.</p>
<p><b>Answer</b> with the buttons or keys: <kbd>a</kbd>/<kbd>&larr;</kbd> left, <kbd>d</kbd>/<kbd>&rarr;</kbd>
  right, <kbd>e</kbd>/<kbd>&darr;</kbd> equal, <kbd>s</kbd> skip (you cannot tell). Each answer is saved at once.</p>
<p><b>Options and subgoals.</b> The agent's higher level proposes a
  <span class="subgoal">subgoal (&times;, numbered in order)</span>; its lower level then spends an option, a few
  steps, trying to reach it. A dot marks where each option ended (a dotted line joins it to its subgoal): the dots
  from the black square, the start, are the trajectory. Judge the dots; a subgoal is only a request. Robot tasks
  show frames instead: the start, then the scene after some of the options.</p>
<p><b>A hindsight goal.</b> Usually both sides share a hindsight goal: not the goal the agent was given, but a place
  one of the two trajectories reached, so that both answer the same question. A trajectory may pass it without
  aiming at it; judge it all the same. If the two goals differ, judge each side toward its own.</p>
<p><b>Different starts.</b> Each side is a whole episode drawn at random from the agent's recent ones, usually two
  different episodes, each starting where the task put the agent. (DPO-FLAT's pairs are two short segments cut from
  anywhere in their episodes.)</p>
</details>
</div>
<script>
let client = sessionStorage.getItem("client");
if (!client) {
  client = Math.random().toString(36).slice(2) + Date.now().toString(36);
  sessionStorage.setItem("client", client);
}
let current = null;
let busy = false;
// The sides of the current pair whose pictures have loaded: it can be answered once both have.
let loaded = new Set();
function allowAnswers(allowed) {
  for (const button of document.querySelectorAll("#buttons button")) { button.disabled = !allowed; }
}
function show(counts) {
  document.getElementById("labelled").textContent = counts.labelled;
  document.getElementById("waiting").textContent = counts.waiting;
}
// The JSON body of an answer; an error of its own if the server sent none (a proxy's page, a lost connection).
async function reply(response) {
  return response.json().catch(() => ({error: "The page's server answered " + response.status + "."}));
}
async function next() {
  const response = await fetch("api/next", {method: "POST", headers: {"Content-Type": "application/json"},
    body: JSON.stringify({client: client})});
  const data = await reply(response);
  if (!response.ok) {
    document.getElementById("message").textContent = data.error + " Trying again in 10 s.";
    setTimeout(next, 10000);
    return;
  }
  show(data.counts);
  current = data.pair_id;
  loaded = new Set();
  allowAnswers(false);
  document.getElementById("pair-id").textContent = current === null ? "-" : current;
  for (const side of ["left", "right"]) {
    const image = document.getElementById(side + "-img");
    if (current === null) { image.removeAttribute("src"); continue; }
    const pair = current;
    image.onload = () => {
      if (pair !== current) { return; }
      loaded.add(side);
      allowAnswers(loaded.size === 2);
    };
    image.onerror = () => pictureFailed(image, pair, side);
    // A new address every time: the browser asks the server, which records that it sent the picture (a restarted
    // server has sent nothing yet), instead of showing its own copy.
    image.src = "api/pair/" + pair + "/" + side + ".png?view=" + Date.now();
  }
  document.getElementById("message").textContent =
    current === null ? "Nothing to label now: new pairs appear as training queues them." : "";
  if (current === null) { setTimeout(next, 3000); }
}
// An image's error event carries no reply: ask again for the server's message (a picture it cannot draw fails again).
async function pictureFailed(image, pair, side) {
  if (pair !== current) { return; }
  allowAnswers(false);
  const response = await fetch(image.src);
  const why = response.ok ? "it did not load; reload the page to try again." : (await reply(response)).error;
  if (pair === current) {
    document.getElementById("message").textContent =
      "The " + side + " picture of pair " + pair + " cannot be shown, so the pair cannot be answered: " + why;
  }
}
async function answer(choice) {
  if (current === null || busy || loaded.size < 2) { return; }
  busy = true;
  const response = await fetch("api/label", {method: "POST", headers: {"Content-Type": "application/json"},
    body: JSON.stringify({pair_id: current, client: client, answer: choice})});
  const data = await reply(response);
  if (!response.ok) { document.getElementById("message").textContent = data.error; }
  busy = false;
  await next();
}
for (const button of document.querySelectorAll("#buttons button")) {
  button.addEventListener("click", () => answer(button.dataset.answer));
}
const keys = {ArrowLeft: "left", a: "left", ArrowRight: "right", d: "right", ArrowDown: "equal", e: "equal", s: "skip"};
document.addEventListener("keydown", (event) => { if (keys[event.key]) { event.preventDefault(); answer(keys[event.key]); } });
next();
</script>
</body>
</html>
"""


def labels_directory(run: str | Path) -> Path:
    """The label queue of ``run``: the directory itself, or its ``labels/`` folder."""
    run = Path(run)
    for candidate in (run, run / "labels"):
        if (candidate / "queue.json").exists() or (candidate / "pairs").is_dir():
            return candidate
    raise FileNotFoundError(
        f"No label queue in {run} or {run / 'labels'}: pass the directory given to training as "
        "preference_source='people:DIRECTORY' (it holds queue.json and pairs/), or the folder that holds it as labels/."
    )


class Claims:
    """Which tab has which pair: a pair goes to one client at a time."""

    def __init__(self) -> None:
        self._by_pair: dict[int, tuple[str, float]] = {}

    def holder(self, pair_id: int) -> str | None:
        claim = self._by_pair.get(pair_id)
        if claim is None or time.monotonic() - claim[1] > CLAIM_SECONDS:
            return None
        return claim[0]

    def claim(self, pair_id: int, client: str) -> None:
        self._by_pair[pair_id] = (client, time.monotonic())

    def release(self, pair_id: int) -> None:
        self._by_pair.pop(pair_id, None)


class LabellingServer:
    """What the page's requests do, on the label queue ``directory`` (one lock: tabs are served one at a time).

    :param directory: the label queue directory
    :param show_skipped: show skipped pairs again (a label then replaces the skip)
    """

    def __init__(self, directory: str | Path, show_skipped: bool = False) -> None:
        self.queue = LabelQueue(directory)
        self.show_skipped = show_skipped
        self.claims = Claims()
        self.lock = threading.Lock()
        self._renderer: PairRenderer | None = None
        # The pictures this process sent (LabelQueue.image_path): a pair is answered only once both of its were. Not
        # the pictures cached in images/: a restarted server counts a pair as shown when the page fetches it again.
        self._sent: set[Path] = set()

    def waiting(self) -> list[int]:
        """The pairs to show, oldest first."""
        if not self.show_skipped:
            return self.queue.waiting_ids()
        answers = self.queue.answers().as_dict()
        return [pair_id for pair_id in self.queue.queued_ids() if math.isnan(answers.get(pair_id, math.nan))]

    def counts(self) -> dict[str, int]:
        skipped = np.isnan(self.queue.answers().labels)
        return {"labelled": int((~skipped).sum()), "skipped": int(skipped.sum()), "waiting": len(self.waiting())}

    def next_pair(self, client: str) -> dict[str, Any]:
        """The pair ``client`` holds, or else the oldest pair no other client holds (then ``client`` holds it)."""
        with self.lock:
            ids = self.waiting()
            held = [pair_id for pair_id in ids if self.claims.holder(pair_id) == client]
            free = [pair_id for pair_id in ids if self.claims.holder(pair_id) is None]
            candidates = held or free
            pair_id = candidates[0] if candidates else None
            if pair_id is not None:
                self.claims.claim(pair_id, client)
            return {"pair_id": pair_id, "counts": self.counts()}

    def answer(self, pair_id: int, client: str, answer: str) -> tuple[dict[str, Any], int]:
        """Record ``client``'s answer for ``pair_id``: the JSON reply and its HTTP status (409: someone was first, or
        this server has not sent both pictures of the pair)."""
        with self.lock:
            holder = self.claims.holder(pair_id)
            if holder is not None and holder != client:
                return {"error": f"Pair {pair_id} is being labelled in another tab"}, 409
            if not self.queue.pair_path(pair_id).exists():
                return {"error": f"No queued pair {pair_id}"}, 404
            if not all(self.queue.image_path(pair_id, side) in self._sent for side in SIDES):
                return {
                    "error": f"Pair {pair_id} was not shown: this server has not sent both its pictures "
                    f"(api/pair/{pair_id}/left.png and right.png), and an answer counts only for a pair the person saw"
                }, 409
            if not self.queue.record_answer(pair_id, ANSWERS[answer], replace_skip=self.show_skipped):
                return {"error": f"Pair {pair_id} already has an answer: the first one counts"}, 409
            self.claims.release(pair_id)
            return {"ok": True, "counts": self.counts()}, 200

    def image(self, pair_id: int, side: str) -> bytes:
        """The picture of one side of a pair, rendered on first request and kept in ``images/``; recorded as sent."""
        cached = self.queue.image_path(pair_id, side)
        if not cached.exists():
            with self.lock:
                if self._renderer is None:
                    self._renderer = PairRenderer(self.queue.read_info())
                png = self._renderer.render(self.queue.read_pair(pair_id), side)
            write_bytes_atomically(cached, png)
        png = cached.read_bytes()
        with self.lock:
            self._sent.add(cached)
        return png


def allowed_host(host_header: str, served_on: str) -> bool:
    """Whether a request's ``Host`` header names this server: the address it serves on, a local name, or (served on
    every address) any IP address. A domain name that resolves here by DNS rebinding is none of these.

    :param host_header: the request's ``Host`` header (``name[:port]``, ``[v6]:port``)
    :param served_on: the address the server listens on
    """
    name = host_header.rsplit(":", 1)[0] if host_header.count(":") == 1 else host_header
    name = name.removeprefix("[").split("]", 1)[0].lower()
    if name in (*LOCAL_HOST_NAMES, served_on.lower()):
        return True
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return served_on in ("0.0.0.0", "::")


def refuse_other_sites(host: str) -> None:
    """Abort a request that another site could have sent: a foreign ``Host``, or a cross-origin call of the API.

    :param host: the address the page is served on
    """
    if not allowed_host(request.host, host):
        abort(400, f"Unknown Host {request.host!r}: open the page as http://127.0.0.1:PORT or http://localhost:PORT")
    if not request.path.startswith("/api/"):
        return
    origin = request.headers.get("Origin")
    if origin is not None and origin != request.host_url.rstrip("/"):
        abort(403, f"Requests from {origin} are refused: the API answers the labelling page only")
    if request.headers.get("Sec-Fetch-Site", "same-origin") not in ("same-origin", "none"):
        abort(403, "Requests from other sites are refused: the API answers the labelling page only")


def json_object() -> dict[str, Any]:
    """The request's JSON body, which must be an object (anything else is a 400 naming the fix)."""
    body = request.get_json(silent=True)
    if not isinstance(body, dict):
        abort(400, "Send a JSON object (Content-Type: application/json)")
    return body


def create_app(directory: str | Path, show_skipped: bool = False, host: str = "127.0.0.1") -> Flask:
    """The labelling page of the label queue ``directory`` (arguments as :class:`LabellingServer`).

    :param directory: the label queue directory
    :param show_skipped: show skipped pairs again
    :param host: the address the page is served on, which the ``Host`` header of a request may name
    """
    server = LabellingServer(directory, show_skipped)
    app = Flask("sb3_dipper.labelling")
    # Set here, not from FLASK_DEBUG or a .flaskenv: debug mode would show tracebacks and offer Werkzeug's console.
    app.debug = False
    app.config["MAX_CONTENT_LENGTH"] = MAX_BODY_BYTES

    app.before_request(lambda: refuse_other_sites(host))

    @app.errorhandler(HTTPException)
    def json_error(error: HTTPException) -> tuple[Response, int]:
        return jsonify(error=error.description), error.code or 500

    @app.errorhandler(ValueError)
    def queue_error(error: ValueError) -> tuple[Response, int]:
        # A damaged file of the queue: its message names the file and the fix, which the page shows.
        return jsonify(error=str(error)), 500

    @app.get("/")
    def page() -> Response:
        return Response(PAGE, mimetype="text/html")

    @app.get("/api/status")
    def status() -> Response:
        with server.lock:
            return jsonify(counts=server.counts())

    @app.post("/api/next")
    def next_pair() -> Response:
        client = json_object().get("client")
        if not isinstance(client, str) or not client:
            abort(400, "Send client (a non-empty string): the id of the tab that claims the pair")
        return jsonify(server.next_pair(client))

    @app.post("/api/label")
    def label() -> tuple[Response, int]:
        body = json_object()
        pair_id, client, answer = body.get("pair_id"), body.get("client"), body.get("answer")
        # bool is an int in Python: true would label pair 1.
        if type(pair_id) is not int or not isinstance(client, str) or not isinstance(answer, str) or answer not in ANSWERS:
            return jsonify(error=f"Send pair_id (int), client (str) and answer (one of {sorted(ANSWERS)})"), 400
        reply, status_code = server.answer(pair_id, client, answer)
        return jsonify(reply), status_code

    @app.get("/api/pair/<int:pair_id>/<side>.png")
    def image(pair_id: int, side: str) -> Response:
        if side not in SIDES or not server.queue.pair_path(pair_id).exists():
            abort(404)
        return Response(server.image(pair_id, side), mimetype="image/png")

    return app


def serve_in_background(directory: str | Path, host: str = "127.0.0.1", port: int = 5000) -> BaseWSGIServer:
    """Serve the labelling page of ``directory`` from a daemon thread of this process (training's, for example).

    The queue directory is created if training has not queued a pair yet; the page then waits for pairs. A port that
    is taken raises ``OSError`` here, before anything else starts.

    :param directory: the label queue directory
    :param host: the address to serve on
    :param port: the port to serve on (0: a free port, then read ``server.server_port``)
    :return: the running server: ``server.shutdown()`` stops it
    """
    Path(directory).mkdir(parents=True, exist_ok=True)
    server = make_server(host, port, create_app(directory, host=host), threaded=True)
    threading.Thread(target=server.serve_forever, name="labelling-page", daemon=True).start()
    return server


def main(argv: list[str] | None = None) -> None:
    """``sb3-dipper-label --run DIR [--port N] [--host H] [--show-skipped]``: serve the labelling page."""
    parser = argparse.ArgumentParser(prog="sb3-dipper-label", description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", required=True, help="the label queue directory, or a folder holding it as labels/")
    parser.add_argument("--port", type=int, default=5000, help="the port to serve on (default 5000)")
    parser.add_argument("--host", default="127.0.0.1", help="the address to serve on (default: this machine only)")
    parser.add_argument("--show-skipped", action="store_true", help="show skipped pairs again")
    args = parser.parse_args(argv)
    try:
        directory = labels_directory(args.run)
    except FileNotFoundError as error:
        parser.error(str(error))
    app = create_app(directory, args.show_skipped, args.host)
    # Werkzeug's server, without Flask's app.run: that would read FLASK_DEBUG and .env files, and could start the
    # debugger. The page serves one person on this machine, not the public.
    server = make_server(args.host, args.port, app, threaded=True)
    print(f"Labelling page of {directory}: http://{args.host}:{server.server_port}", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
