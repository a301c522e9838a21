"""What the command modules share: the consoles, one-line errors, --json output (and the dask cluster seam of
bench/app/cluster.py).

Imported by ``bench --help`` and by every TAB completion: nothing heavy at module level (numpy, scipy, numba, the
models, dask load inside the functions that need them; tests/test_cli_startup.py). Even rich's console, text and
table modules (a fifth of ``bench --help``, which typer prints without them) load on first use: the consoles are
made when something is printed, and ``Table`` and ``escape`` here import rich's when called.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ParamSpec, TypeVar, cast

import typer

from bench.app.cluster import CLUSTER_EXTRA, cluster_client  # noqa: F401  # re-exported: the commands take it here
from drivers.errors import InstrumentError

if TYPE_CHECKING:
    from rich.table import Table as Table

    from bench.cli.console import BenchConsole
else:
    def Table(*args: Any, **kwargs: Any) -> Any:
        """:class:`rich.table.Table`, imported on first use."""
        from rich.table import Table as RichTable

        return RichTable(*args, **kwargs)


def escape(markup: str) -> str:
    """:func:`rich.markup.escape`, imported on first use: ``markup`` printed as written."""
    from rich.markup import escape as rich_escape

    return rich_escape(markup)


class _OnFirstUse:
    """A :class:`BenchConsole` made on first use (attribute, ``with``): stands for it everywhere."""

    def __init__(self, **kwargs: Any) -> None:
        object.__setattr__(self, "_kwargs", kwargs)
        object.__setattr__(self, "_console", None)

    def _made(self) -> BenchConsole:
        made = object.__getattribute__(self, "_console")
        if made is None:
            from bench.cli.console import BenchConsole

            made = BenchConsole(**object.__getattribute__(self, "_kwargs"))
            object.__setattr__(self, "_console", made)
        return cast("BenchConsole", made)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._made(), name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._made(), name, value)

    def __enter__(self) -> BenchConsole:  # rich's Live does `with console:`
        made = self._made()
        made.__enter__()
        return made

    def __exit__(self, *exc: Any) -> None:
        self._made().__exit__(*exc)


# units in brackets stay text; redirected output is not cut to a terminal width (bench/cli/console.py)
console = cast("BenchConsole", _OnFirstUse())
err_console = cast("BenchConsole", _OnFirstUse(stderr=True))
JsonOpt = Annotated[bool, typer.Option("--json", help="Print the result as JSON on stdout (nothing else).")]

P = ParamSpec("P")
R = TypeVar("R")


def fail(message: str, code: int = 2) -> typer.Exit:
    """Print a one-line error on stderr and return the Exit to raise (``message`` is plain text, not markup)."""
    err_console.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
    return typer.Exit(code)


def clean_errors(fn: Callable[P, R]) -> Callable[P, R]:
    """Turn the expected failures of a command (bad values, missing files) into one-line errors, exit 2."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return fn(*args, **kwargs)
        except (ValueError, OSError, InstrumentError) as exc:
            raise fail(" ".join(str(exc).splitlines())) from None
        except (RecursionError, MemoryError) as exc:  # inputs are bounded where they are read; a last resort
            raise fail(f"input too large or too deeply nested ({type(exc).__name__})") from None

    return wrapper


def print_json(data: object) -> None:
    """Write ``data`` as JSON to stdout (NaN and infinities as null), whatever --quiet says."""
    import json
    import math
    import sys

    import numpy as np

    def clean(x: object) -> object:
        if isinstance(x, float | np.floating):
            return float(x) if math.isfinite(x) else None
        if isinstance(x, np.bool_):
            return bool(x)
        if isinstance(x, np.integer):
            return int(x)
        if isinstance(x, np.ndarray):
            return clean(x.tolist())
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        if isinstance(x, Path):
            return str(x)
        return x

    sys.stdout.write(json.dumps(clean(data), indent=1, ensure_ascii=False) + "\n")
    sys.stdout.flush()


@contextlib.contextmanager
def json_mode(enabled: bool) -> Iterator[None]:
    """While enabled, the console prints nothing (stdout carries the JSON only); errors still go to stderr."""
    quiet = console.quiet
    console.quiet = quiet or enabled
    try:
        yield
    finally:
        console.quiet = quiet


@contextlib.contextmanager
def progress(description: str) -> Iterator[Callable[[float], None]]:
    """A progress callback (fraction done, 0 … 1) for a use case that lasts: a rich progress bar with the time
    spent and an estimate of the time left on a terminal (gone when done), nothing on a pipe, with -q or with
    --json (:func:`json_mode`)."""
    if console.quiet or not console.is_terminal:
        yield lambda _fraction: None
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with Progress(TextColumn(description), BarColumn(), TextColumn("{task.percentage:>3.0f} %"), TimeElapsedColumn(),
                  TextColumn("ETA"), TimeRemainingColumn(), console=console, transient=True) as bar:
        task = bar.add_task(description, total=1.0)
        yield lambda fraction: bar.update(task, completed=min(max(fraction, 0.0), 1.0))


def _version(value: bool) -> None:
    if value:
        from bench import __version__

        console.print(f"dea-bench {__version__}")
        raise typer.Exit()
