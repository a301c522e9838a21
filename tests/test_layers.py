"""Import direction between the packages (the layers of docs and README "Layout"), checked on the source.

drivers/ speak wire protocols and know nothing of the application or the twins; sim_devices/ are written from the
manuals and never take a driver's protocol constants. (The rule for bench.protocol — no twins, no driver
constants — is the next step of the architecture issue and is not enforced yet.)
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import ROOT


def imported_modules(path: Path) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
    return out


@pytest.mark.parametrize("package, forbidden", [
    ("drivers", ("bench", "sim_devices")),
    ("sim_devices", ("drivers",)),
])
def test_no_import_goes_up_or_across_the_layers(package: str, forbidden: tuple[str, ...]) -> None:
    offenders = [f"{path.relative_to(ROOT)} imports {mod}"
                 for path in sorted((ROOT / package).rglob("*.py"))
                 for mod in imported_modules(path) if mod.split(".")[0] in forbidden]
    assert not offenders, offenders
