"""Shared by the run-catalogue tests (tests/test_catalog.py, tests/test_catalog_rows.py; two files so that the two
test workers can share them): a temporary PostgreSQL server, the catalogue on each backend, the CLI as a process or
in this process, and the specimen statistics computed here from a run file with h5py."""

from __future__ import annotations

import glob
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.conftest import ROOT

sa = pytest.importorskip("sqlalchemy")

from bench.storage.catalog import COLUMNS, Catalog, row_from_attrs  # noqa: E402,F401

SHORT = ROOT / "protocols" / "short"
SWEEPS = SHORT / "thesis-sweeps-short.toml"  # 5 kV then 7 kV, raised cosine at 1/3 Hz, on the DAQ rig
IDENT = SHORT / "thesis-identification-short.toml"  # 7 kV raised cosine at 1/9 Hz for 10 s, then 1 s at rest
THRESHOLD_V = 500.0  # the threshold README and `bench specimen show` state
SPECIMEN = "S7"


def _env(state: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "BENCH_CATALOG"}
    return {**env, "PYTHONPATH": str(ROOT), "COLUMNS": "200", "BENCH_STATE_DIR": str(state)}


def _bench(*args: str, env: dict[str, str], timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)


def _bench_here(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """The same command in this process (typer's runner, the environment ``env`` set for the call): for a test's
    further calls once one has gone through ``python -m bench``, without a Python start-up and its imports each.
    An exception the command lets out is a traceback on stderr, as it would be from the process."""
    import traceback

    from typer.testing import CliRunner

    from bench.cli import app

    res = CliRunner().invoke(app, list(args), env={**env, "BENCH_CATALOG": env.get("BENCH_CATALOG")})
    err = res.stderr
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        err += "".join(traceback.format_exception(res.exception))
    return subprocess.CompletedProcess(["bench", *args], res.exit_code, res.stdout, err)


# ---- a real PostgreSQL server ---------------------------------------------------------------------------------------


def _pg_bin(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    cands = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
    return cands[-1] if cands else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def pg_server() -> Iterator[str]:
    """A temporary PostgreSQL cluster (initdb, pg_ctl) on a free port; yields a server URL without database.
    As root the server runs as ``nobody`` (PostgreSQL refuses to run as root)."""
    initdb, pg_ctl = _pg_bin("initdb"), _pg_bin("pg_ctl")
    if initdb is None or pg_ctl is None:
        pytest.skip("PostgreSQL server binaries (initdb, pg_ctl) not installed: apt-get install postgresql")
    pytest.importorskip("psycopg")
    base = Path(tempfile.mkdtemp(prefix="bench-pg-"))
    data = base / "data"
    as_user: list[str] = []
    if os.geteuid() == 0:
        runuser = shutil.which("runuser")
        if runuser is None:
            pytest.skip("running as root without runuser: cannot start PostgreSQL as another user")
        as_user = [runuser, "-u", "nobody", "--"]
        os.chmod(base, 0o755)
        shutil.chown(base, "nobody")
    port = _free_port()
    env = {**os.environ, "LC_ALL": "C"}
    try:
        subprocess.run([*as_user, initdb, "-D", str(data), "-U", "bench", "--auth=trust", "-E", "UTF8"], check=True,
                       capture_output=True, env=env, cwd=base, timeout=120)
        opts = f"-p {port} -k {base} -c listen_addresses=127.0.0.1 -c fsync=off"
        subprocess.run([*as_user, pg_ctl, "-D", str(data), "-o", opts, "-l", str(base / "log"), "-w", "-t", "60",
                        "start"], check=True, capture_output=True, env=env, cwd=base, timeout=120)
    except subprocess.CalledProcessError as exc:
        shutil.rmtree(base, ignore_errors=True)
        raise AssertionError(f"PostgreSQL did not start: {exc.stderr!r}") from None
    try:
        yield f"postgresql+psycopg://bench@127.0.0.1:{port}"
    finally:
        subprocess.run([*as_user, pg_ctl, "-D", str(data), "-m", "immediate", "-w", "stop"], capture_output=True,
                       env=env, cwd=base, timeout=120)
        shutil.rmtree(base, ignore_errors=True)


_DB_COUNT = [0]


def _new_pg_db(server: str) -> str:
    _DB_COUNT[0] += 1
    name = f"cat{os.getpid()}_{_DB_COUNT[0]}"
    engine = sa.create_engine(f"{server}/postgres", isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(sa.text(f"CREATE DATABASE {name}"))
    engine.dispose()
    return f"{server}/{name}"


@pytest.fixture(params=["sqlite", "postgresql"])
def catalog_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """An empty catalogue on each backend."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'other' / 'catalog.sqlite'}"
    return _new_pg_db(request.getfixturevalue("pg_server"))


# ---- the specimen's history, against numbers computed here from the files -------------------------------------------


def _measured(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with h5py.File(path, "r", libver="latest", swmr=True) as f:
        n = dict(zip(json.loads(f["status/samples"].attrs["names"]), f["status/samples"][:], strict=True))["amplifier"]
        return f["amplifier/t"][:n], np.abs(f["amplifier/voltage"][:n])


def _expected(path: Path) -> tuple[float, int, float]:
    """(time above the threshold, rises above it re-armed below half of it, peak |V|) by a plain loop."""
    t, v = _measured(path)
    hv, rises, armed = 0.0, 0, True
    for i in range(len(v)):
        if v[i] > THRESHOLD_V:
            if i + 1 < len(v):
                hv += t[i + 1] - t[i]
            if armed:
                rises, armed = rises + 1, False
        elif v[i] < THRESHOLD_V / 2:
            armed = True
    return hv, rises, float(v.max()) if v.size else 0.0
