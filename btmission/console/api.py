"""The operator console's HTTP/JSON API, and the guard in front of the whole server.

Routes (added to the viewer's app by :func:`add_console_routes`; the schema is served at
``/openapi.json``):

=====================================  ==========================================================
``GET    /api/console``                the task types, places, priority names, next task id
``GET    /api/status``                 agents and tasks as they stand (JSON)
``POST   /api/tasks``                  add a task ``{id?, type, priority?, <fields>}`` → 201
``DELETE /api/tasks/{id}``             cancel a task
``PATCH  /api/tasks/{id}``             change its priority ``{priority}``
``POST   /api/agents/{id}/recall``     the agent gives up its task and runs its default behaviour
``POST   /api/agents/{id}/exclude``    out of the auction (it keeps the task it holds)
``POST   /api/agents/{id}/include``    back into the auction (a recalled agent too)
``POST   /api/agents/{id}/link``       ``{up}``: cut or restore its link (simulator only)
``POST   /api/allocation``             ``{paused}``: pause or resume allocation
``POST   /api/stop``                   end the run after the current step
=====================================  ==========================================================

Security (:class:`Guard`, an ASGI middleware in front of every route of the server):

* every request that changes something (POST, PATCH, DELETE) needs the run's token, as
  ``Authorization: Bearer <token>`` (or ``?token=``): none is 401, a wrong one 403;
* on a server bound to an address other than loopback every request needs it, but the page's
  static files (read-only views are token-free only on loopback);
* a request from a browser page of another origin (its ``Origin`` header) is refused (403), and
  on loopback the ``Host`` header must name loopback too (DNS rebinding);
* a body over ``BTMISSION_MAX_REQUEST_BYTES`` is 413; commands are rate-limited and bounded
  (:mod:`btmission.console.service`), reads too (:data:`READ_RATE_HZ`), each 429 beyond.

Every refusal is JSON with ``message`` (one sentence, naming the field) and ``detail``.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import re
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qs

from fastapi import Body, Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from fastapi.security import HTTPBearer
from pydantic import BaseModel, ConfigDict, Field, StrictBool
from starlette.exceptions import HTTPException as StarletteHTTPException

from btmission.console.service import Console, ConsoleError, RateLimit
from btmission.errors import BtmissionError

READ_RATE_HZ = 50.0
"""Requests a second (of any kind) the server answers each client on average; a burst of
:data:`READ_BURST` at once; beyond, 429 before any work is done."""
READ_BURST = 100
MAX_CLIENTS = 256
"""Clients with a request-rate bucket of their own; the others share one."""
READ_ONLY = "read-only: the run was started with --view; start it with --console to command it"
TOKEN_ENV = "BTMISSION_TOKEN"
"""The environment variable a run's console token (and the CLI's) may come from."""
MUTATING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
COOKIE = "btmission_token"
"""The cookie that keeps the token for reads off loopback after the page removed it from its
address (HttpOnly, SameSite=Strict; commands still need the header)."""
FREE_PATHS = ("/static/", "/favicon.ico")
"""What needs no token even off loopback: the page's own script and style (public code)."""

Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[MutableMapping[str, Any]]]
Send = Callable[[MutableMapping[str, Any]], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


def new_token() -> str:
    """A fresh per-run secret (192 bits, URL-safe)."""
    return secrets.token_urlsafe(24)


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or ``localhost``) is this machine only."""
    if host.lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@dataclass
class Security:
    """Who may do what on a server bound to ``host``: ``token`` is the run's secret (None: no
    request may change anything, the console is read-only); ``origins``: page origins allowed
    besides the server's own."""

    host: str = "127.0.0.1"
    token: str | None = None
    origins: frozenset[str] = frozenset()
    read_only: str = READ_ONLY
    """Why a command is refused when there is no token."""
    reads: dict[tuple[str, str], RateLimit] = field(default_factory=dict)
    """A request-rate bucket per client (address and ``X-Btmission-Client``): a script's
    flood does not starve the page."""

    def bucket(self, address: str, client: str) -> RateLimit:
        key = (address, client[:24])
        found = self.reads.get(key)
        if found is None:
            if len(self.reads) >= MAX_CLIENTS:  # beyond: the others share one bucket
                key = ("*", "*")
                found = self.reads.get(key)
            if found is None:
                found = self.reads[key] = RateLimit(READ_RATE_HZ, READ_BURST)
        return found

    @property
    def loopback(self) -> bool:
        return is_loopback(self.host)

    def needs_token(self, method: str, path: str) -> bool:
        if method in MUTATING:
            return True
        return not self.loopback and not path.startswith(FREE_PATHS)


def _refusal(status: int, message: str, detail: Any = None, **headers: str) -> JSONResponse:
    return JSONResponse(
        {"message": message, "detail": detail if detail is not None else message},
        status_code=status,
        headers=headers or None,
    )


class Guard:
    """The ASGI middleware of the module docstring (token, origin, host, size, rate)."""

    def __init__(self, app: ASGIApp, security: Security) -> None:
        self.app = app
        self.security = security

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        refusal = self.check(scope)
        if refusal is not None:
            await refusal(scope, receive, send)
            return
        if self.security.token is not None and scope["method"] == "GET" and scope["path"] == "/":
            send = self._remember(scope, send)
        await self.app(scope, _bounded(receive), send)

    def _remember(self, scope: Scope, send: Send) -> Send:
        """The page opened with ``?token=``: a cookie keeps the token for this browser, so that
        a reload (the page removes the token from its address) still reads off loopback. The
        cookie serves reads only: a command needs the header (no cross-site request sends it)."""
        token = parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token", [""])[0]
        assert self.security.token is not None
        if not token or not hmac.compare_digest(token.encode(), self.security.token.encode()):
            return send
        secure = "; Secure" if scope.get("scheme") == "https" else ""
        cookie = f"{_cookie(scope)}={token}; Path=/; HttpOnly; SameSite=Strict{secure}"

        async def inner(message: MutableMapping[str, Any]) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", []), (b"set-cookie", cookie.encode())]
            await send(message)

        return inner

    def check(self, scope: Scope) -> JSONResponse | None:
        """The refusal of this request, or None to let it through."""
        from btmission.limits import MAX_REQUEST_BYTES

        sec = self.security
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        peer = scope.get("client") or ("?", 0)
        wait = sec.bucket(str(peer[0]), headers.get("x-btmission-client", "api")).take()
        if wait > 0:
            return _refusal(
                429,
                f"too many requests: at most {READ_RATE_HZ:g} a second; retry in {wait:.2f} s",
                **{"Retry-After": str(max(1, round(wait)))},
            )
        host = headers.get("host", "")
        if sec.loopback and host and not is_loopback(_hostname(host)):
            return _refusal(
                403,
                f"host '{host}' is not this machine: the console answers on loopback only "
                "(start it with --host to serve other machines)",
            )
        origin = headers.get("origin")
        if origin is not None:  # "null" too: a sandboxed frame or a file:// page
            own = {f"{scope.get('scheme', 'http')}://{host}"}
            if origin not in own and origin not in sec.origins:
                return _refusal(403, f"origin '{origin}' may not use this console")
        size = headers.get("content-length")
        limit = int(MAX_REQUEST_BYTES.value)
        if size is not None and (not size.isdigit() or int(size) > limit):
            return _refusal(
                413, f"the request body is over {limit} bytes (BTMISSION_MAX_REQUEST_BYTES)"
            )
        method, path = scope["method"], scope["path"]
        if sec.needs_token(method, path):
            if sec.token is None:
                return _refusal(403, sec.read_only)
            query = scope.get("query_string", b"")
            given = _token_of(headers, query, _cookie(scope) if method not in MUTATING else None)
            if not given:
                return _refusal(
                    401,
                    "this request needs the run's token, printed with the URL when the run started",
                    **{"WWW-Authenticate": "Bearer"},
                )
            if not hmac.compare_digest(given.encode(), sec.token.encode()):
                return _refusal(403, "wrong token: use the one printed when the run started")
        return None


def _hostname(host: str) -> str:
    if host.startswith("["):
        return host[1 : host.find("]")]
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def _cookie(scope: Scope) -> str:
    """The cookie's name on this server (cookies ignore ports: two runs must not share one)."""
    server = scope.get("server") or ("", 0)
    return f"{COOKIE}_{server[1]}"


def _token_of(headers: dict[str, str], query: bytes, cookie: str | None) -> str:
    """The token a request carries: its Bearer header, its ``?token=``, or (a read only) the
    page's cookie."""
    auth = headers.get("authorization", "")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    values = parse_qs(query.decode("latin-1")).get("token")
    if values:
        return values[0]
    if cookie is not None:  # a read: the page's cookie will do
        for part in headers.get("cookie", "").split(";"):
            name, _, value = part.strip().partition("=")
            if name == cookie:
                return value
    return ""


def _bounded(receive: Receive) -> Receive:
    """``receive`` that stops a body with no (or a false) Content-Length past the budget."""
    from btmission.limits import MAX_REQUEST_BYTES

    limit = int(MAX_REQUEST_BYTES.value)
    seen = 0

    async def inner() -> MutableMapping[str, Any]:
        nonlocal seen
        message = await receive()
        if message["type"] == "http.request":
            seen += len(message.get("body", b""))
            if seen > limit:
                raise _TooLarge(limit)
        return message

    return inner


class _TooLarge(BtmissionError):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the request body is over {limit} bytes (BTMISSION_MAX_REQUEST_BYTES)")


# ---------------------------------------------------------------------------- the routes' models
class CommandResult(BaseModel):
    """A command's answer."""

    ok: bool
    command: str
    t: float = Field(description="Mission time (s) it was applied at.")
    message: str = Field(description="What happened, in one sentence.")
    task: str | None = None


class PriorityBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    priority: Any = Field(  # checked by the console (priority_value): one message for all
        json_schema_extra={
            "anyOf": [
                {"type": "number", "exclusiveMinimum": 0},
                {"type": "string", "enum": ["low", "normal", "high", "urgent"]},
            ]
        },
        description="A number > 0, or low / normal / high / urgent (× the type's priority).",
    )


class LinkBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    up: StrictBool = Field(description="false: cut the link; true: restore it.")


class AllocationBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    paused: StrictBool


class StopBody(BaseModel):
    model_config = ConfigDict(extra="forbid")
    reason: str = Field("", max_length=200)


class Refusal(BaseModel):
    """Every refusal: one sentence naming the field, and FastAPI's detail (for a 422 a list of
    ``{loc, msg, type}``)."""

    message: str
    detail: Any = None


class AgentStatus(BaseModel):
    id: str
    alive: bool
    link_up: bool
    recalled: bool
    excluded: bool
    task: str | None
    action: str
    mode: str
    armed: bool
    p: list[float] = Field(description="[x, y, z] (m), map frame")
    yaw: float


class TaskStatus(BaseModel):
    id: str
    type: str
    state: str = Field(description="open, assigned, committed, done, failed, unreachable, "
                       "cancelled, or scheduled (its arrival time is still to come)")  # fmt: skip
    agent: str | None
    priority: float
    added_s: float
    note: str = Field(description="Why it is in that state (the pool's note).")
    since_s: float
    history: list[list[Any]] = Field(description="Its latest changes: [t, state, agent, reason].")
    fields: dict[str, Any]


class Status(BaseModel):
    """The run after its last step."""

    t: float
    steps: int
    running: bool
    ended: str | None
    allocation: dict[str, bool]
    agents: list[AgentStatus]
    tasks: list[TaskStatus]


_WHY = {
    401: "No token (the run's token: Authorization: Bearer <token>).",
    403: "A wrong token, another origin, a Host not on loopback, or a read-only run.",
    404: "No such task or agent.",
    409: "Not now: the task is over, or the run has ended.",
    413: "The body is over BTMISSION_MAX_REQUEST_BYTES.",
    422: "A bad body: the message names the field.",
    429: "Too many requests or commands (Retry-After).",
}
REFUSALS: dict[int | str, dict[str, Any]] = {
    202: {"model": CommandResult, "description": "Queued: its step did not come within 5 s."},
    **{code: {"model": Refusal, "description": why} for code, why in _WHY.items()},
}
READ_REFUSALS: dict[int | str, dict[str, Any]] = {
    code: {"model": Refusal, "description": _WHY[code]} for code in (401, 403, 429)
}
TASK_EXAMPLE = {"type": "inspect", "location": [60.0, 9.5, 2.0], "priority": "high"}
_CLIENT = re.compile(r"[^A-Za-z0-9_.-]")


def who(request: Request) -> str:
    """``<client>@<address>``: the ``X-Btmission-Client`` header (page, cli, a script's name;
    default api) and where the request came from; logged with the command."""
    client = _CLIENT.sub("", request.headers.get("x-btmission-client", "api"))[:24] or "api"
    address = request.client.host if request.client is not None else "?"
    return f"{client}@{address}"


def _answer(result: Any, created: bool = False) -> JSONResponse:
    status = result.status if result.status != 200 or not created else 201
    return JSONResponse(result.to_json(), status_code=status)


def add_console_routes(app: FastAPI, console: Console | None, read_only_reason: str) -> None:
    """The routes of the module docstring on ``app``. Without a ``console`` (a replay, or a
    run started with --view), status still answers where it can and commands are refused with
    ``read_only_reason``."""

    @app.exception_handler(ConsoleError)
    async def console_error(request: Request, exc: ConsoleError) -> JSONResponse:
        detail: Any = exc.message
        if exc.field or exc.status == 422:  # FastAPI's form: where in the body, and why
            loc = ["body", exc.field] if exc.field else ["body"]
            detail = [{"loc": loc, "msg": exc.message, "type": "value_error"}]
        headers = {"Retry-After": "1"} if exc.status == 429 else {}
        return _refusal(exc.status, exc.message, detail, **headers)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code == 404:
            message = f"no such route: {request.method} {request.url.path} (see /openapi.json)"
        elif exc.status_code == 405:
            message = f"{request.url.path} does not take {request.method} (see /openapi.json)"
        else:
            message = str(exc.detail)
        return _refusal(exc.status_code, message, exc.detail)

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = json.loads(json.dumps(exc.errors(), default=str))
        first: dict[str, Any] = errors[0] if errors else {"loc": ["body"], "msg": "invalid"}
        if first.get("type") == "missing" and list(first.get("loc", [])) == ["body"]:
            return _refusal(422, "the request needs a JSON body (see /openapi.json)", errors)
        if first.get("type") == "json_invalid":
            why = (first.get("ctx") or {}).get("error", "")
            at = first.get("loc", ["body", 0])[-1]
            message = f"the body is not valid JSON: {why} (at character {at})"
        else:
            where = ".".join(str(p) for p in first.get("loc", []) if p != "body") or "body"
            message = f"{where}: {first.get('msg')}"
        return _refusal(422, message, errors)

    @app.exception_handler(_TooLarge)
    async def too_large(request: Request, exc: _TooLarge) -> JSONResponse:
        return _refusal(413, str(exc))

    def need() -> Console:
        if console is None:
            raise ConsoleError(403, read_only_reason)
        return console

    bearer = HTTPBearer(
        auto_error=False,
        description="The run's token, printed with the page's URL when it started "
        "(?token=…); also accepted as ?token=.",
    )
    command: dict[str, Any] = {
        "tags": ["console"],
        "response_model": CommandResult,
        "dependencies": [Depends(bearer)],  # (the guard checks it: this documents it)
        "responses": REFUSALS,
    }

    @app.get("/api/console", tags=["console"], responses=READ_REFUSALS)
    def console_info() -> dict[str, Any]:
        """What a client needs to build a command: the task types (their fields, which are
        positions, their priority), the places, the priority names, the next free task id
        (``/api/info`` has the same under ``console``, with the map's bounds)."""
        return need().info()

    @app.get("/api/status", tags=["console"], responses={200: {"model": Status}, **READ_REFUSALS})
    def status() -> Response:
        """Agents (pose, task, alive, link, recalled, excluded) and tasks (state, agent,
        priority, the pool's note, its latest changes) after the run's last step."""
        return Response(need().status_json(), media_type="application/json")

    @app.post("/api/tasks", status_code=201, **command)
    def add_task(
        request: Request,
        task: Any = Body(  # any JSON: the service says what it wants
            ...,
            examples=[TASK_EXAMPLE],
            json_schema_extra={"type": "object", "additionalProperties": True},
        ),
    ) -> JSONResponse:
        """Add a task: ``type``, the type's fields (a position ``[x, y, z]`` or a place),
        optionally ``id`` (default: the next free one, e.g. T8), ``priority`` (a number or
        low/normal/high/urgent) and ``at`` (s). It is checked as a mission file's task is,
        and its positions against the map: a refusal is 422 naming the field."""
        return _answer(need().add_task(task, who(request)), created=True)

    @app.delete("/api/tasks/{task_id}", **command)
    def cancel_task(request: Request, task_id: str) -> JSONResponse:
        """Cancel a task: it leaves the pool (state cancelled); its agent stops it."""
        return _answer(need().cancel_task(task_id, who(request)))

    @app.patch("/api/tasks/{task_id}", **command)
    def set_priority(request: Request, task_id: str, body: PriorityBody) -> JSONResponse:
        """Change a task's priority (it is announced again with it)."""
        return _answer(need().set_priority(task_id, body.priority, who(request)))

    @app.post("/api/agents/{agent}/recall", **command)
    def recall(request: Request, agent: str) -> JSONResponse:
        """The agent gives up its task, bids no more and runs its default behaviour now."""
        return _answer(need().recall(agent, who(request)))

    @app.post("/api/agents/{agent}/exclude", **command)
    def exclude(request: Request, agent: str) -> JSONResponse:
        """The agent leaves the auction: it keeps the task it holds and wins nothing else."""
        return _answer(need().exclude(agent, True, who(request)))

    @app.post("/api/agents/{agent}/include", **command)
    def include(request: Request, agent: str) -> JSONResponse:
        """The agent takes part in the auction again (an excluded or a recalled one)."""
        return _answer(need().exclude(agent, False, who(request)))

    @app.post("/api/agents/{agent}/link", **command)
    def link(request: Request, agent: str, body: LinkBody) -> JSONResponse:
        """Cut (``up: false``) or restore an agent's link to the coordinator, for drills:
        simulated vehicles only. The agent keeps executing its task meanwhile."""
        return _answer(need().set_link(agent, body.up, who(request)))

    @app.post("/api/allocation", **command)
    def allocation(request: Request, body: AllocationBody) -> JSONResponse:
        """Pause allocation (every holder keeps its task, nothing else is assigned) or
        resume it."""
        return _answer(need().set_allocation(body.paused, who(request)))

    @app.post("/api/stop", **command)
    def stop(request: Request, body: StopBody | None = None) -> JSONResponse:
        """End the run after the current step (as Ctrl-C does); the log and report are
        complete."""
        return _answer(need().stop(who(request), body.reason if body is not None else ""))
