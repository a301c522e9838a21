"""The watch page's server: Starlette routes over :class:`~bench.watch.follow.Follower` (run by uvicorn).

Routes: ``/`` the page and ``/static/…`` its scripts (uPlot vendored); ``GET /api/runs`` the served run files;
``GET /api/runs/{name}?have=stream:generation:bins,…`` a run's state, marks and the bins the page lacks;
``POST /api/runs/{name}/pause`` and ``…/stop`` — the only actions — written to the run's control file
(:mod:`bench.runtime.control`, as ``bench pause`` does) with ``by = "web <client address>"``, so the run records
where they came from.

Safe by default: the command binds 127.0.0.1; bound to any other address it requires a token (printed at start),
sent as the ``X-Bench-Token`` header, the ``token`` query parameter (the page's address) or the cookie that
parameter sets. A POST must carry the ``X-Bench`` header (a cross-site form cannot), and on loopback the Host header
must name the loopback (a DNS-rebinding page cannot reach the server). Only the served run files are read: a file
given by name, or any ``.h5`` directly in a served folder; a name is a bare file name, never a path.
"""

from __future__ import annotations

import ipaddress
import secrets
import socket
from dataclasses import dataclass, field
from pathlib import Path

from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from bench.runtime.control import write_control
from bench.watch.follow import Follower

STATIC = Path(__file__).with_name("static")
TOKEN_HEADER = "x-bench-token"
TOKEN_COOKIE = "bench_token"
ACTION_HEADER = "x-bench"  # a POST without it is refused (cross-site requests cannot set it without a preflight)
ACTIONS = {"pause": "the pause button of the watch page", "stop": "the stop button of the watch page"}
LOOPBACK_HOSTS = ["127.0.0.1", "localhost", "[::1]", "testserver"]  # testserver: Starlette's test client


@dataclass
class Served:
    """What may be read: run files named one by one, and folders whose ``.h5`` files (also new ones) are runs."""

    files: list[Path] = field(default_factory=list)
    folders: list[Path] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.files = [p.resolve() for p in self.files]
        self.folders = [p.resolve() for p in self.folders]

    def names(self) -> list[str]:
        """The served runs' file names (a folder's newest first)."""
        found = [p.name for p in self.files]
        for d in self.folders:
            found += [p.name for p in sorted(d.glob("*.h5"), key=lambda p: p.stat().st_mtime, reverse=True)]
        return list(dict.fromkeys(found))

    def resolve(self, name: str) -> Path | None:
        """The served file called ``name``; None for anything else (a path, ``..``, another file)."""
        if not name or "/" in name or "\\" in name or name in (".", "..") or not name.endswith(".h5"):
            return None
        for p in self.files:
            if p.name == name:
                return p
        for d in self.folders:
            p = (d / name).resolve()
            if p.parent == d and p.is_file():
                return p
        return None


class TokenGate:
    """ASGI middleware: every request carries the token (header, ``token`` query parameter or cookie)."""

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app = app
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request = Request(scope)
        offered = [request.headers.get(TOKEN_HEADER, ""), request.query_params.get("token", ""),
                   request.cookies.get(TOKEN_COOKIE, "")]
        if not any(secrets.compare_digest(o.encode(), self.token.encode()) for o in offered if o):
            await JSONResponse({"error": "token required: open the address `bench watch` printed"}, 401)(
                scope, receive, send)
            return
        if secrets.compare_digest(offered[1].encode(), self.token.encode()):  # the page's address: keep it as cookie

            async def with_cookie(message: Message) -> None:
                if message["type"] == "http.response.start":
                    cookie = f"{TOKEN_COOKIE}={self.token}; Path=/; HttpOnly; SameSite=Strict"
                    message.setdefault("headers", []).append((b"set-cookie", cookie.encode()))
                await send(message)

            await self.app(scope, receive, with_cookie)
            return
        await self.app(scope, receive, send)


def create_app(served: Served, token: str | None = None, loopback: bool = True) -> Starlette:
    """The watch app over ``served``; ``token``: required on every request (needed when not on loopback)."""
    followers: dict[Path, Follower] = {}

    def follower(name: str) -> Follower | None:
        path = served.resolve(name)
        if path is None:
            return None
        if path not in followers:
            followers[path] = Follower(path)
        return followers[path]

    def page(_request: Request) -> Response:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    def runs(_request: Request) -> Response:
        return JSONResponse({"runs": served.names()})

    def run(request: Request) -> Response:  # sync: Starlette runs it in its thread pool (h5py blocks)
        f = follower(request.path_params["name"])
        if f is None:
            return JSONResponse({"error": "not a served run"}, 404)
        have: dict[str, tuple[int, int]] = {}
        for part in request.query_params.get("have", "").split(","):
            stream, _, rest = part.partition(":")
            gen, _, bins = rest.partition(":")
            if stream and gen.lstrip("-").isdigit() and bins.isdigit():
                have[stream] = (int(gen), int(bins))
        try:
            f.look()
        except (OSError, KeyError, ValueError) as exc:  # not a run file, or a read that failed: said on the page
            return JSONResponse({"error": f"{f.path.name}: {' '.join(str(exc).split())[:300]}"}, 500)
        return JSONResponse(f.payload(have), headers={"Cache-Control": "no-store"})

    def action(request: Request) -> Response:
        what = request.path_params["action"]
        if what not in ACTIONS:
            return JSONResponse({"error": "the page can only pause or stop a run"}, 404)
        if ACTION_HEADER not in request.headers:
            return JSONResponse({"error": f"missing {ACTION_HEADER} header"}, 403)
        f = follower(request.path_params["name"])
        if f is None:
            return JSONResponse({"error": "not a served run"}, 404)
        try:
            f.look()
        except (OSError, KeyError, ValueError) as exc:
            return JSONResponse({"error": f"{f.path.name}: {' '.join(str(exc).split())[:300]}"}, 409)
        if f.info.get("state") not in ("running", "paused"):
            return JSONResponse({"error": f"no run is writing {f.path.name} ({f.info.get('state')})"}, 409)
        client = request.client.host if request.client else "unknown"
        write_control(f.path, True, f"web {client}", ACTIONS[what], stop=what == "stop")
        return JSONResponse({"asked": what, "by": f"web {client}"})

    routes = [Route("/", page), Route("/api/runs", runs), Route("/api/runs/{name}", run),
              Route("/api/runs/{name}/{action}", action, methods=["POST"]),
              Mount("/static", StaticFiles(directory=STATIC), name="static")]
    middleware = [Middleware(TrustedHostMiddleware, allowed_hosts=LOOPBACK_HOSTS)] if loopback else []
    if token:
        middleware.append(Middleware(TokenGate, token=token))
    app = Starlette(routes=routes, middleware=middleware)
    app.state.followers = followers
    return app


def is_loopback(host: str) -> bool:
    """Whether binding ``host`` serves this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (port 0: a free one); one line on failure."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise ValueError(f"cannot serve on {host}:{port}: {exc.strerror or exc}") from None
    sock.listen(64)
    return sock


def serve(app: Starlette, sock: socket.socket) -> None:
    """Serve ``app`` on ``sock`` until Ctrl-C / SIGTERM (uvicorn: HTTP/1.1 and the asyncio loop are its own)."""
    import uvicorn

    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="off")
    uvicorn.Server(config).run(sockets=[sock])
