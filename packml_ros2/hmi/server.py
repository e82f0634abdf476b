"""The web side of the HMI: a FastAPI app over a :class:`~.bridge.Bridge`, served by uvicorn.

Routes (everything local: the page loads nothing from elsewhere, its Content-Security-Policy
forbids it):

- ``GET /``: the page; ``GET /static/...``: its script, style sheet and icon;
- ``GET /api/config``, ``GET /api/snapshot``: what the page draws, as JSON;
- ``GET /api/events``: server-sent events: one ``snapshot`` first, then an ``update`` per change
  (``{topic, unit, data, received}``; ``received`` = when the bridge got the message, ms since the
  epoch), a ``ping`` every 5 s (the page notices a server that went silent; proxies keep the
  stream open). At most :data:`MAX_STREAMS_PER_CLIENT` anonymous streams per address and
  ``MAX_STREAMS - OPERATOR_STREAMS`` in all (429/503 beyond); ``?ticket=`` from ``POST
  /api/events/ticket`` (authorized, used once within 30 s) opens one of the streams kept for
  operators who have logged in; a page of another origin opens none (403);
- ``GET /api/units/{unit}/recipes``: the unit's recipes (also in the config) and the recipe in
  use, the changeover and each EM's answer as its last status shows them;
- ``POST /api/units/{unit}/{action}`` (command, set_mode, ack_alarms, reset_alarms, reset_times,
  reset_counters, set_em_active, set_mach_speed, set_recipe ``{recipe_id}`` or
  ``{recipe_name}``) and ``POST /api/cell/{action}`` (command,
  set_mode through the coordinator), JSON body with the action's arguments: the unit's answer
  ``{accepted, result, result_name, message, ...}`` (200 also when the unit refuses);
- ``POST /api/auth``: 200 with ``{user, level}`` when the credential is good (or none is
  configured), else 403;
- ``POST /api/login`` ``{user, password}`` (with ``hmi.users``): 200 with ``{session, user,
  level}``, else 403 (``LOGIN_WRONG``); ``POST /api/logout`` ends the session sent.

Access control (:mod:`.access`): with users or a token configured every action needs
``Authorization: Bearer <session or token>``; without it, with a wrong one or below the level the
action needs, the answer is 403 with the reason in ``message`` and nothing reaches the unit;
wrong tokens, passwords and unknown sessions are throttled per address and account (429).
Reading (page, snapshot, events) needs nothing: the page is read-only then.

Requests (:mod:`.guard`): the Host header is checked on every request, a POST from another site is
refused, an action's body is read only after its token is checked, and only if it is JSON and at
most 64 kB. Every refusal is JSON ``{accepted: false, result, result_name, code, message}`` with a
4xx status; an answer of the unit is 200 (also a refusal), an argument refused here 400.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import socket
import threading
import time
from collections.abc import AsyncIterator, Iterable
from importlib import resources
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException

from ..core.reasons import Reason
from . import line
from .access import Principal, Refusal, level_refusal
from .bridge import BAD_ARGUMENT, ActionError, Bridge, Event
from .guard import HostGuard, Json, dumps, json_content, parse_object, read_body, refuse
from .settings import HmiSettings

STATIC = Path(str(resources.files("packml_ros2.hmi") / "static"))
KEEPALIVE = 5.0  # s between pings on an idle event stream
QUEUE_LIMIT = 2000  # events waiting for one slow browser before it is sent a fresh snapshot
MAX_STREAMS = 64  # event streams open at once (each holds a queue)
#: of them, streams kept for operators who have logged in (a stream ticket): 64 anonymous
#: streams made every operator page answer 503 until they closed
OPERATOR_STREAMS = 16
MAX_STREAMS_PER_CLIENT = 6  # anonymous streams from one address (a browser opens at most 6)
TICKET_LIFETIME = 30.0  # s: a stream ticket is used once, within this
MAX_TICKETS = 256
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
        self.clients: dict[str, int] = {}  # address -> anonymous streams open
        self.operators = 0  # streams opened with a ticket
        self.tickets: dict[str, float] = {}  # ticket -> when it expires (monotonic)

    def ticket(self) -> str:
        """A one-use ticket for an operator's stream (``GET /api/events?ticket=``: EventSource
        cannot send an Authorization header)."""
        now = time.monotonic()
        for t in [t for t, due in self.tickets.items() if due <= now]:
            del self.tickets[t]
        while len(self.tickets) >= MAX_TICKETS:
            del self.tickets[next(iter(self.tickets))]
        ticket = secrets.token_urlsafe(24)
        self.tickets[ticket] = now + TICKET_LIFETIME
        return ticket

    def admit(self, ticket: str | None, client: str) -> tuple[bool, Refusal | None]:
        """Whether a stream may open now: (an operator's, refusal or None)."""
        due = self.tickets.pop(ticket, None) if ticket else None
        if due is not None and due > time.monotonic():
            if self.operators >= OPERATOR_STREAMS and len(self.queues) >= MAX_STREAMS:
                return True, Refusal(
                    503,
                    Reason.UNIT_UNAVAILABLE,
                    "TOO_MANY_STREAMS",
                    f"{OPERATOR_STREAMS} operators' event streams are open: close a page",
                )
            return True, None
        anonymous = len(self.queues) - self.operators
        if anonymous >= MAX_STREAMS - OPERATOR_STREAMS:
            return False, Refusal(
                503,
                Reason.UNIT_UNAVAILABLE,
                "TOO_MANY_STREAMS",
                f"{anonymous} event streams are open: close a page (an operator who "
                "has logged in still gets one)",
            )
        if self.clients.get(client, 0) >= MAX_STREAMS_PER_CLIENT:
            return False, Refusal(
                429,
                Reason.UNIT_UNAVAILABLE,
                "TOO_MANY_STREAMS",
                f"{MAX_STREAMS_PER_CLIENT} event streams are open from this address: close a page",
            )
        return False, None

    def count(self, operator: bool, client: str, delta: int) -> None:
        if operator:
            self.operators += delta
        else:
            n = self.clients.get(client, 0) + delta
            if n > 0:
                self.clients[client] = n
            else:
                self.clients.pop(client, None)

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
    return f"event: {kind}\ndata: {dumps(data)}\n\n"


def _token(request: Request) -> str | None:
    auth = request.headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    return request.headers.get("x-packml-token") or None


def _client(request: Request) -> str:
    return request.client.host if request.client else "unknown"


LOG = logging.getLogger("packml_ros2.hmi")
_STATUS_CODES = {404: "NOT_FOUND", 405: "METHOD_NOT_ALLOWED"}


def create_app(bridge: Bridge, allowed_hosts: Iterable[str] = ()) -> FastAPI:
    """The HMI app for ``bridge`` (the caller spins the bridge and closes it); ``allowed_hosts``:
    host names besides IP addresses, localhost and this machine's name (:class:`.guard.HostGuard`)."""
    app = FastAPI(
        title=f"PackML HMI {bridge.cell.cell}",
        docs_url=None,
        redoc_url=None,
        openapi_url=None,
        default_response_class=Json,
    )
    hub = Hub(bridge)
    app.state.hub = hub
    app.state.bridge = bridge
    guard = HostGuard(allowed_hosts)
    access = bridge.access

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, exc: HTTPException) -> Response:
        code = _STATUS_CODES.get(exc.status_code, "BAD_REQUEST")
        text = "no such page or action" if exc.status_code == 404 else f"{exc.detail}".lower()
        return refuse(Refusal(exc.status_code, Reason.INVALID_ARGUMENT, code, text))

    @app.exception_handler(Exception)
    async def internal_error(request: Request, exc: Exception) -> Response:
        # a defect, never the user's fault: one line in the log, no traceback on the wire
        LOG.error("HMI: %s %s failed: %s", request.method, request.url.path, type(exc).__name__)
        return refuse(
            Refusal(
                500,
                Reason.UNIT_UNAVAILABLE,
                "INTERNAL_ERROR",
                "the HMI server failed on this request (see its log)",
            )
        )

    @app.middleware("http")
    async def headers(request: Request, call_next: Any) -> Response:
        refusal = guard.host(request)
        if refusal is None and request.method not in ("GET", "HEAD"):
            refusal = guard.cross_site(request)
        response: Response = refuse(refusal) if refusal is not None else await call_next(request)
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
    async def config() -> Json:
        return Json(bridge.config)

    @app.get("/api/snapshot")
    async def snapshot() -> Json:
        return Json(bridge.snapshot())

    @app.get("/api/units/{unit}/recipes")
    async def recipes(unit: str) -> Json:
        found = next((u for u in bridge.config["units"] if u["name"] == unit), None)
        if found is None:
            return refuse(Refusal(404, Reason.INVALID_ARGUMENT, "NOT_FOUND", "no such unit"))
        status = bridge.snapshot()["units"][unit]["status"] or {}
        keys = ("recipes", "recipe_states", "recipe_timeout")
        now = {k: v for k, v in status.items() if k.startswith("recipe_")}
        ems = [
            {k: e[k] for k in ("name", "recipe_answer", "recipe_answer_name", "recipe_message")}
            for e in status.get("equipment_modules", ())
        ]
        return Json({"unit": unit, **{k: found[k] for k in keys}, **now, "equipment_modules": ems})

    @app.post("/api/events/ticket")
    async def events_ticket(request: Request) -> Json:
        who = access.authorize(_token(request), _client(request))
        if isinstance(who, Refusal):
            return refuse(who)
        return welcome(who, "a ticket for one event stream", ticket=hub.ticket())

    @app.get("/api/events", response_model=None)
    async def events(request: Request, ticket: str | None = None) -> Response:
        refusal = guard.cross_site(request)  # (another site's page may open a stream too)
        client = _client(request)
        operator, refused = hub.admit(ticket[:100] if ticket else None, client)
        refusal = refusal or refused
        if refusal is not None:
            return refuse(refusal)
        snap, queue, unsubscribe = hub.open()
        hub.count(operator, client, +1)

        async def stream() -> AsyncIterator[str]:
            try:
                yield "retry: 1000\n\n" + _sse("snapshot", snap)
                while not hub.closed:
                    try:
                        event = await asyncio.wait_for(queue.get(), KEEPALIVE)
                    except TimeoutError:
                        yield "event: ping\ndata: {}\n\n"
                        continue
                    if event is None:
                        return
                    if event is _RESYNC:
                        yield _sse("snapshot", bridge.snapshot())
                    else:
                        yield _sse("update", event)
            finally:
                hub.close(queue, unsubscribe)
                hub.count(operator, client, -1)

        return StreamingResponse(
            stream(),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
        )

    async def run_action(unit: str | None, action: str, request: Request) -> Json:
        # the order matters: who asks (before a byte of the body is read), what is asked, then
        # the body, bounded
        token = _token(request)
        who = access.authorize(token, _client(request))
        if isinstance(who, Refusal):
            return refuse(who)
        try:
            bridge.builder(unit, action)
        except ActionError as exc:
            return refuse(Refusal(404, Reason.INVALID_ARGUMENT, "NOT_FOUND", str(exc.args[0])))
        refusal = level_refusal(who, unit, action) or json_content(request)
        body = await read_body(request) if refusal is None else refusal
        args = parse_object(body) if isinstance(body, bytes) else body
        if isinstance(args, Refusal):
            return refuse(args)
        try:
            future = bridge.act(unit, action, args, who=who)
        except ActionError as exc:
            return refuse(Refusal(404, Reason.INVALID_ARGUMENT, "NOT_FOUND", str(exc.args[0])))
        timeout = CELL_ACTION_TIMEOUT if unit is None else ACTION_TIMEOUT
        try:
            answer = await asyncio.wait_for(asyncio.wrap_future(future), timeout)
        except TimeoutError:
            answer = {
                "accepted": False,
                "result": int(Reason.UNIT_UNAVAILABLE),
                "result_name": "UNIT_UNAVAILABLE",
                "message": f"{unit or 'the coordinator'}: no answer within {timeout:g} s",
            }
        status = (
            403
            if answer.get("result") == Reason.UNAUTHORIZED
            else 400
            if answer.get("code") == BAD_ARGUMENT
            else 200
        )
        return Json(answer, status_code=status)

    @app.post("/api/units/{unit}/{action}")
    async def unit_action(unit: str, action: str, request: Request) -> Json:
        return await run_action(unit, action, request)

    @app.post("/api/cell/{action}")
    async def cell_action(action: str, request: Request) -> Json:
        return await run_action(None, action, request)

    def welcome(who: Principal, message: str, **more: Any) -> Json:
        return Json(
            {
                "accepted": True,
                "result": 0,
                "result_name": "ACCEPTED",
                "message": message,
                "user": who.name,
                "level": who.level,
                **more,
            }
        )

    @app.post("/api/auth")
    async def auth(request: Request) -> Json:
        who = access.authorize(_token(request), _client(request))
        if isinstance(who, Refusal):
            return refuse(who)
        return welcome(who, "operating")

    @app.post("/api/login")
    async def login(request: Request) -> Json:
        client = _client(request)
        refusal = access.blocked(client) or json_content(request)
        body = await read_body(request, 4096) if refusal is None else refusal
        args = parse_object(body) if isinstance(body, bytes) else body
        if isinstance(args, Refusal):
            return refuse(args)
        # (the password is checked in a worker thread: a hash takes a while on purpose)
        result = await access.login(args.get("user"), args.get("password"), client)
        if isinstance(result, Refusal):
            return refuse(result)
        session, who = result
        return welcome(who, f"logged in as {who.name} ({who.level})", session=session)

    @app.post("/api/logout")
    async def logout(request: Request) -> Json:
        who = access.logout(_token(request))
        return Json(
            {
                "accepted": True,
                "result": 0,
                "result_name": "ACCEPTED",
                "message": f"{who.name} logged out" if who else "not logged in",
            }
        )

    line.add_routes(app, bridge, STATIC)  # the line page: hmi/line.py
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app


# -- serving ---------------------------------------------------------------------------------------
def bind(host: str, port: int) -> socket.socket:
    """A listening socket (port 0: any free port; read it with ``getsockname()``)."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, _, _, _, address = infos[0]
    # proto=TCP: asyncio sets TCP_NODELAY only on sockets that say so (accepted ones inherit
    # it); without it every answer waited ~40 ms for a delayed ACK (Nagle)
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
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

    def __init__(
        self,
        bridge: Bridge,
        sock: socket.socket,
        log_level: str = "warning",
        allowed_hosts: Iterable[str] = (),
    ) -> None:
        import uvicorn

        self.app = create_app(bridge, allowed_hosts)
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
            # the client's address is the socket's: an X-Forwarded-For from a local process
            # must not pick the address the throttle counts (or write it into the log)
            proxy_headers=False,
            server_header=False,
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
    return Server(
        bridge,
        bind(settings.host, settings.port),
        allowed_hosts=(*settings.allowed_hosts, settings.host),
    )
