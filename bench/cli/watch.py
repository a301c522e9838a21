"""``bench watch``: live plots of run files in a browser; and the server ``bench run --web`` starts beside its run.

The web libraries (Starlette, uvicorn) are the optional ``web`` extra, imported inside the command only, so
``bench --help`` and every other command start without them.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer

from bench.cli.common import clean_errors, console, escape

WEB_EXTRA = "bench watch needs the web extra: pip install 'dea-bench[web]'"
DEFAULT_PORT = 8765
LINGER_S = 1.5  # bench run --web: the server outlives the run this long, so an open page shows how it ended
TOKEN_ENV = "BENCH_WATCH_TOKEN"  # bench run --web hands the token to its server through the environment


def _web_libraries() -> None:
    try:
        import starlette  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError:
        raise ValueError(WEB_EXTRA) from None


def url(host: str, port: int, token: str | None) -> str:
    """The page's address (with the token when one is required)."""
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/" + (f"?token={token}" if token else "")


@clean_errors
def watch(
    runs: Annotated[list[Path], typer.Argument(help="Run files (.h5), finished or being written, or folders whose "
                                               "run files (also new ones) are served.")],
    host: Annotated[str, typer.Option(help="Address to serve on; any other than the loopback needs the token "
                                      "printed at start.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Port (0: a free one).", min=0, max=65535)] = DEFAULT_PORT,
    pending: Annotated[bool, typer.Option("--pending", hidden=True, help="The run file may not exist yet "
                                          "(bench run --web).")] = False,
) -> None:
    """Serve live plots of run files to a browser: every stream on the run's time base, steps and events marked,
    the rig's limits, the run's state and faults; follows a file being written within a second.

    Safe by default: it binds 127.0.0.1; on any other address every request needs the token printed here. The page
    can only pause a run or stop it (go safe), through the run's control file as `bench pause` does; both are
    recorded in the run file as coming from "web <client address>"."""
    if pending:  # first: Linux lowers the calling thread's priority, which the threads started later inherit
        _yield_to_the_run()
    _web_libraries()  # before the server's module, which imports Starlette itself
    from bench.watch.server import Served, bind, create_app, is_loopback, serve

    files, folders = [], []
    for p in runs:
        if p.is_dir():
            folders.append(p)
        elif p.is_file() or (pending and p.parent.is_dir()):
            if p.suffix != ".h5":
                raise ValueError(f"run file {p}: not a .h5 file")
            files.append(p)
        else:
            from bench.storage.absent import absent_run_file

            raise ValueError(absent_run_file(p))
    loopback = is_loopback(host)
    token = None if loopback else (os.environ.get(TOKEN_ENV) or secrets.token_urlsafe(18))
    sock = bind(host, port)
    app = create_app(Served(files, folders), token=token, loopback=loopback)
    if pending:  # bench run --web: the server ends with the run's process, also when that one is killed
        _end_with(os.getppid())
    if not pending:
        console.print(f"watching {len(files) + len(folders)} run(s): {url(host, sock.getsockname()[1], token)}")
        if token:
            console.print(f"token required (not on the loopback): {token}")
        console.print("Ctrl-C stops the server (not the runs)")
    sys.stdout.flush()
    serve(app, sock)


SERVER_NICE = 10  # bench run --web: the page's server this much nicer than the run it shows


def _yield_to_the_run() -> None:
    """Lower this server's CPU priority (``bench run --web``): on a loaded host the run, which feeds the DAQ and
    must not fall behind it, gets the CPU before the page's reads and plots (a wall-clock run that falls 0.5 s behind
    trips on a stream-out underrun). Best effort: a platform without ``os.nice`` serves as it is."""
    with contextlib.suppress(AttributeError, OSError):
        os.nice(SERVER_NICE)


def _end_with(parent: int) -> None:
    """SIGTERM to this process (uvicorn's graceful end) once ``parent`` is gone (this process is re-parented)."""
    import signal
    import threading

    def watch_parent() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch_parent, name="bench-watch-parent", daemon=True).start()


@contextlib.contextmanager
def serving(run_file: Path, port: int) -> Iterator[str]:
    """``bench run --web``: ``bench watch`` on the run file in its own process (its reads never hold up the run's
    writes), from before the file exists until shortly after the run ends; yields the page's address."""
    from bench.watch import free_port

    _web_libraries()
    port = free_port(port)
    cmd = [sys.executable, "-m", "bench", "watch", str(run_file), "--port", str(port), "--pending"]
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL)
    try:
        address = url("127.0.0.1", port, None)
        console.print(f"watch the run at {escape(address)} (pause and stop there too)")
        sys.stdout.flush()
        yield address
        time.sleep(LINGER_S)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def register(app: typer.Typer) -> None:
    """Put ``watch`` on ``app``."""
    app.command()(watch)
