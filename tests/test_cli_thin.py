"""Issue 22: the command line only parses, calls one use case of bench/app and renders its result.

Every command registered on the app (``bench --help`` and its groups) has a body of at most 30 lines (its
docstring not counted): a longer one holds use-case logic that belongs in bench/app. And the command modules take
their use cases from bench/app (imports read from the source, in any form).
"""

from __future__ import annotations

import ast
import inspect
import textwrap
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import typer

from bench.cli import app
from tests.conftest import ROOT
from tests.test_layers import imported_modules

MAX_BODY = 30

# commands whose use case is still in the command line, and why (none today)
EXEMPT: dict[str, str] = {}


def commands(t: typer.Typer, prefix: str = "") -> Iterator[tuple[str, Callable[..., Any]]]:
    """(``group command``, the function) of every command and group callback of a typer app."""
    for c in t.registered_commands:
        assert c.callback is not None
        yield prefix + (c.name or c.callback.__name__.replace("_", "-")), c.callback
    if t.registered_callback is not None and t.registered_callback.callback is not None:
        yield prefix.strip() or "bench", t.registered_callback.callback
    for g in t.registered_groups:
        assert g.typer_instance is not None
        yield from commands(g.typer_instance, f"{prefix}{g.name} ")


def body_lines(fn: Callable[..., Any]) -> int:
    """Source lines of a function's body, from its first statement after the docstring to the end of its last
    (nested functions included: they are part of the command)."""
    node = ast.parse(textwrap.dedent(inspect.getsource(inspect.unwrap(fn)))).body[0]
    assert isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
    body = node.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        body = body[1:]
    return 0 if not body else (body[-1].end_lineno or body[-1].lineno) - body[0].lineno + 1


def test_the_measure_counts_the_body_without_its_docstring() -> None:
    """The checker itself, on a function written here: 3 statements over 4 lines, after a 2-line docstring."""
    def sample(x: int) -> int:
        """Two
        lines."""
        y = x + 1
        if y:
            y += 1
        return y

    assert body_lines(sample) == 4


def test_every_command_body_is_at_most_30_lines() -> None:
    found = list(commands(app))
    assert len(found) > 30 and {"run", "inspect", "demo", "simulate thesis", "devices control"} <= {n for n, _ in found}
    long = {name: n for name, fn in found if (n := body_lines(fn)) > MAX_BODY and name not in EXEMPT}
    assert not long, f"command bodies over {MAX_BODY} lines (use-case logic to move to bench/app): {long}"


@pytest.mark.parametrize("module, use_cases", [
    ("run", ("bench.app.runs",)),
    ("analysis", ("bench.app.analysis", "bench.app.fit", "bench.app.demo")),
    ("main", ("bench.app.simulate", "bench.app.sim")),
    ("lab", ("bench.app.manual",)),
])
def test_the_command_modules_take_their_use_cases_from_the_app_layer(module: str, use_cases: tuple[str, ...]) -> None:
    imported = imported_modules(ROOT / "bench" / "cli" / f"{module}.py")
    assert set(use_cases) <= imported, (module, sorted(m for m in imported if m.startswith("bench.")))


def test_progress_shows_a_bar_on_a_terminal_and_nothing_on_a_pipe_or_with_json(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 26 item 7: a use case that lasts reports its fraction done; the command line draws it as a rich
    progress bar on a terminal only (a pipe and --json get nothing extra)."""
    import io

    from rich.console import Console

    from bench.cli import common

    def shown(terminal: bool, json_out: bool = False) -> str:
        out = io.StringIO()
        monkeypatch.setattr(common, "console", Console(file=out, force_terminal=terminal, width=100))
        with common.json_mode(json_out), common.progress("analysing 2 run file(s)") as advance:
            advance(0.5)
            advance(1.0)
        return out.getvalue()

    assert "analysing 2 run file(s)" in shown(terminal=True) and "ETA" in shown(terminal=True)
    assert shown(terminal=False) == ""
    assert shown(terminal=True, json_out=True) == ""


def test_run_planning_shows_its_progress_on_a_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 26 item 7: `bench run`'s validation and dry run (the model over the whole protocol) draws a bar through
    common.progress (on a terminal only: the test above); a dry run plans and touches nothing."""
    import io

    from rich.console import Console
    from typer.testing import CliRunner

    from bench.cli import common

    out = io.StringIO()
    monkeypatch.setattr(common, "console", Console(file=out, force_terminal=True, width=120))
    short = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
    res = CliRunner().invoke(app, ["run", str(short), "--dry-run"], env={"COLUMNS": "200"})
    assert res.exit_code == 0 and "dry run" in res.output, res.output
    assert "validating and dry-running the protocol on the model" in out.getvalue()
