"""Campaign fits, the search's per-record costs and design maps on a real multi-process dask cluster give the
in-process results, bit for bit (and the per-record costs those of the whole prediction, up to the sums' order).

The module starts a scheduler and two single-threaded workers, each its own process (`python -m
distributed.cli.dask_scheduler` / `dask_worker`) on loopback with a free port, fits through
``scheduler="tcp://127.0.0.1:PORT"`` (the API and `bench fit --scheduler`), shuts the cluster down and checks that
every process exited 0 with no traceback or error on its output, nor on this process's dask log.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.design_map import MapSettings, compute_map
from bench.identify.core import Cost, FitSettings, fit
from bench.identify.distributed import cluster_client, kernel_ready, tiles
from bench.identify.problems import MembraneProblem
from bench.runtime.run import run_protocol

pytest.importorskip("distributed")
ROOT = Path(__file__).resolve().parent.parent
SHORT = ROOT / "protocols" / "short"


@dataclass
class Cluster:
    address: str  # tcp://127.0.0.1:PORT
    processes: dict[str, subprocess.Popen[bytes]]  # scheduler, worker-0, worker-1
    logs: Path


def _start(logs: Path, name: str, *args: str) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    with (logs / f"{name}.log").open("wb") as out:  # stdout and stderr together
        return subprocess.Popen([sys.executable, "-m", *args], stdout=out, stderr=subprocess.STDOUT, env=env,
                                cwd=ROOT)


def _address(file: Path, processes: dict[str, subprocess.Popen[bytes]], timeout: float = 60.0) -> str:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if file.exists():
            try:
                return str(json.loads(file.read_text())["address"])
            except (ValueError, KeyError):  # being written
                pass
        assert processes["scheduler"].poll() is None, "the scheduler exited before it wrote its address"
        time.sleep(0.05)
    raise TimeoutError("the scheduler wrote no address")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """A scheduler and two `--nthreads 1` workers, three processes on 127.0.0.1; shut down through the scheduler at
    the end (workers, then the scheduler), then every process's exit and output checked (and this process's dask
    log)."""
    from distributed import Client

    logs = tmp_path_factory.mktemp("cluster")
    file = logs / "scheduler.json"
    ours: list[logging.LogRecord] = []
    catch = logging.Handler(logging.WARNING)
    catch.emit = ours.append  # type: ignore[method-assign]
    logging.getLogger("distributed").addHandler(catch)
    processes = {"scheduler": _start(logs, "scheduler", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                                     "--port", "0", "--no-dashboard", "--dashboard-address", "127.0.0.1:0",
                                     "--scheduler-file", str(file))}
    try:
        address = _address(file, processes)
        assert address.startswith("tcp://127.0.0.1:")
        for k in range(2):
            processes[f"worker-{k}"] = _start(logs, f"worker-{k}", "distributed.cli.dask_worker", address,
                                              "--nthreads", "1", "--no-nanny", "--no-dashboard", "--host", "127.0.0.1",
                                              "--preload", "bench.identify.worker_plugins")  # README
        with Client(address) as client:
            client.wait_for_workers(2, timeout=60)
        yield Cluster(address, processes, logs)
        with Client(address) as client:  # the workers first (the scheduler closing first cuts their streams)
            client.retire_workers(close_workers=True)
            codes = {name: p.wait(timeout=30) for name, p in processes.items() if name != "scheduler"}
            client.shutdown()
        codes["scheduler"] = processes["scheduler"].wait(timeout=30)
    finally:
        for p in processes.values():
            if p.poll() is None:
                p.kill()
                p.wait()
        logging.getLogger("distributed").removeHandler(catch)
    assert codes == dict.fromkeys(processes, 0)
    for name in processes:
        text = (logs / f"{name}.log").read_text(errors="replace")
        assert "Traceback" not in text and " - ERROR - " not in text, f"{name}:\n{text}"
    assert not [r for r in ours if r.levelno >= logging.ERROR or r.exc_info], [r.getMessage() for r in ours]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    tmp = tmp_path_factory.mktemp("runs")
    out = []
    for name in ("thesis-sweeps-short.toml", "thesis-identification-short.toml"):
        res = run_protocol(SHORT / name, virtual=True, out=tmp / f"{Path(name).stem}.h5")
        assert res.state == "completed", res.reason
        out.append(Path(res.path))
    return out


def _lm_steps(problem: MembraneProblem, z: np.ndarray) -> tuple[np.ndarray, int]:
    """Two batched Levenberg–Marquardt iterations of the intervals (two rows, one with a column held) from z:
    the rows and their χ², and the evaluations they made."""
    from bench.identify.core import sigma_of
    from bench.identify.trust import Weighted, _lm

    w = Weighted(problem.predict, problem.data, sigma_of(problem))
    lo, hi = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    free = np.arange(z.size)
    out = _lm(w, np.vstack([z, z]), free, np.array([-1, 0]), lo, hi, 1e-4 * (hi - lo), 2, 0.0)
    return out, w.evaluations


def test_campaign_fit_on_a_real_cluster_equals_the_in_process_fit(runs: list[Path], cluster: Cluster) -> None:
    # a short polish keeps it cheap; every Jacobian of it is a batch on the cluster all the same
    settings = FitSettings(population=12, generations=3, polish_iterations=3)
    local = fit(MembraneProblem(runs), settings, fine=MembraneProblem(runs, h=1e-4))
    coarse, fine = MembraneProblem(runs), MembraneProblem(runs, h=1e-4)
    with cluster_client(scheduler=cluster.address) as client:
        coarse.distribute(client)
        fine.distribute(client)
        # every worker has the kernel loaded before the first batch (a cold one would hold up the batch; the first
        # test on the module's cluster, so its workers start cold)
        assert set(client.run(kernel_ready).values()) == {True}
        remote = fit(coarse, settings, fine=fine)
        assert coarse.remote is not None and fine.remote is not None
        on_cluster = coarse.remote.evaluations + fine.remote.evaluations
        # the intervals' batched Levenberg–Marquardt (trust.py) evaluates through the same predict
        before = coarse.remote.evaluations
        assert remote.z is not None
        lm_remote, lm_evaluations = _lm_steps(coarse, remote.z)
        assert coarse.remote.evaluations - before == lm_evaluations > 0
        coarse.distribute(None)
        fine.distribute(None)
    np.testing.assert_array_equal(lm_remote, _lm_steps(coarse, remote.z)[0])
    assert len(coarse.records) == 2
    np.testing.assert_array_equal(remote.values, local.values)
    assert remote.cost == local.cost and remote.evaluations == local.evaluations
    np.testing.assert_array_equal(remote.sensitivity, local.sensitivity)
    # every evaluation went through the cluster: the search's generations, the polish's Jacobians (and the
    # intervals' batches above)
    assert on_cluster == remote.evaluations > settings.population * (settings.generations + 1)


def test_bench_fit_with_a_scheduler_equals_the_in_process_fit(runs: list[Path], cluster: Cluster) -> None:
    settings = FitSettings(population=12, generations=3, polish=False)
    local = fit(MembraneProblem(runs), settings, fine=MembraneProblem(runs, h=1e-4))
    res = CliRunner().invoke(app, ["fit", *map(str, runs), "--population", "12", "--generations", "3", "--no-polish",
                                   "--starts", "1", "--no-intervals", "--scheduler", cluster.address, "--json"])
    assert res.exit_code == 0, res.output
    values = [p["value"] for p in json.loads(res.stdout)["parameters"]]
    assert values == local.values.tolist()  # JSON floats round-trip exactly


def test_design_map_on_a_real_cluster_equals_the_in_process_map(cluster: Cluster) -> None:
    s = MapSettings(lambda2p=(2.5, 2.75, 3.0), xp=(0.035, 0.040))
    reported: list[float] = []
    with cluster_client(scheduler=cluster.address) as client:
        a, b = compute_map(s), compute_map(s, client=client, progress=reported.append)
    assert sorted(reported) == reported and reported[-1] == 1.0 and len(reported) == 3  # one report per row done
    np.testing.assert_array_equal(a.min_stiffness(), b.min_stiffness())
    np.testing.assert_array_equal(a.design(3.0, 0.040).force, b.design(3.0, 0.040).force)


KINDS: tuple[Cost, ...] = ("sae", "lsq")


def _candidates(problem: MembraneProblem) -> np.ndarray:
    """24 candidates drawn in the bounds; with this seed two of them (rows 0 and 20) fail in the model."""
    lo, hi = problem.lower, problem.upper
    Z: np.ndarray = lo + (hi - lo) * np.random.default_rng(3).random((24, lo.size))
    return Z


def _plain_costs(pred: np.ndarray, data: np.ndarray, sigma: np.ndarray, kind: str) -> np.ndarray:
    """The search's cost the plain way: numpy over the whole prediction, inf where a compared residual is not
    finite."""
    r = ((pred - data) / sigma)[:, np.isfinite(data)]
    c: np.ndarray = np.sum(np.abs(r), axis=1) if kind == "sae" else np.sum(r**2, axis=1)
    c[~np.all(np.isfinite(r), axis=1)] = np.inf
    return c


def test_per_record_costs_agree_with_the_costs_of_the_whole_prediction(runs: list[Path]) -> None:
    from bench.identify.core import sigma_of

    problem = MembraneProblem(runs)
    Z = _candidates(problem)
    pred = problem.predict(Z)
    compared = np.isfinite(problem.data)
    assert len(problem.records) == 2 and not compared.all()  # some data points are not compared
    failed = ~np.all(np.isfinite(pred[:, compared]), axis=1)
    assert 0 < failed.sum() < len(Z)
    for kind in KINDS:
        plain = _plain_costs(pred, problem.data, sigma_of(problem), kind)
        costs = problem.costs(Z, kind)
        np.testing.assert_array_equal(np.isinf(costs), failed)
        np.testing.assert_allclose(costs[~failed], plain[~failed], rtol=1e-12)  # the same sums in another order


def test_distributed_costs_equal_the_in_process_costs(runs: list[Path], cluster: Cluster) -> None:
    problem = MembraneProblem(runs)
    Z = _candidates(problem)
    local = {kind: problem.costs(Z, kind) for kind in KINDS}
    with cluster_client(scheduler=cluster.address) as client:
        problem.distribute(client)
        assert problem.remote is not None
        # planned for 4 threads: the first record is cut along its candidates (16 + 8), the second is not
        problem.remote.threads = 4
        assert sorted(t for t in tiles(len(Z), problem.remote.steps, 4) if t[0] == 0) == [(0, 1, 0, 16),
                                                                                      (0, 1, 16, 24)]
        remote = {kind: problem.costs(Z, kind) for kind in KINDS}
        assert problem.remote.evaluations == 2 * len(Z)
        problem.distribute(None)
    for kind in local:
        assert np.isinf(local[kind]).sum() == 2
        np.testing.assert_array_equal(remote[kind], local[kind])


def test_a_record_cut_unevenly_gives_the_same_bits(runs: list[Path], cluster: Cluster,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """Planned for 5 worker threads, 50 candidates (7 registers) over the two records: the longer record is cut
    3 + 3 + 1 registers (24 + 24 + 2 sets, a chunk peeled off an even cut), the other 4 + 3; the predictions and
    costs are the in-process ones, bit for bit (each candidate's lanes are its own)."""
    problem = MembraneProblem(runs)
    lo, hi = problem.lower, problem.upper
    Z = lo + (hi - lo) * np.random.default_rng(5).random((50, lo.size))
    local = {kind: problem.costs(Z, kind) for kind in KINDS}
    local_pred = problem.predict(Z)
    with cluster_client(scheduler=cluster.address) as client:
        problem.distribute(client)
        remote = problem.remote
        assert remote is not None
        five = [(address, k) for address, _ in remote.slots() for k in range(3)][:5]
        monkeypatch.setattr(remote, "slots", lambda: five)
        plan = tiles(len(Z), remote.steps, 5)
        assert sorted(b - a for r, _, a, b in plan if r == 0) == [2, 24, 24]
        assert sorted(b - a for r, _, a, b in plan if r == 1) == [18, 32]
        got = {kind: problem.costs(Z, kind) for kind in KINDS}
        pred = problem.predict(Z)
        problem.distribute(None)
    for kind in KINDS:
        np.testing.assert_array_equal(got[kind], local[kind])
    np.testing.assert_array_equal(pred, local_pred)


def test_one_worker_thread_gets_a_batch_as_one_task_and_the_same_bits(runs: list[Path], cluster: Cluster,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """With one worker thread known, a batch's tiles (one per record here) go as one task, run one after the other
    there (no scheduler round trip between them); the costs and the predictions are the in-process ones, bit for
    bit."""
    problem = MembraneProblem(runs)
    Z = _candidates(problem)
    local = {kind: problem.costs(Z, kind) for kind in KINDS}
    local_pred = problem.predict(Z)
    with cluster_client(scheduler=cluster.address) as client:
        problem.distribute(client)
        remote = problem.remote
        assert remote is not None and len(remote.slots()) == 2
        assert len(tiles(len(Z), remote.steps, 1)) == 2  # the batch has two tiles
        one = remote.slots()[:1]
        monkeypatch.setattr(remote, "slots", lambda: one)
        submitted: list[object] = []
        submit = client.submit

        def counted(func: object, *args: object, **kwargs: object) -> object:
            submitted.append(func)
            return submit(func, *args, **kwargs)

        monkeypatch.setattr(client, "submit", counted)
        got = {kind: problem.costs(Z, kind) for kind in KINDS}
        pred = problem.predict(Z)
        problem.distribute(None)
    assert len(submitted) == len(KINDS) + 1  # one task a batch
    for kind in KINDS:
        np.testing.assert_array_equal(got[kind], local[kind])
    np.testing.assert_array_equal(pred, local_pred)


def test_a_closing_workers_failed_heartbeat_is_dropped_and_a_running_ones_kept() -> None:
    """dask logs a heartbeat cut by the worker's own close as an ERROR with a traceback (seen at the end of a
    16-worker LocalCluster); the filter drops only that record, and only while its worker closes."""
    import inspect

    from distributed import Worker
    from distributed.core import Status

    from bench.identify.worker_plugins import HEARTBEAT_FAILED, ClosingHeartbeatFilter

    # the message is dask's own (its source), not ours
    assert f'"{HEARTBEAT_FAILED}.' in inspect.getsource(Worker.heartbeat)

    class FakeWorker:
        status = Status.running

    worker = FakeWorker()
    keep = ClosingHeartbeatFilter(worker)
    log = logging.getLogger("distributed.worker")
    try:
        raise OSError("Stream is closed")
    except OSError:
        exc = sys.exc_info()
    failed = log.makeRecord(log.name, logging.ERROR, __file__, 1, HEARTBEAT_FAILED + ".", (), exc)
    other = log.makeRecord(log.name, logging.ERROR, __file__, 1, "Unexpected exception during heartbeat.", (), exc)
    assert keep.filter(failed) and keep.filter(other)  # running: a scheduler really lost
    for status in (Status.closing, Status.closed):
        worker.status = status
        assert not keep.filter(failed), status
        assert keep.filter(other), status
    worker.status = Status.closing_gracefully  # retiring: still running, a lost scheduler still logs
    assert keep.filter(failed)
    worker.status = Status.closed
    del worker
    assert not keep.filter(failed)  # the worker is gone: its heartbeat cannot matter
    assert keep.filter(other)


def test_a_task_cancelled_by_a_closing_worker_is_not_logged_and_one_of_a_running_worker_is() -> None:
    """A Ctrl-C while `--workers`' processes warmed up left one dask WARNING per worker ("Async instruction for
    <Task …> ended with CancelledError") under the fit's one line; dropped while its worker closes (the only place
    dask's source says it happens), kept otherwise."""
    import inspect

    from distributed.core import Status
    from distributed.worker_state_machine import BaseWorker

    from bench.identify.worker_plugins import CANCELLED_ON_CLOSE, CancelledOnCloseFilter, QuietClosingHeartbeat

    source = inspect.getsource(BaseWorker._finish_async_instruction)  # dask's own message, not ours
    assert 'f"' + CANCELLED_ON_CLOSE[0] + "{task}" + CANCELLED_ON_CLOSE[1] + '"' in source

    class FakeWorker:
        status = Status.running

    worker = FakeWorker()
    log = logging.getLogger("distributed.worker.state_machine")  # the logger it is logged to
    assert QuietClosingHeartbeat.loggers[log.name] is CancelledOnCloseFilter
    keep = CancelledOnCloseFilter(worker)
    text = "Async instruction for <Task cancelled name=\"execute('_warm-1')\"> ended with CancelledError"
    cancelled = log.makeRecord(log.name, logging.WARNING, __file__, 1, text, (), None)
    other = log.makeRecord(log.name, logging.WARNING, __file__, 1, "Async instruction for <Task> ended", (), None)
    assert keep.filter(cancelled) and keep.filter(other)
    for status in (Status.closing, Status.closed):
        worker.status = status
        assert not keep.filter(cancelled) and keep.filter(other), status


def test_an_unretrieved_allexit_of_a_closing_client_is_not_logged_and_another_exception_is(
        caplog: pytest.LogCaptureFixture) -> None:
    """A Ctrl-C during `--workers`' polish printed two asyncio "Task exception was never retrieved" tracebacks of
    dask's AllExit (its client's sentinel for gathers cut by its close) above the fit's one line (outside tester).
    The cluster's client drops those; any other unretrieved exception still logs."""
    import asyncio
    import gc

    from distributed.client import AllExit

    from bench.identify.distributed import _quiet_all_exit

    _quiet_all_exit()

    async def fail(exc: Exception) -> None:
        raise exc

    def unretrieved(exc: Exception) -> None:
        loop = asyncio.new_event_loop()
        try:
            task = loop.create_task(fail(exc))
            loop.run_until_complete(asyncio.sleep(0))  # the task runs to its exception, which nobody retrieves
            del task
            gc.collect()  # asyncio logs it when the task is collected
        finally:
            loop.close()

    with caplog.at_level(logging.ERROR, logger="asyncio"):
        unretrieved(AllExit())
        unretrieved(RuntimeError("a real failure"))
    logged = [r for r in caplog.records if "exception was never retrieved" in r.getMessage()]
    assert [r.exc_info[0] for r in logged if r.exc_info] == [RuntimeError], logged


def test_a_ctrl_c_while_the_cluster_starts_is_taken_once_it_is_up() -> None:
    """The cluster's workers are spawned with SIGINT kept from them; it was ignored in this process meanwhile, so a
    Ctrl-C while the cluster started (several seconds) was lost and the fit ran to its end (on a loaded machine:
    2 minutes, stored). Blocked instead (in the thread that spawns them): the signal is taken once the cluster is
    up (sent to the main thread here: a signal to the process may be taken at once by another of its threads, as
    the fit's progress bar's, which is as good), never lost."""
    import signal

    from bench.identify.distributed import _sigint_ignored_in_children

    assert threading.current_thread() is threading.main_thread()  # (pytest's, and xdist's workers': the signals')
    got: list[int] = []
    before = signal.signal(signal.SIGINT, lambda sig, _frame: got.append(sig))
    try:
        with _sigint_ignored_in_children():
            signal.pthread_kill(threading.main_thread().ident or 0, signal.SIGINT)  # to this thread: what it blocks
            for _ in range(1000):  # bytecodes at which a handler could run
                pass
        for _ in range(1000):
            pass
        assert got == [signal.SIGINT]
    finally:
        signal.signal(signal.SIGINT, before)


def test_workers_of_a_cluster_of_ones_own_carry_the_filter_through_the_preload(cluster: Cluster) -> None:
    """The README's `dask worker --preload bench.identify.worker_plugins`: the fixture's two worker processes carry
    the closing-heartbeat filter once each (the fixture then checks their logs for a traceback at the close)."""
    from distributed import Client

    from bench.identify.worker_plugins import ClosingHeartbeatFilter

    def installed() -> int:
        return sum(isinstance(f, ClosingHeartbeatFilter) for f in logging.getLogger("distributed.worker").filters)

    with Client(cluster.address) as client:
        assert sorted(client.run(installed).values()) == [1, 1]


def test_the_workers_of_our_local_cluster_carry_the_filter_and_close_without_a_traceback(
        capfd: pytest.CaptureFixture[str]) -> None:
    """Also: their malloc reuses a freed buffer. Dask's nannies set MALLOC_TRIM_THRESHOLD_, which switches off
    glibc's sliding mmap threshold (mallopt(3)), so each tile's few-MB buffers were mapped afresh and every page
    faulted in again. 40 rounds of a freed 4-MiB buffer (1,024 pages of 4 KiB) fault tens of thousands of times
    that way, each round mapping it afresh; reused, a buffer's worth at most."""
    from bench.identify.worker_plugins import ClosingHeartbeatFilter

    def installed() -> int:
        return sum(isinstance(f, ClosingHeartbeatFilter) for f in logging.getLogger("distributed.worker").filters)

    def faults_of_40_buffers() -> int:
        import resource

        import numpy

        numpy.ones(1 << 19).sum()  # the first buffer may fault in: not counted
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(40):
            numpy.ones(1 << 19).sum()  # 4 MiB, written, freed
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

    from bench.identify.distributed import _AllExitFilter

    with cluster_client(workers=2) as client:
        assert client is not None
        client.wait_for_workers(2, timeout=60)
        assert sorted(client.run(installed).values()) == [1, 1]
        # this process's asyncio logger drops the AllExit of gathers the client's close cuts (once, however often)
        assert sum(isinstance(f, _AllExitFilter) for f in logging.getLogger("asyncio").filters) == 1
        # a terminal's Ctrl-C reaches them too (the process group): they keep it from themselves, and stay up
        pids = client.run(os.getpid)
        for pid in pids.values():
            os.kill(pid, signal.SIGINT)
        time.sleep(0.5)  # (taken, a worker would be dying or restarted by now: an order, not a bound)
        assert client.run(os.getpid) == pids
        if sys.platform.startswith("linux"):  # glibc's malloc (the CI's and the lab PCs' Linux)
            faults = client.run(faults_of_40_buffers)
            assert max(faults.values()) < 4 * 1024, faults  # a few buffers' worth, not 40
    err = capfd.readouterr().err  # the worker processes write to this process's stderr
    assert "Traceback" not in err and " - ERROR - " not in err, err
