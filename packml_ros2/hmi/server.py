"""The web side of the HMI: a FastAPI app over a :class:`~.bridge.Bridge`, served by uvicorn.

Routes (everything local: the page loads nothing from elsewhere, its Content-Security-Policy
forbids it):

- ``GET /``: the page; ``GET /static/...``: its script, style sheet and icon;
- ``GET /api/config``, ``GET /api/snapshot``: what the page draws, as JSON;
- ``GET /api/events``: server-sent events: one ``snapshot`` first, then an ``update`` per change
  (``{topic, unit, data, received}``; ``received`` = when the bridge got the message, ms since the
  epoch), a comment every 15 s to keep proxies from closing the stream;
- ``POST /api/units/{unit}/{action}`` (command, set_mode, ack_alarms, reset_alarms, reset_times,
  reset_counters, set_em_active, set_mach_speed) and ``POST /api/cell/{action}`` (command,
  set_mode through the coordinator), JSON body with the action's arguments: the unit's answer
  ``{accepted, result, result_name, message, ...}`` (200 also when the unit refuses);
- ``POST /api/auth``: 200 when the token is right (or none is configured), else 403.

Access control: with a token configured every POST needs ``Authorization: Bearer <token>``;
without it, or with a wrong one, the answer is 403 with the reason in ``message`` and nothing
reaches the unit. Reading (page, snapshot, events) needs no token: the page is read-only then.
"""

from __future__ import annotations

import asyncio
import json
import socket
import threading
from collections.abc import AsyncIterator
from importlib import resources
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles

from ..core.reasons import Reason
from .bridge import ActionError, Bridge, Event
from .settings import HmiSettings

STATIC = Path(str(resources.files("packml_ros2.hmi") / "static"))
KEEPALIVE = 15.0  # s between comments on an idle event stream
QUEUE_LIMIT = 2000  # events waiting for one slow browser before it is sent a fresh snapshot
ACTION_TIMEOUT = 10.0
CELL_ACTION_TIMEOUT = 120.0  # a cell command waits for the whole sequence
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
    "connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
)
_RESYNC: Event = {"topic": "resync"}


class Hub:
    """Hands the bridge's events (its thread) to the browsers' streams (the event loop)."""

    def __init__(self, bridge: Bridge) -> None:
        self.bridge = bridge
        self.loop: asyncio.AbstractEventLoop | None = None
        self.queues: set[asyncio.Queue[Event | None]] = set()
        self.closed = False

    def open(self) -> tuple[dict[str, Any], asyncio.Queue[Event | None], Any]:
        loop = self.loop = asyncio.get_running_loop()
        queue: asyncio.Queue[Event | None] = asyncio.Queue(QUEUE_LIMIT)

        def deliver(event: Event) -> None:
            if queue.full():  # a stalled browser: drop what it missed, send it the whole state
                while not queue.empty():
                    queue.get_nowait()
                queue.put_nowait(_RESYNC)
            else:
                queue.put_nowait(event)

        def listener(event: Event) -> None:
            if not loop.is_closed():
                loop.call_soon_threadsafe(deliver, event)

        snapshot, unsubscribe = self.bridge.subscribe(listener)
        self.queues.add(queue)
        return snapshot, queue, unsubscribe

    def close(self, queue: asyncio.Queue[Event | None], unsubscribe: Any) -> None:
        unsubscribe()
        self.queues.discard(queue)

    def shutdown(self) -> None:
        """End every stream (server shutdown), from any thread."""
        self.closed = True
        for queue in list(self.queues):
            loop = self.loop
            if loop is not None and not loop.is_closed():
                loop.call_soon_threadsafe(queue.put_nowait, None)


def _sse(kind: str, data: Any) -> str:
    return f"event: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def _token(request: Request) -> str | None:
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return request.headers.get("x-packml-token") or None


def create_app(bridge: Bridge) -> FastAPI:
    """The HMI app for ``bridge`` (the caller spins the bridge and closes it)."""
    app = FastAPI(title=f"PackML HMI {bridge.cell.cell}", docs_url=None, redoc_url=None,
                  openapi_url=None)  # fmt: skip
    hub = Hub(bridge)
    app.state.hub = hub
    app.state.bridge = bridge

    @app.middleware("http")
    async def headers(request: Request, call_next: Any) -> Response:
        response: Response = await call_next(request)
        response.headers["Content-Security-Policy"] = CSP
        response.headers["X-Content-Type-Options"] = "nosniff"
        response.headers["Referrer-Policy"] = "no-referrer"
        if request.url.path == "/" or request.url.path.startswith("/static/"):
            response.headers["Cache-Control"] = "no-cache"
        return response

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html")

    @app.get("/favicon.ico", include_in_schema=False)
    async def favicon() -> FileResponse:
        return FileResponse(STATIC / "favicon.svg", media_type="image/svg+xml")

    @app.get("/api/config")
    async def config() -> dict[str, Any]:
        return bridge.config

    @app.get("/api/snapshot")
    async def snapshot() -> dict[str, Any]:
        return bridge.snapshot()

    @app.get("/api/events")
    async def events(request: Request) -> StreamingResponse:
        snap, queue, unsubscribe = hub.open()

        async def stream() -> AsyncIterator[str]:
            try:
                yield "retry: 1000\n\n" + _sse("snapshot", snap)
                while not hub.closed:
                    try:
                        event = await asyncio.wait_for(queue.get(), KEEPALIVE)
                    except TimeoutError:
                        yield ": keep-alive\n\n"
                        continue
                    if event is None:
                        return
                    if event is _RESYNC:
                        yield _sse("snapshot", bridge.snapshot())
                    else:
                        yield _sse("update", event)
            finally:
                hub.close(queue, unsubscribe)

        return StreamingResponse(
            stream(),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
        )

    async def run_action(unit: str | None, action: str, request: Request) -> JSONResponse:
        try:
            body = await request.json() if await request.body() else {}
        except json.JSONDecodeError:
            return JSONResponse(
                {"accepted": False, "result": int(Reason.INVALID_ARGUMENT),
                 "result_name": "INVALID_ARGUMENT", "message": "the body is not JSON"},
                status_code=400,
            )  # fmt: skip
        if not isinstance(body, dict):
            body = {}
        try:
            future = bridge.act(unit, action, body, _token(request))
        except ActionError as exc:
            return JSONResponse(
                {"accepted": False, "result": int(Reason.INVALID_ARGUMENT),
                 "result_name": "INVALID_ARGUMENT", "message": str(exc.args[0])},
                status_code=404,
            )  # fmt: skip
        timeout = CELL_ACTION_TIMEOUT if unit is None else ACTION_TIMEOUT
        try:
            answer = await asyncio.wait_for(asyncio.wrap_future(future), timeout)
        except TimeoutError:
            answer = {"accepted": False, "result": int(Reason.UNIT_UNAVAILABLE),
                      "result_name": "UNIT_UNAVAILABLE",
                      "message": f"{unit or 'the coordinator'}: no answer within {timeout:g} s"}  # fmt: skip
        status = 403 if answer.get("result") == Reason.UNAUTHORIZED else 200
        return JSONResponse(answer, status_code=status)

    @app.post("/api/units/{unit}/{action}")
    async def unit_action(unit: str, action: str, request: Request) -> JSONResponse:
        return await run_action(unit, action, request)

    @app.post("/api/cell/{action}")
    async def cell_action(action: str, request: Request) -> JSONResponse:
        return await run_action(None, action, request)

    @app.post("/api/auth")
    async def auth(request: Request) -> JSONResponse:
        denied = bridge.authorized(_token(request))
        if denied is not None:
            return JSONResponse(denied, status_code=403)
        return JSONResponse({"accepted": True, "result": 0, "result_name": "ACCEPTED",
                             "message": "operating"})  # fmt: skip

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app


# -- serving ----------------------------------------------------------------------------------------------
def bind(host: str, port: int) -> socket.socket:
    """A listening socket (port 0: any free port; read it with ``getsockname()``)."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, _, _, _, address = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if family == socket.AF_INET6:
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
    try:
        sock.bind(address)
    except OSError:
        sock.close()
        raise
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


def url_of(sock: socket.socket, host: str) -> str:
    port = sock.getsockname()[1]
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/"


class Server:
    """uvicorn serving the HMI app on ``sock``; :meth:`run` blocks (signals: Ctrl-C stops it when
    run in the main thread), :meth:`start` runs it in a thread, :meth:`stop` ends it."""

    def __init__(self, bridge: Bridge, sock: socket.socket, log_level: str = "warning") -> None:
        import uvicorn

        self.app = create_app(bridge)
        self.sock = sock
        hub: Hub = self.app.state.hub

        class _Server(uvicorn.Server):
            def handle_exit(self, sig: int, frame: Any) -> None:
                hub.shutdown()  # open event streams would hold up the shutdown
                super().handle_exit(sig, frame)

        config = uvicorn.Config(
            self.app,
            log_level=log_level,
            access_log=False,
            ws="none",
            lifespan="off",
            timeout_graceful_shutdown=2,
        )
        self.server = _Server(config)
        self.hub = hub
        self._thread: threading.Thread | None = None

    def run(self) -> None:
        self.server.run(sockets=[self.sock])

    def start(self) -> Server:
        self._thread = threading.Thread(target=self.run, name="hmi-server", daemon=True)
        self._thread.start()
        return self

    def started(self) -> bool:
        return bool(self.server.started)

    def stop(self, timeout: float = 5.0) -> None:
        self.hub.shutdown()
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout)
        self.sock.close()


def serve(bridge: Bridge, settings: HmiSettings) -> Server:
    """A :class:`Server` for ``bridge`` bound to ``settings.host``/``port`` (not started)."""
    return Server(bridge, bind(settings.host, settings.port))
