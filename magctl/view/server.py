"""The view's web server: the live page of a running task and the replay page of run logs, over starlette/uvicorn.

One page (``static/index.html``, ``view.js``; the plots are plotly.js, served from the ``plotly`` package, so no
network and no build step) in two modes:

* **live** — ``GET /api/info`` gives the scene, the history so far and the attempts; the WebSocket ``/ws`` then
  carries the latest frame at the rate the page asks for (30/s at most). Each connection has its own sender that
  sends the newest frame when the last send has finished: a slow page skips frames, a page that never reads
  blocks only its own sender, and the runtime, which only hands its documents to the
  :class:`~magctl.view.feed.LiveFeed`, never waits on any of them. Stop, pause and resume arrive on the same socket
  and go to :class:`~magctl.rig.monitor.RunControls` — when the run allows controls, with the run's token when the
  server listens beyond loopback. Garbage on the socket is ignored (a connection that sends only garbage is
  closed); a message over 64 KiB closes its connection.
* **replay** — ``/api/info`` lists the runs; ``/api/series`` and ``/api/frames`` give a run's plot points and its
  event documents by range, for the timeline, playback and side-by-side comparison.

The server runs on its own thread (:class:`ViewServer`) with its own event loop; the address is bound before the
thread starts, so a taken port is a one-line :class:`ViewError` before any coil is activated.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
import math
import secrets
import socket
import threading
import time
from importlib import resources
from pathlib import Path
from typing import Any

from magctl.core.errors import MagctlError
from magctl.rig.monitor import ACTIONS, RunControls
from magctl.view.feed import LiveFeed
from magctl.view.replay import ReplayRun

DEFAULT_ADDRESS = "127.0.0.1:8050"
MAX_MESSAGE_BYTES = 65536
MAX_BAD_MESSAGES = 100
"""A connection that sends this many messages the page never sends is closed."""
INSTALL_HINT = "the view needs the 'view' extra: pip install 'magctl[view]' (in a magctl checkout: " \
               ".venv/bin/pip install -e '.[view]')"


class ViewError(MagctlError):
    """The view cannot start: its extra is missing, its address is malformed or taken."""


def _web():
    """starlette and uvicorn, or the one-line install hint."""
    try:
        import plotly  # noqa: F401 - its plotly.min.js is what the page plots with
        import starlette  # noqa: F401
        import uvicorn
        import websockets  # noqa: F401 - uvicorn's WebSocket protocol
    except ImportError:
        raise ViewError(INSTALL_HINT) from None
    return uvicorn


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT`` or ``PORT`` (host 127.0.0.1) → (host, port); a one-line ViewError otherwise."""
    host, sep, port = str(text).rpartition(":")
    if not sep:
        host, port = "", text
    host = host.strip("[]") or "127.0.0.1"
    try:
        number = int(port)
    except ValueError:
        raise ViewError(f"view address {text!r}: the port must be a number (HOST:PORT, e.g. {DEFAULT_ADDRESS})") \
            from None
    if not 0 <= number <= 65535:
        raise ViewError(f"view address {text!r}: port {number} is not in 0-65535")
    return host, number


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def dumps(doc: Any) -> str:
    """JSON for the page: a non-finite number (JSON has none) becomes null."""
    try:
        return json.dumps(doc, allow_nan=False, separators=(",", ":"))
    except ValueError:
        return json.dumps(_finite(doc), allow_nan=False, separators=(",", ":"))


def _finite(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _static_dir() -> Path:
    return Path(str(resources.files("magctl.view") / "static"))


def _plotly_js() -> Path:
    import plotly

    return Path(plotly.__file__).parent / "package_data" / "plotly.min.js"


class _Live:
    """The live mode's state on the server's event loop: the feed, the controls, who is connected."""

    def __init__(self, feed: LiveFeed, controls: RunControls | None, token: str | None):
        self.feed, self.controls, self.token = feed, controls, token
        self.connections: dict[int, int] = {}   # id(websocket) → last version sent
        self._cache: tuple[int, str] | None = None

    def frame_text(self) -> tuple[int, str | None]:
        """The newest frame as the message every page gets (encoded once per version)."""
        version = self.feed.version
        if self._cache is not None and self._cache[0] == version:
            return self._cache
        latest, stop = self.feed.latest, self.feed.stop
        if stop is not None:
            text = dumps({"type": "stopped", "stop": stop, "attempts": list(self.feed.attempts.rows),
                          "passes": list(self.feed.passes.rows),
                          "event": None if latest is None else latest[0],
                          "status": None if latest is None else latest[1]})
        elif latest is not None:
            text = dumps({"type": "frame", "event": latest[0], "status": latest[1],
                          "attempts": list(self.feed.attempts.rows), "passes": list(self.feed.passes.rows)})
        else:
            text = None
        self._cache = (version, text)
        return self._cache

    def control(self, msg: dict, who: str) -> dict:
        """Apply one control message; the reply the page shows."""
        action = msg.get("action")
        if self.controls is None:
            return {"type": "control", "ok": False, "action": action,
                    "reason": "controls are off for this run (start it with --view-controls)"}
        if self.token is not None and not hmac.compare_digest(str(msg.get("token", "")), self.token):
            return {"type": "control", "ok": False, "action": action, "reason": "wrong or missing token"}
        page = "".join(c for c in str(msg.get("page", ""))[:32] if c.isalnum())
        by = f"{who} page {page}" if page else who
        latest = self.feed.latest
        self.controls.request(action, by, None if latest is None else latest[0]["seq"])
        return {"type": "control", "ok": True, "action": action, "by": by}


def build_app(*, live: _Live | None = None, runs: list[ReplayRun] | None = None):
    """The starlette application of one mode."""
    from starlette.applications import Starlette
    from starlette.responses import FileResponse, JSONResponse, Response
    from starlette.routing import Mount, Route, WebSocketRoute
    from starlette.staticfiles import StaticFiles
    from starlette.websockets import WebSocket, WebSocketDisconnect

    static = _static_dir()

    def json_response(doc, status: int = 200):
        return Response(dumps(doc), status_code=status, media_type="application/json")

    async def index(request):
        return FileResponse(static / "index.html", headers={"Cache-Control": "no-store"})

    async def no_icon(request):
        return Response(status_code=204)

    async def plotly_js(request):
        return FileResponse(_plotly_js(), media_type="text/javascript")

    async def info(request):
        if live is not None:
            return json_response({"mode": "live", "controls": live.controls is not None,
                                  "token_required": live.token is not None, "runs": [live.feed.info()]})
        return json_response({"mode": "replay", "controls": False, "token_required": False,
                              "runs": [r.info() for r in runs]})

    def of_run(answer):
        """An endpoint answering for the replay run ``?run=K`` (400 for a run that is not there)."""
        async def endpoint(request):
            try:
                k = int(request.query_params.get("run", "0"))
            except ValueError:
                k = -1
            if not 0 <= k < len(runs or []):
                return JSONResponse({"error": "run: no such run"}, status_code=400)
            return answer(runs[k], request.query_params)
        return endpoint

    def frames_of(run, query):
        try:
            start, count = int(query.get("start", "0")), int(query.get("count", "1"))
        except ValueError:
            return JSONResponse({"error": "start and count must be integers"}, status_code=400)
        return json_response({"start": start, "events": run.frames(start, count)})

    series = of_run(lambda run, query: json_response(run.series()))
    times = of_run(lambda run, query: json_response(run.times))
    path = of_run(lambda run, query: json_response(run.robot_path()))
    frames = of_run(frames_of)

    async def camera(request):
        got = None if live is None else await asyncio.to_thread(live.feed.camera_png)
        if got is None:
            return Response(status_code=204)
        png, affine = got
        return Response(png, media_type="image/png",
                        headers={"X-Magctl-Affine": ",".join(repr(float(v)) for v in affine),
                                 "Cache-Control": "no-store"})

    async def ws_endpoint(websocket: WebSocket):
        await websocket.accept()
        if live is None:
            await websocket.close(code=1008)
            return
        client = websocket.client
        who = f"{client.host}:{client.port}" if client else "unknown"
        key = id(websocket)
        live.connections[key] = -1
        replies: asyncio.Queue = asyncio.Queue(maxsize=16)
        state = {"period": 1 / 30, "bad": 0}

        async def sender():
            last = -1
            try:
                while True:
                    while not replies.empty():
                        await websocket.send_text(dumps(replies.get_nowait()))
                    version, text = live.frame_text()
                    if version != last and text is not None:
                        await websocket.send_text(text)
                        last = version
                        live.connections[key] = version
                    await asyncio.sleep(state["period"])
            except (WebSocketDisconnect, RuntimeError, OSError):
                return    # the page went away: its reader ends the connection

        task = asyncio.ensure_future(sender())
        try:
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return
                try:
                    msg = json.loads(message.get("text") or "")   # a binary frame is not a page's message
                    if not isinstance(msg, dict):
                        raise ValueError
                except ValueError:
                    msg = None
                if msg is not None and msg.get("action") in ACTIONS:
                    reply = live.control(msg, who)
                elif msg is not None and isinstance(msg.get("rate"), (int, float)) and 0.5 <= msg["rate"] <= 30:
                    state["period"] = 1.0 / float(msg["rate"])
                    continue
                else:
                    state["bad"] += 1
                    if state["bad"] >= MAX_BAD_MESSAGES:
                        await websocket.close(code=1008)
                        return
                    continue
                if not replies.full():
                    replies.put_nowait(reply)
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            task.cancel()
            live.connections.pop(key, None)

    routes = [Route("/", index), Route("/favicon.ico", no_icon), Route("/static/plotly.min.js", plotly_js),
              Route("/api/info", info), Route("/api/series", series), Route("/api/frames", frames),
              Route("/api/times", times), Route("/api/path", path), Route("/api/camera.png", camera),
              WebSocketRoute("/ws", ws_endpoint),
              Mount("/static", StaticFiles(directory=str(static)), name="static")]
    return Starlette(routes=routes)


class ViewServer:
    """The view's server on its own thread. ``ViewServer.live(feed, …)`` or ``ViewServer.replay(paths, …)``;
    :attr:`url` is the address to open; :meth:`close` stops it."""

    def __init__(self, app, address: str, *, token: str | None = None, live: _Live | None = None):
        uvicorn = _web()
        host, port = parse_address(address)
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except socket.gaierror as err:
            raise ViewError(f"view address {address}: {err.strerror}") from None
        family, _, _, _, sockaddr = infos[0]
        sock = socket.socket(family, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(sockaddr)
            sock.listen(64)
        except OSError as err:
            sock.close()
            raise ViewError(f"view address {address}: {err.strerror or err}") from None
        self.host, self.port = host, sock.getsockname()[1]
        self.token, self._live = token, live
        config = uvicorn.Config(app, log_level="error", access_log=False, lifespan="off",
                                ws_max_size=MAX_MESSAGE_BYTES, timeout_graceful_shutdown=1)
        self._server = uvicorn.Server(config)
        self._sock = sock
        self._thread = threading.Thread(target=self._server.run, kwargs={"sockets": [sock]}, daemon=True,
                                        name="magctl-view")
        self._thread.start()
        deadline = time.monotonic() + 20
        while not self._server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                sock.close()
                raise ViewError(f"view address {address}: the web server did not start")
            time.sleep(0.01)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        query = f"?token={self.token}" if self.token else ""
        return f"http://{host}:{self.port}/{query}"

    @classmethod
    def live(cls, feed: LiveFeed, address: str = DEFAULT_ADDRESS, controls: RunControls | None = None) -> ViewServer:
        """The live page of ``feed``'s run; ``controls`` None keeps the buttons off. Beyond loopback the controls
        need the token the printed address carries."""
        host, _ = parse_address(address)
        token = secrets.token_urlsafe(16) if controls is not None and not is_loopback(host) else None
        live = _Live(feed, controls, token)
        return cls(build_app(live=live), address, token=token, live=live)

    @classmethod
    def replay(cls, runs: list[ReplayRun], address: str = DEFAULT_ADDRESS) -> ViewServer:
        return cls(build_app(runs=runs), address)

    def close(self, grace: float = 2.0) -> None:
        """Stop serving. A live server first gives its pages up to ``grace`` s to receive the last frame."""
        if self._live is not None:
            deadline = time.monotonic() + grace
            while time.monotonic() < deadline:
                version = self._live.feed.version
                if all(v >= version for v in list(self._live.connections.values())):
                    break
                time.sleep(0.02)
        self._server.should_exit = True
        self._thread.join(timeout=5)
        self._sock.close()
