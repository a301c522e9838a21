"""The compiled chain of go-tos plans the very profiles that :meth:`MotionProfile.plan` does one call at a time
from the state :meth:`MotionProfile.at` gives (what ``Plant.set_motion`` did per set-point tick), bit for bit."""

from __future__ import annotations

import numpy as np

from bench.core.motion import MotionProfile
from bench.core.motion_chain import chain


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float).view(np.uint64)


def _one_by_one(start: MotionProfile, t: np.ndarray, target: np.ndarray, vmax: np.ndarray,
                acc: np.ndarray) -> list[MotionProfile]:
    """The reference: the Python planner, one go-to after the other."""
    out, prof = [], start
    for tj, g, vm, a in zip(t.tolist(), target.tolist(), vmax.tolist(), acc.tolist(), strict=True):
        p, v = prof.at(tj)
        prof = MotionProfile.plan(tj, p, v, g, vm, a, a)
        out.append(prof)
    return out


def _assert_same(got: list[MotionProfile], want: list[MotionProfile]) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        for f in ("t_start", "p_start", "v_start", "acc"):
            assert np.array_equal(_bits(getattr(g, f)), _bits(getattr(w, f))), f
        assert (g.t_end, g.target) == (w.t_end, w.target)
        assert type(g.t_end) is float and type(g.target) is float


def test_streamed_go_tos_match_the_python_planner() -> None:
    """Go-tos every 10 ms, superseded mid-motion (towards, away from and past the target, above vmax)."""
    rng = np.random.default_rng(7)
    n = 3000
    t = np.cumsum(rng.choice([0.0, 0.01, 0.013, 0.25], n, p=[0.05, 0.6, 0.3, 0.05]))
    target = np.cumsum(rng.normal(0.0, 2e-3, n)) + rng.choice([0.0, 0.05], n, p=[0.95, 0.05])
    vmax = rng.choice([1e-4, 0.01, 0.05, 0.3, 1.0], n)
    acc = rng.choice([0.1, 1.0, 10.0], n)
    target[::97] = target[np.arange(0, n, 97) - 1]  # the same target again (no motion, or a stop)
    start = MotionProfile.plan(0.0, 0.01, -0.02, 0.03, 0.05, 1.0, 1.0)
    _assert_same(chain(start, t, target, vmax, acc), _one_by_one(start, t, target, vmax, acc))


def test_from_rest_and_a_single_go_to() -> None:
    start = MotionProfile.hold(0.0, 0.0)
    args = (np.array([0.5]), np.array([0.04]), np.array([0.05]), np.array([1.0]))
    _assert_same(chain(start, *args), _one_by_one(start, *args))
    args = (np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -0.0]), np.array([0.05] * 3), np.array([1.0] * 3))
    _assert_same(chain(start, *args), _one_by_one(start, *args))
