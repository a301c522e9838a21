"""Campaign fits and design maps on a dask.distributed LocalCluster give the in-process results, bit for bit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.design_map import MapSettings, compute_map
from bench.identify.core import FitSettings, fit
from bench.identify.distributed import cluster_client
from bench.identify.problems import MembraneProblem
from bench.runtime.run import run_protocol

pytest.importorskip("distributed")
SHORT = Path(__file__).resolve().parent.parent / "protocols" / "short"


@pytest.fixture(scope="module")
def client():
    with cluster_client(workers=2) as c:
        yield c


def test_campaign_fit_on_a_local_cluster_equals_the_in_process_fit(tmp_path: Path, client) -> None:
    paths = []
    for name in ("thesis-sweeps-short.toml", "thesis-identification-short.toml"):
        res = run_protocol(SHORT / name, virtual=True, out=tmp_path / f"{Path(name).stem}.h5")
        assert res.state == "completed", res.reason
        paths.append(res.path)
    settings = FitSettings(population=12, generations=3)
    local = fit(MembraneProblem(paths), settings, fine=MembraneProblem(paths, h=1e-4))
    coarse, fine = MembraneProblem(paths), MembraneProblem(paths, h=1e-4)
    coarse.distribute(client)
    fine.distribute(client)
    remote = fit(coarse, settings, fine=fine)
    assert len(coarse.records) == 2
    np.testing.assert_array_equal(remote.values, local.values)
    assert remote.cost == local.cost and remote.evaluations == local.evaluations
    np.testing.assert_array_equal(remote.sensitivity, local.sensitivity)


def test_design_map_on_a_local_cluster_equals_the_in_process_map(client) -> None:
    s = MapSettings(lambda2p=(2.5, 2.75, 3.0), xp=(0.035, 0.040))
    reported: list[float] = []
    a, b = compute_map(s), compute_map(s, client=client, progress=reported.append)
    assert sorted(reported) == reported and reported[-1] == 1.0 and len(reported) == 3  # one report per row done
    np.testing.assert_array_equal(a.min_stiffness(), b.min_stiffness())
    np.testing.assert_array_equal(a.design(3.0, 0.040).force, b.design(3.0, 0.040).force)
