"""Import direction between the packages (docs/architecture.md), checked on the source.

drivers/ speak wire protocols and know nothing of the application or the twins; sim_devices/ are written from the
manuals and never take a driver's protocol constants; the core (bench/core: clock, motion profile, plant) and
protocol compilation (bench/protocol) know neither twins nor drivers, and the core needs nothing of the
application beyond the physical models; storage (run files) knows neither the run time nor the command line, only
bench/cli and bench/__main__.py import the command line, and bench's packages import one another without a cycle.
Every import counts, including those inside functions.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import ROOT


def imported_modules(path: Path) -> set[str]:
    """Absolute modules a source file imports (anywhere in it); relative imports resolved against its package."""
    package = ".".join(path.relative_to(ROOT).parts[:-1]) if path.is_relative_to(ROOT) else ""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                out.add(node.module or "")
            else:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                out.add(".".join([*base, *([node.module] if node.module else [])]))
    return out


def offenders(package: str, forbidden: tuple[str, ...], allowed: tuple[str, ...] = ()) -> list[str]:
    """Imports of the package's files that start with a forbidden module and with no allowed one."""
    def starts(mod: str, prefixes: tuple[str, ...]) -> bool:
        return any(mod == p or mod.startswith(p + ".") for p in prefixes)

    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"no sources under {package}"
    return [f"{path.relative_to(ROOT)} imports {mod}" for path in files for mod in sorted(imported_modules(path))
            if starts(mod, forbidden) and not starts(mod, allowed)]


@pytest.mark.parametrize("package, forbidden, allowed", [
    ("drivers", ("bench", "sim_devices"), ()),
    ("sim_devices", ("drivers", "bench"), ("bench.core", "bench.models")),  # the twins know no rig file
    ("bench/protocol", ("sim_devices", "drivers"), ()),
    # bench.numbers: how a value is said against its limit (a leaf: it imports math only, checked below)
    ("bench/core", ("sim_devices", "drivers", "bench"), ("bench.core", "bench.models", "bench.numbers")),
    ("bench/storage", ("bench.runtime", "bench.cli"), ()),
    ("bench/app", ("bench.cli", "typer", "rich"), ()),  # the use cases know no command line, print nothing
    ("bench", ("tests",), ()),  # the fuzz harnesses (tests/fuzzing) are a testing tool, never product code
])
def test_no_import_goes_up_or_across_the_layers(package: str, forbidden: tuple[str, ...],
                                                allowed: tuple[str, ...]) -> None:
    found = offenders(package, forbidden, allowed)
    assert not found, found


def test_the_check_sees_imports_inside_functions(tmp_path: Path) -> None:
    """The checker itself: a function-level import and a relative one are found (a lazy import counts too)."""
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from bench.runtime.sim_rig import SimRig\n    import drivers.keyence\n",
                   encoding="utf-8")
    assert imported_modules(src) >= {"bench.runtime.sim_rig", "drivers.keyence"}
    inside = ROOT / "bench" / "protocol" / "program.py"
    assert "bench.rig" in imported_modules(inside)


def test_only_the_entry_points_import_the_command_line() -> None:
    """bench/cli is the top: nothing of the application imports it but bench/cli itself and bench/__main__.py."""
    found = [f"{path.relative_to(ROOT)} imports {mod}" for path in sorted((ROOT / "bench").rglob("*.py"))
             if not path.is_relative_to(ROOT / "bench" / "cli") and path != ROOT / "bench" / "__main__.py"
             for mod in sorted(imported_modules(path)) if mod == "bench.cli" or mod.startswith("bench.cli.")]
    assert not found, found


def test_only_the_command_line_imports_the_application_layer() -> None:
    """Issue 22: bench/app (one call per use case) sits just below the command line: bench/cli is its only
    importer; the run time, storage, identification … never call a use case back."""
    found = [f"{path.relative_to(ROOT)} imports {mod}" for path in sorted((ROOT / "bench").rglob("*.py"))
             if not path.is_relative_to(ROOT / "bench" / "cli") and not path.is_relative_to(ROOT / "bench" / "app")
             for mod in sorted(imported_modules(path)) if mod == "bench.app" or mod.startswith("bench.app.")]
    assert not found, found
    assert (ROOT / "bench" / "app" / "runs.py").is_file()


def test_command_modules_do_not_import_the_app_back() -> None:
    """bench/cli/__init__.py builds the app and calls each command module's register(); no module imports it back."""
    found = [f"{path.relative_to(ROOT)} imports bench.cli" for path in sorted((ROOT / "bench" / "cli").glob("*.py"))
             if path.name != "__init__.py" and "bench.cli" in imported_modules(path)]
    assert not found, found


def package_graph() -> dict[str, set[str]]:
    """bench's import graph by package: a subpackage (bench/runtime, …) or a top-level module (bench/rig.py) is one
    node; an edge for every import of another node by any file of it (imports inside functions included)."""
    graph: dict[str, set[str]] = {}
    for path in sorted((ROOT / "bench").rglob("*.py")):
        parts = path.relative_to(ROOT / "bench").parts
        node = parts[0] if len(parts) > 1 else path.stem
        graph.setdefault(node, set())
        for mod in imported_modules(path):
            names = mod.split(".")
            if names[0] == "bench" and len(names) > 1 and names[1] != node:
                graph[node].add(names[1])
    return graph


def test_the_packages_of_bench_import_one_another_without_a_cycle() -> None:
    """No import cycle between bench's packages (and top-level modules): the layout reads as layers, top to bottom
    cli → benchmarks → runtime → storage, identify → analysis → protocol → core → models (see docs/architecture.md).
    No exception is needed today: a cycle found here is a package boundary to fix, not to allow."""
    graph = package_graph()
    assert {"cli", "runtime", "storage", "benchmarks", "core", "protocol", "models"} <= set(graph)
    done: set[str] = set()

    def visit(node: str, path: tuple[str, ...]) -> None:
        assert node not in path, f"import cycle: {' → '.join([*path[path.index(node):], node])}"
        if node in done:
            return
        for nxt in sorted(graph.get(node, ())):
            visit(nxt, (*path, node))
        done.add(node)

    for start in sorted(graph):
        visit(start, ())


def test_the_cycle_check_finds_a_cycle(monkeypatch: pytest.MonkeyPatch) -> None:
    """The checker itself: a planted cycle between two packages fails the test."""
    monkeypatch.setattr(f"{__name__}.package_graph",
                        lambda: {"cli": set(), "runtime": {"storage"}, "storage": {"runtime"}, "benchmarks": set(),
                                 "core": set(), "protocol": set(), "models": set()})
    with pytest.raises(AssertionError, match="import cycle: runtime → storage → runtime"):
        test_the_packages_of_bench_import_one_another_without_a_cycle()


def test_the_engine_polls_through_the_poll_table_not_by_instrument() -> None:
    """Issue 9, issue 22: a new instrument declares (at most) its role's hooks in bench/runtime/polls.py; the engine
    iterates the rig's polls and names no polled quantity or recording rate itself."""
    from bench.runtime.polls import COLLECT, FETCH, ROLES

    engine = (ROOT / "bench" / "runtime" / "engine.py").read_text(encoding="utf-8")
    for rate in ("monitors_Hz", "position_Hz", "force_Hz", "PASSIVE_LASER_HZ", "FETCH_PERIOD_S", "SENSOR_PERIOD_S"):
        assert rate not in engine, rate
    assert "rig_polls(self.ctx)" in engine
    names = [p.name for p in ROLES.values()] + [FETCH.name, COLLECT.name]
    assert len(set(names)) == len(names) and {"monitors", "position", "force", "laser"} <= set(names)


def test_protocol_compilation_reaches_no_driver_even_through_the_rig_file() -> None:
    """bench/protocol imports bench.rig (the rig file); that module takes no driver table either."""
    found = [m for m in imported_modules(ROOT / "bench" / "rig.py") if m == "drivers" or m.startswith("drivers.")]
    assert not found, found


def module_graph(packages: tuple[str, ...]) -> dict[str, set[str]]:
    """The import graph by module of the given packages (``bench.runtime``, …): a node per source file, an edge for
    every import of another module of them in any form — at the top, under ``if TYPE_CHECKING:``, inside a
    function, relative. ``from bench.x import name`` counts as an import of ``bench.x`` (or of ``bench.x.name``
    when that is a module)."""
    files = {".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): p
             for pkg in packages for p in sorted((ROOT / pkg.replace(".", "/")).rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for mod, path in files.items():
        graph[mod] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = (node.module or "") if node.level == 0 else ".".join(
                    [*mod.split(".")[: len(mod.split(".")) - node.level + (path.name == "__init__.py")],
                     *([node.module] if node.module else [])])
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            graph[mod].update(t for t in targets if t in files and t != mod)
    return graph


def cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of the graph (its modules, first one repeated at the end), or None."""
    done: set[str] = set()

    def visit(node: str, path: list[str]) -> list[str] | None:
        if node in path:
            return [*path[path.index(node):], node]
        if node in done:
            return None
        for nxt in sorted(graph.get(node, ())):
            if (found := visit(nxt, [*path, node])) is not None:
                return found
        done.add(node)
        return None

    for start in sorted(graph):
        if (found := visit(start, [])) is not None:
            return found
    return None


@pytest.mark.parametrize("packages", [("bench.runtime", "bench.storage", "bench.protocol", "bench.core"), ("drivers",)])
def test_no_module_imports_itself_back_in_any_form(packages: tuple[str, ...]) -> None:
    """Issue 22: no cycle between the modules of the run time, storage, protocol compilation, the core and the
    drivers — including imports under ``TYPE_CHECKING`` and inside functions, which hide a cycle from Python
    but not from a reader."""
    graph = module_graph(packages)
    assert "bench.runtime.engine" in graph or "drivers.labjack" in graph
    assert cycle(graph) is None, " → ".join(cycle(graph) or [])


def test_the_module_cycle_check_sees_hidden_imports(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The checker itself: a cycle made only of a ``TYPE_CHECKING`` import one way and an in-function import the
    other way is found."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("", encoding="utf-8")
    (pkg / "a.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.b import B\n",
                              encoding="utf-8")
    (pkg / "b.py").write_text("class B:\n    def f(self):\n        from . import a\n", encoding="utf-8")
    monkeypatch.setattr(f"{__name__}.ROOT", tmp_path)
    assert module_graph(("pkg",)) == {"pkg": set(), "pkg.a": {"pkg.b"}, "pkg.b": {"pkg.a"}}
    assert cycle(module_graph(("pkg",))) == ["pkg.a", "pkg.b", "pkg.a"]


def foreign_privates(source: str) -> list[str]:
    """``x._name`` in a source where ``x`` is not ``self`` or ``cls`` ("line: expression"): a read or write of
    another object's private member (dunders excepted)."""
    return [f"{node.lineno}: {ast.unparse(node)}" for node in ast.walk(ast.parse(source))
            if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
            and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))]


@pytest.mark.parametrize("name", ["engine", "context", "polls", "hardware_timed"])
def test_the_run_time_core_reads_no_other_objects_private_members(name: str) -> None:
    """Issue 22: the engine, its run context, the polls and the hardware-timed path share state through the run
    context's public members, not through one another's private ones."""
    found = foreign_privates((ROOT / "bench" / "runtime" / f"{name}.py").read_text(encoding="utf-8"))
    assert not found, (name, found)


def test_the_private_member_check_finds_one() -> None:
    """The checker itself: a write through another object is found; the object's own members and dunders are not."""
    assert foreign_privates("def f(e):\n    e._t0 = 1\n    return self._ok, e.__class__\n") == ["2: e._t0"]


def test_the_numbers_module_the_core_may_use_imports_nothing_of_the_application() -> None:
    """bench/numbers.py is allowed to the core (its field messages) because it is a leaf: standard library only."""
    tree = ast.parse((ROOT / "bench" / "numbers.py").read_text(encoding="utf-8"))
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert set(names) <= {"__future__", "math"}, names
