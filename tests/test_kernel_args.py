"""The compiled kernels see their arrays in one form (bench.models.kernel_args): a read-only array (a dask
worker's, a broadcast view), an F-ordered solver history or a strided slice costs no second compiled variant (the
batch kernels take 10-20 s to compile on the development machine, once per variant), and the values do not
depend on the form an array came in."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.models.kernel_args import kernel_array
from bench.models.lozenge import LozengeParams, lozenge_observe
from bench.models.lozenge_batch import _batch as lozenge_kernel
from bench.models.lozenge_batch import lozenge_batch
from bench.models.lozenge_runs import lozenge_outputs
from bench.models.membrane import MembraneParams, _any_failure, membrane_observe, membrane_outputs
from bench.models.membrane_batch import _batch as membrane_kernel
from bench.models.membrane_batch import membrane_batch_records


def _read_only(a: np.ndarray) -> np.ndarray:
    a = np.array(a)
    a.flags.writeable = False
    return a


def test_kernel_array_passes_a_c_float_array_through_and_copies_any_other_form() -> None:
    a = np.arange(12.0).reshape(3, 4)
    assert kernel_array(a) is a
    for other in (_read_only(a), np.asfortranarray(a), a[:, ::2], np.arange(12).reshape(3, 4)):
        b = kernel_array(other)
        assert b.flags.c_contiguous and b.flags.writeable and b.dtype == np.float64
        assert np.array_equal(b, other)
    row = kernel_array(np.array([0.0, 1.0]), (5, 2))
    assert row.shape == (5, 2) and row.flags.writeable and np.array_equal(row[4], [0.0, 1.0])


def test_arrays_of_any_form_compile_one_variant_of_each_batch_kernel_and_give_the_same_values() -> None:
    p = MembraneParams()
    P = np.tile(p.pack(), (3, 1))
    P[:, -1] *= np.array([0.9, 1.0, 1.1])  # three candidates
    U = np.column_stack([np.linspace(0.0, 2000.0, 300), np.full(300, 296.0)])
    y0 = p.initial_state()[None, :]
    cal = np.tile([[0.0, 1.0]], (1, 3, 1))
    want = membrane_batch_records(P, y0, [U], 1e-4, 10, 0, cal)
    for args in ((_read_only(P), _read_only(np.tile(y0[:, None, :], (1, 3, 1))), [_read_only(U)], _read_only(cal)),
                 (np.asfortranarray(P), y0, [np.asfortranarray(U)], np.broadcast_to(cal, (1, 3, 2)))):
        got = membrane_batch_records(args[0], args[1], args[2], 1e-4, 10, 0, args[3])
        assert np.array_equal(got, want, equal_nan=True)
    assert len(membrane_kernel.signatures) == 1

    q = LozengeParams()
    Q = np.tile(q.pack(), (2, 1))
    Y0 = np.tile(q.relaxed_state(q.xp), (2, 1))
    V = np.column_stack([np.linspace(0.0, 3000.0, 200), np.full(200, q.xp), np.zeros(200)])
    want = lozenge_batch(Q, Y0, V, 1e-4, -1, 10)
    got = lozenge_batch(_read_only(Q), _read_only(Y0), _read_only(V), 1e-4, -1, 10, _read_only(np.tile([0.0, 1.0],
                                                                                                        (2, 1))))
    assert np.array_equal(got, want, equal_nan=True)
    assert len(lozenge_kernel.signatures) == 1


def test_observables_compile_one_variant_whatever_form_the_history_and_inputs_come_in() -> None:
    p = MembraneParams()
    t = np.arange(50) * 1e-4
    Y = np.tile(p.initial_state(), (50, 1))
    phi = np.linspace(0.0, 3000.0, 50)
    want = membrane_outputs(p, t, Y, phi, 296.0)
    for got in (membrane_outputs(p, t, np.asfortranarray(Y), _read_only(phi), np.full(50, 296.0)),
                membrane_outputs(p, t, np.tile(p.initial_state(), (100, 1))[::2], phi, 296.0)):
        assert np.array_equal(got.field, want.field) and np.array_equal(got.current, want.current)
    assert len(membrane_observe.signatures) == 1 and len(_any_failure.signatures) == 1

    q = LozengeParams()
    Z = np.tile(q.relaxed_state(q.xp), (50, 1))
    first = lozenge_outputs(q, t, Z, phi)
    again = lozenge_outputs(q, t, np.asfortranarray(Z), _read_only(phi))
    assert np.array_equal(first.force, again.force)
    assert len(lozenge_observe.signatures) == 1


def test_a_daq_run_compiles_its_host_kernels_before_it_connects_and_no_other_variant(tmp_path: Path,
                                                                                      monkeypatch) -> None:
    """The host's kernels of a hardware-timed run (error diffusion, the reconstruction filter) are compiled before
    any instrument or twin runs, with the argument types the run passes: a first compile inside a wall-clock run
    holds the interpreter ~0.3 s while the twins' threads wait."""
    from bench.core.one_pole import one_pole
    from bench.runtime import hardware_timed
    from bench.runtime.run import execute, plan_run
    from tests.conftest import ROOT

    order: list[str] = []
    warm = hardware_timed.warm_up
    monkeypatch.setattr(hardware_timed, "warm_up", lambda: (order.append("warm"), warm())[1])
    from bench.runtime import sim_rig

    start = sim_rig.SimRig.start
    monkeypatch.setattr(sim_rig.SimRig, "start", lambda self: (order.append("twins"), start(self))[1])
    warm()
    before = (list(hardware_timed._diffuse.signatures), list(one_pole.signatures))
    plan = plan_run(ROOT / "protocols" / "short" / "thesis-identification-short.toml")
    assert plan.rig.daq is not None and plan.rig.daq.drive_filter_Hz is not None  # both kernels run in it
    result = execute(plan, tmp_path / "r.h5", virtual=True)
    assert result.state == "completed"
    assert order == ["warm", "twins"]
    assert (list(hardware_timed._diffuse.signatures), list(one_pole.signatures)) == before
