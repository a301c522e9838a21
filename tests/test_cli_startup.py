"""Fast start of the command line (issue 24): ``bench --help``, a command's ``--help`` and TAB completion load no
numerics (numpy, scipy, numba, h5py, matplotlib, dask) and none of bench's model, run-time, storage or
identification code (``bench --help`` not even rich's console); completion of protocol and rig files and of
shipped protocol names; the one-line refusal of ``--workers``/``--scheduler`` when dask.distributed (the
``cluster`` extra) is not installed.

What is loaded is read from ``sys.modules`` in a fresh interpreter: an order/count check, not a duration (the
start-up time against ``import typer, rich`` is a row of ``bench benchmark startup``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.cli.completion import protocol_files, protocol_names, rig_files
from tests.conftest import ROOT

# what `bench --help` must not load: third-party numerics and bench's heavy layers
HEAVY = ("numpy", "scipy", "numba", "h5py", "matplotlib", "dask", "distributed", "pint", "bench.models", "bench.core",
         "bench.runtime", "bench.storage", "bench.identify", "bench.analysis", "bench.protocol.schema",
         "bench.protocol.program", "sim_devices")

# run the app as `python -m bench ARGS` does, then print which of HEAVY were loaded (JSON, on the last line)
PROBE = """
import json, sys
from bench.cli import app
try:
    app(sys.argv[1:], prog_name="bench")
except SystemExit:
    pass
heavy = {heavy!r}
print(json.dumps(sorted(m for m in sys.modules if any(m == h or m.startswith(h + ".") for h in heavy))))
"""


def loaded(*args: str, env: dict[str, str] | None = None) -> tuple[list[str], str]:
    """(heavy modules loaded, stdout before the JSON line) of ``bench ARGS`` in a fresh interpreter."""
    res = subprocess.run([sys.executable, "-c", PROBE.format(heavy=HEAVY), *args], cwd=ROOT, capture_output=True,
                         text=True, env={**os.environ, **(env or {})}, timeout=60)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    out, _, last = res.stdout.rstrip("\n").rpartition("\n")
    return json.loads(last), out


def test_importing_the_command_line_loads_no_numerics_and_no_model() -> None:
    res = subprocess.run([sys.executable, "-c", "import json, sys, bench.cli; print(json.dumps(sorted(sys.modules)))"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    modules = json.loads(res.stdout)
    assert "bench.cli.analysis" in modules and "typer" in modules  # the probe sees what was imported
    assert [m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY)] == []


@pytest.mark.parametrize("args", [["--help"], ["fit", "--help"], ["run", "--help"], ["benchmark", "--help"],
                                  ["simulate", "thesis", "--help"], ["devices", "control", "--help"]])
def test_help_loads_no_numerics_and_no_model(args: list[str]) -> None:
    heavy, out = loaded(*args)
    assert "Usage" in out  # the help was printed
    assert heavy == []


def test_top_level_help_loads_no_rich_console() -> None:
    """typer prints ``bench --help`` without rich's console (rich_markup_mode=None): the command modules make their
    consoles on first print. (A command's help is parsed by typer, which loads rich itself.)"""
    code = ("import json, sys\nfrom bench.cli import app\ntry:\n    app(['--help'], prog_name='bench')\n"
            "except SystemExit:\n    pass\n"
            "print(json.dumps([m for m in ('rich.console', 'rich.table') if m in sys.modules]))")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "Usage" in res.stdout, res.stderr
    assert json.loads(res.stdout.strip().splitlines()[-1]) == []


@pytest.mark.parametrize(("words", "expected"), [
    # the shipped sweep over voltage (protocols/thesis-voltage-sweep.toml) is the only thesis-v… protocol
    ("bench protocols show thesis-v", ["thesis-voltage-sweep"]),
    # rigs/ holds thesis-sim.toml and thesis-daq-sim.toml; only the first starts so (a rig option of `bench run`)
    ("bench run protocols/thesis-identification.toml --rig rigs/thesis-s", ["rigs/thesis-sim.toml"]),
])
def test_tab_completion_loads_no_numerics_and_completes_names(words: str, expected: list[str]) -> None:
    """Through typer's completion protocol (the environment a shell's completion script sets)."""
    heavy, out = loaded(env={"_BENCH_COMPLETE": "complete_bash", "COMP_WORDS": words,
                             "COMP_CWORD": str(len(words.split()) - 1)})
    assert heavy == []
    assert out.split() == expected


def test_a_command_that_computes_still_loads_what_it_needs() -> None:
    """The probe itself: a command that simulates imports the models (lazily, inside the command)."""
    heavy, _ = loaded("simulate", "thesis", "--duration", "0.01")
    assert "numba" in heavy and "bench.models.membrane" in heavy


def _tree(tmp: Path) -> None:
    (tmp / "protocols").mkdir()
    (tmp / "rigs").mkdir()
    (tmp / ".hidden").mkdir()
    (tmp / "protocols" / "a.toml").write_text('# comment\n[protocol]\nname = "a"\n', encoding="utf-8")
    (tmp / "protocols" / "b.toml").write_text('[[steps]]\ntype = "hold"\n', encoding="utf-8")  # neither kind
    (tmp / "protocols" / "notes.txt").write_text("[protocol]\n", encoding="utf-8")
    (tmp / "rigs" / "r-sim.toml").write_text('name = "r"\n\n[specimen]\nkind = "membrane"\n', encoding="utf-8")
    (tmp / "p.toml").write_text("[protocol]\n", encoding="utf-8")


def test_file_completion_offers_folders_and_files_of_the_kind(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    _tree(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert protocol_files("") == ["p.toml", "protocols/", "rigs/"]  # no hidden folder unless typed
    assert protocol_files("protocols/") == ["protocols/a.toml"]
    assert rig_files("protocols/") == []
    assert rig_files("rigs/r") == ["rigs/r-sim.toml"]
    assert protocol_files(".h") == [".hidden/"]
    assert protocol_files(f"{tmp_path}/protocols/") == [f"{tmp_path}/protocols/a.toml"]
    assert protocol_files("missing/") == []


def test_name_completion_offers_the_shipped_protocols() -> None:
    # the repository's protocols/ folder is what the wheel ships (bench/data/protocols links to it)
    names = {p.relative_to(ROOT / "protocols").with_suffix("").as_posix()
             for p in (ROOT / "protocols").rglob("*.toml")}
    assert set(protocol_names("")) == names
    assert set(protocol_names("short/")) == {n for n in names if n.startswith("short/")} != set()


def test_cluster_options_without_dask_are_refused_in_one_line_naming_the_extra() -> None:
    """dask.distributed is the optional `cluster` extra: simulate its absence (None in sys.modules makes the
    import fail as an uninstalled package does) and ask for a local cluster."""
    code = ("import sys\nsys.modules['distributed'] = None\nsys.modules['dask'] = None\n"
            "from bench.cli import app\napp(sys.argv[1:], prog_name='bench')\n")
    res = subprocess.run([sys.executable, "-c", code, "design-map", "--workers", "2", "--voltages", "0"],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0 and "Traceback" not in res.stderr, res.stderr
    assert "pip install 'dea-bench[cluster]'" in res.stderr and "--workers" in res.stderr


def test_in_process_fits_need_no_dask(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without --workers/--scheduler the seam asks nothing of dask (the default install has no cluster extra)."""
    from bench.cli.common import cluster_client

    monkeypatch.setitem(sys.modules, "distributed", None)
    with cluster_client(None, None) as client:
        assert client is None
    with pytest.raises(ValueError, match=r"pip install 'dea-bench\[cluster\]'"), cluster_client("tcp://x:1", None):
        pass


def test_benchmark_help_lists_the_startup_set() -> None:
    res = CliRunner().invoke(app, ["benchmark", "--help"])
    assert res.exit_code == 0 and "startup" in res.output


def test_cluster_options_with_dask_installed_reach_the_cluster() -> None:
    """With the extra installed, the seam hands over a working client (a LocalCluster of one worker process),
    whose worker process samples no stacks (dask's profiler is on by default, dask's distributed.yaml)."""
    pytest.importorskip("distributed")
    import dask

    from bench.cli.common import cluster_client

    with cluster_client(None, 1) as client:
        assert client is not None
        assert client.submit(pow, 2, 10).result(timeout=60) == 1024
        settings = client.run(dask.config.get, "distributed.worker.profile.enabled")
        assert list(settings.values()) == [False]


def test_the_console_made_on_first_use_stands_for_the_bench_console() -> None:
    """The stand-in forwards attributes, assignments and ``with`` (rich's Live uses all three) to a BenchConsole:
    units in brackets stay text (bench/cli/console.py), quiet silences it, a ``with`` block prints at its end."""
    import io

    from bench.cli.common import _OnFirstUse

    out = io.StringIO()
    c = _OnFirstUse(file=out, width=80)
    with c:
        c.print("[bold]peak[/] 7.68 [mm]")
        assert out.getvalue() == ""  # buffered until the block ends
    assert out.getvalue() == "peak 7.68 [mm]\n"
    c.quiet = True
    c.print("not shown")
    assert out.getvalue() == "peak 7.68 [mm]\n" and c.quiet is True


def test_a_run_on_the_daq_rig_loads_no_scipy_signal_optimize_or_integrate(tmp_path: Path) -> None:
    """``bench run`` (plan, dry run, a virtual-time run on the hardware-timed rig with its reconstruction filter,
    file, catalogue) needs none of scipy's signal, optimize or integrate packages (0.4 s, 0.3 s and 0.1 s to import
    each); only fitting and the offline solver do."""
    probe = ("import json, sys\nfrom bench.cli import app\ntry:\n    app(sys.argv[1:], prog_name='bench')\n"
             "except SystemExit as e:\n    assert not e.code, e.code\n"
             "print(json.dumps(sorted(m for m in sys.modules if m.startswith('scipy.'))))")
    res = subprocess.run([sys.executable, "-c", probe, "run", "protocols/short/thesis-identification-short.toml",
                          "--virtual-time", "--no-live", "--yes", "--out", str(tmp_path)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300,
                         env={**os.environ, "BENCH_STATE_DIR": str(tmp_path / "state")})
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert list(tmp_path.glob("*.h5"))  # the run happened
    scipy = json.loads(res.stdout.rstrip("\n").rpartition("\n")[2])
    assert "scipy.linalg" in scipy  # the probe sees scipy's modules (numba loads linalg)
    assert [m for m in scipy if m.split(".")[1] in ("signal", "optimize", "integrate")] == []
