"""Design map of the LS-DEA (Moretti et al., Fig. 2): force–displacement over pre-stretch λ2p and aperture xp.

For each design (λ2p, xp) of a grid, the static force F(x, V) = F_el(x) + F_es(x, V) (physics.md §2.1, eqs 4
and 6, relaxed branches) over the working stroke at several voltages, with

* the stiffness dF/dx: a design is *stiff* where its smallest elastic stiffness over the stroke exceeds
  ``flat`` N/m, *near-zero* (stiffness-compensated) within ±``flat``, *negative* below −``flat``;
* the breakdown curve F_B(x) = F(x, V_B(x)), V_B = E0 t0 λ3^(1 − r/2);
* the loss-of-tension region: the part of the stroke where a Cauchy stress incl. the Maxwell stress,
  σj = λj ∂Ψ/∂λj − εE², is ≤ 0 at that voltage.

The paper's prototypes #1–#3 (xp = 40 mm, λ2p = 2.5 / 2.75 / 3.0) are marked on the map. Designs are
independent, so a map can be computed on a dask cluster (:func:`compute_map` with ``client``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from bench.models.jit import njit
from bench.models.lozenge import (
    PROTOTYPE_LAMBDA2P,
    Q_E0,
    Q_EPS,
    Q_R,
    Q_T0,
    LozengeParams,
    elastic_force,
    electrostatic_force,
    gentgent,
    kinematics,
)

if TYPE_CHECKING:
    from distributed import Client

Region = Literal["stiff", "near-zero", "negative"]
STROKE = (0.050, 0.140)  # m: the paper's working stroke (model valid for x ≥ 50 mm at xp = 40 mm)


@dataclass(frozen=True)
class MapSettings:
    """Grid of the design map (lengths in m, voltages in V, stiffness in N/m)."""

    lambda2p: tuple[float, ...] = tuple(np.round(np.arange(2.0, 3.51, 0.125), 4))
    xp: tuple[float, ...] = tuple(np.round(np.arange(0.025, 0.0551, 0.0025), 5))
    voltages: tuple[float, ...] = (0.0, 3000.0, 5000.0, 7000.0)
    stroke: tuple[float, float] = STROKE
    points: int = 181  # x samples over the stroke
    flat: float = 5.0  # |k| ≤ flat is "near-zero" stiffness (#2: 4.9 N/m, "almost flat", physics.md §2.2)


@dataclass
class DesignCurves:
    """One design's characteristics over the stroke ``x`` (n points); rows of force/tension: the voltages."""

    lambda2p: float
    xp: float
    x: np.ndarray
    force: np.ndarray  # (voltages, n) F [N]
    stiffness: np.ndarray  # (voltages, n) dF/dx [N/m]
    tension_lost: np.ndarray  # (voltages, n) bool: σ1 ≤ 0 or σ2 ≤ 0
    breakdown_voltage: np.ndarray  # (n,) V_B [V]
    breakdown_force: np.ndarray  # (n,) F at V_B [N]
    elastic_stiffness: np.ndarray  # (n,) dF_el/dx [N/m]: at 0 V, whichever voltages the rows hold

    @property
    def min_stiffness(self) -> float:
        """Smallest elastic (0 V) stiffness over the stroke [N/m] (the map's regions: never the first voltage's)."""
        return float(np.min(self.elastic_stiffness))


@dataclass
class DesignMap:
    """The map: one :class:`DesignCurves` per (λ2p, xp), indexed [i_lambda2p][i_xp]."""

    settings: MapSettings
    designs: list[list[DesignCurves]] = field(default_factory=list)

    def min_stiffness(self) -> np.ndarray:
        """(λ2p, xp) grid of the smallest elastic stiffness over the stroke [N/m]."""
        return np.array([[d.min_stiffness for d in row] for row in self.designs])

    def regions(self) -> np.ndarray:
        """(λ2p, xp) grid of region names: stiff / near-zero / negative."""
        k, flat = self.min_stiffness(), self.settings.flat
        return np.where(k > flat, "stiff", np.where(k < -flat, "negative", "near-zero"))

    def design(self, lambda2p: float, xp: float) -> DesignCurves:
        """The grid's design nearest to (λ2p, xp)."""
        i = int(np.argmin(np.abs(np.array(self.settings.lambda2p) - lambda2p)))
        j = int(np.argmin(np.abs(np.array(self.settings.xp) - xp)))
        return self.designs[i][j]


@njit(cache=True)
def _curves(p: np.ndarray, x: np.ndarray, volts: np.ndarray, F: np.ndarray, K: np.ndarray, lost: np.ndarray,
            VB: np.ndarray, FB: np.ndarray, KEL: np.ndarray) -> None:
    eps, t0 = p[Q_EPS], p[Q_T0]
    for n in range(x.size):
        Fel, kel = elastic_force(x[n], p)
        KEL[n] = kel
        l1, l2, _, _, _, _ = kinematics(x[n], p)
        _, P1, P2, _, _, _, _ = gentgent(l1, l2, p)
        lam3 = 1.0 / (l1 * l2)
        VB[n] = p[Q_E0] * t0 * lam3 ** (1.0 - 0.5 * p[Q_R])
        Fes, _ = electrostatic_force(x[n], VB[n], p)
        FB[n] = Fel + Fes
        for v in range(volts.size):
            Fes, kes = electrostatic_force(x[n], volts[v], p)
            F[v, n] = Fel + Fes
            K[v, n] = kel + kes
            E = volts[v] * l1 * l2 / t0
            maxwell = eps * E * E
            lost[v, n] = l1 * P1 - maxwell <= 0.0 or l2 * P2 - maxwell <= 0.0


def design_curves(lambda2p: float, xp: float, settings: MapSettings,
                  base: LozengeParams | None = None) -> DesignCurves:
    """Characteristics of one design over the stroke (the part of it beyond xp)."""
    params = replace(base or LozengeParams(), lambda2p=lambda2p, xp=xp)
    lo, hi = settings.stroke
    x = np.linspace(max(lo, xp * 1.001), hi, settings.points)
    volts = np.asarray(settings.voltages, dtype=float)
    F, K = np.empty((volts.size, x.size)), np.empty((volts.size, x.size))
    lost = np.zeros((volts.size, x.size), dtype=np.bool_)
    VB, FB, KEL = np.empty(x.size), np.empty(x.size), np.empty(x.size)
    _curves(params.pack(), x, volts, F, K, lost, VB, FB, KEL)
    return DesignCurves(lambda2p, xp, x, F, K, lost, VB, FB, KEL)


def _row(lambda2p: float, settings: MapSettings, base: LozengeParams | None) -> list[DesignCurves]:
    return [design_curves(lambda2p, xp, settings, base) for xp in settings.xp]


def compute_map(settings: MapSettings = MapSettings(), base: LozengeParams | None = None,
                client: Client | None = None, progress: Callable[[float], None] | None = None) -> DesignMap:
    """The design map; with a dask ``client`` one task per λ2p row runs on the cluster. ``progress`` gets the
    fraction of the rows done, as each is."""
    n = len(settings.lambda2p)
    if client is None:
        rows = []
        for lam in settings.lambda2p:
            rows.append(_row(lam, settings, base))
            if progress is not None:
                progress(len(rows) / n)
    else:
        from distributed import as_completed

        futures = client.map(_row, list(settings.lambda2p), settings=settings, base=base, pure=False)
        if progress is not None:
            for k, _ in enumerate(as_completed(futures), 1):
                progress(k / n)
        rows = client.gather(futures)
    return DesignMap(settings, rows)


def plot_map(dmap: DesignMap, out: Path) -> list[Path]:
    """Two PNGs: the stiffness map over (xp, λ2p) with the prototypes, and F–x curves of selected designs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    from bench.storage.outputs import atomic_output

    out.mkdir(parents=True, exist_ok=True)
    s = dmap.settings
    k = dmap.min_stiffness()
    xp_mm = np.array(s.xp) * 1e3
    lam = np.array(s.lambda2p)
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    lim = float(np.nanmax(np.abs(np.clip(k, -200, 200))))
    mesh = ax.pcolormesh(xp_mm, lam, np.clip(k, -lim, lim), cmap="RdBu_r", shading="nearest",
                         norm=TwoSlopeNorm(0.0, -lim, lim))
    fig.colorbar(mesh, ax=ax, label="smallest elastic stiffness over the stroke dF/dx [N/m]")
    cs = ax.contour(xp_mm, lam, k, levels=[-s.flat, 0.0, s.flat], colors=["k", "k", "k"],
                    linestyles=["--", "-", "--"], linewidths=1)
    ax.clabel(cs, fmt={-s.flat: f"−{s.flat:g}", 0.0: "0", s.flat: f"{s.flat:g}"}, fontsize=8)
    for num, l2p in PROTOTYPE_LAMBDA2P.items():
        ax.plot(40.0, l2p, "k*", ms=12)
        ax.annotate(f"#{num}", (40.0, l2p), textcoords="offset points", xytext=(8, 4))
    ax.set_xlabel("mounting aperture xp [mm]")
    ax.set_ylabel("pre-stretch λ2p")
    ax.set_title(f"LS-DEA design map: stiff (k > {s.flat:g}), near-zero, negative (k < −{s.flat:g} N/m)\n"
                 f"stroke {s.stroke[0] * 1e3:g}–{s.stroke[1] * 1e3:g} mm, elastic (0 V)")
    fig.tight_layout()
    p1 = out / "design-map.png"
    with atomic_output(p1, replace=True) as tmp:  # whole or not at all
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    # F–x small multiples: the extreme and the prototypes' pre-stretches × the extreme and the prototypes' aperture
    protos = {l2p: num for num, l2p in PROTOTYPE_LAMBDA2P.items()}
    pick_l = [float(lam[0]), *protos, float(lam[-1])]
    pick_x = [s.xp[0], 0.040, s.xp[-1]]
    fig, axes = plt.subplots(len(pick_l), len(pick_x), figsize=(11, 13), sharex=True, sharey=True)
    for a_row, l2p in zip(axes, pick_l, strict=True):
        for ax, xp in zip(a_row, pick_x, strict=True):
            d = dmap.design(l2p, xp)
            mark = f"#{protos[l2p]}: " if l2p in protos and abs(d.xp - 0.040) < 1e-9 else ""
            _curve_panel(ax, d, s, mark)
    axes[0][0].legend(fontsize=7, loc="upper left")
    fig.suptitle("F–x at " + ", ".join(f"{v / 1e3:g} kV" for v in s.voltages)
                 + "; dashed: breakdown F_B(x); grey: loss of tension at the highest voltage")
    fig.supxlabel("aperture x [mm]")
    fig.supylabel("force F [N]")
    fig.tight_layout()
    p2 = out / "design-map-curves.png"
    with atomic_output(p2, replace=True) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return [p1, p2]


def _curve_panel(ax: Any, d: DesignCurves, s: MapSettings, mark: str = "") -> None:
    x = d.x * 1e3
    for v, V in enumerate(s.voltages):
        ax.plot(x, d.force[v], lw=1.2, label=f"{V / 1e3:g} kV")
    ax.plot(x, d.breakdown_force, "k--", lw=1)
    lost = d.tension_lost[-1]
    if lost.any():
        ax.fill_between(x, 0, 1, where=lost, color="0.8", transform=ax.get_xaxis_transform(), zorder=0)
    ax.axhline(0.0, color="0.5", lw=0.5)
    ax.set_title(f"{mark}λ2p {d.lambda2p:g}, xp {d.xp * 1e3:g} mm, k_min {d.min_stiffness:.1f} N/m", fontsize=9,
                 fontweight="bold" if mark else "normal")
