"""Import direction between the packages (docs/architecture.md), checked on the source.

drivers/ speak wire protocols and know nothing of the application or the twins; sim_devices/ are written from the
manuals and never take a driver's protocol constants; the core (bench/core: clock, motion profile, plant) and
protocol compilation (bench/protocol) know neither twins nor drivers, and the core needs nothing of the
application beyond the physical models. Every import counts, including those inside functions.
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
    ("sim_devices", ("drivers",), ()),
    ("bench/protocol", ("sim_devices", "drivers"), ()),
    ("bench/core", ("sim_devices", "drivers", "bench"), ("bench.core", "bench.models")),
])
def test_no_import_goes_up_or_across_the_layers(package: str, forbidden: tuple[str, ...],
                                                allowed: tuple[str, ...]) -> None:
    found = offenders(package, forbidden, allowed)
    assert not found, found


def test_the_check_sees_imports_inside_functions(tmp_path: Path) -> None:
    """The checker itself: a function-level import and a relative one are found (a lazy import counts too)."""
    src = tmp_path / "m.py"
    src.write_text("def f():\n    from sim_devices.rig import SimRig\n    import drivers.keyence\n", encoding="utf-8")
    assert imported_modules(src) >= {"sim_devices.rig", "drivers.keyence"}
    inside = ROOT / "bench" / "protocol" / "program.py"
    assert "bench.rig" in imported_modules(inside)
