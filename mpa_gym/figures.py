"""Simulated reproductions of the paper's Figs. 3, 4, 8, 9, 11, 12 and 14 as PNG files.

Three kinds of figure, one helper each:

- designed pressures over one period with X̂ on a twin axis (Figs. 3, 8, 12), :func:`_pressures`;
- X against X̂ over time for simulated scenarios (Figs. 4, 14), :func:`_tracking`;
- joint stiffness k(t) for each flexor amplitude A_f (Figs. 9, 11), :func:`_k_curves`.

The inputs of Figs. 3 and 12 are the designs of the scenarios ``nominal``, ``kmax`` and ``kmin``
(``configs/scenarios``), so they are exactly the inputs simulated in Figs. 4 and 14; the Fig. 9
sweep is the one that defines k̂_max and k̂_min (:class:`StiffnessEnvelope`). Everything is SI
inside and converted at the plot: pressures in bar, errors in mm. Figures are built on
:class:`matplotlib.figure.Figure` directly, so no pyplot state or backend is touched.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from mpa_gym.analysis.scenario import Inputs, load_scenario
from mpa_gym.analysis.simulate import SimulationResult, simulate
from mpa_gym.design import (
    FeedforwardDesign,
    Reference,
    StiffnessEnvelope,
    stiffness_sweep,
)
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, Params

REFERENCE = Reference()  # X̂0 = 0.8 m, Â = 0.02 m, T = 3 s of Sec. 3.2 and 4.1 (Eq. 21)
N_T = 301  # time samples per period in the design figures
FIG4 = {"a": "initial_error", "b": "impulse", "c": "gamma_mismatch", "d": "mass_mismatch"}
KHAT = {"kmax": r"$\hat{k}_{max}$", "kmin": r"$\hat{k}_{min}$"}
REF_STYLE: dict[str, Any] = dict(color="k", lw=1.0, ls="--", label=r"$\hat{X}$ (reference)")


def _new_figure(nrows: int = 1, ncols: int = 1, **subplots_kw: Any) -> tuple[Figure, list[Axes]]:
    fig = Figure(figsize=(6.4 * ncols**0.8, 3.6 + 2.0 * (nrows - 1)), dpi=120,
                 layout="constrained")
    return fig, list(fig.subplots(nrows, ncols, squeeze=False, **subplots_kw).ravel())


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path)
    return path


def _legend_below(ax: Axes, *twins: Axes, ncol: int = 3) -> None:
    """One legend for ``ax`` and its twin axes, under the axes so it never covers data."""
    handles = [h for a in (ax, *twins) for h in a.get_legend_handles_labels()[0]]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=ncol,
              frameon=False)


# ----------------------------------------------------------------------------- Figs. 3, 8, 12
def _pressures(ax: Axes, design: FeedforwardDesign, title: str) -> None:
    """P'_e and P'_f [bar] over one period, X̂ [m] on a twin axis."""
    s = design.sample(np.linspace(0.0, design.period, N_T))
    ax.plot(s.t, s.pe / BAR, color="C3", label="$P'_e$")
    ax.plot(s.t, s.pf / BAR, color="C0", label="$P'_f$")
    ax.set(xlabel="time [s]", ylabel="pressure [bar]", xlim=(0.0, design.period), title=title)
    ax.set_ylim(-0.05 * ax.get_ylim()[1], None)  # gauge pressures >= 0: show the zero line
    twin = ax.twinx()
    twin.plot(s.t, s.x_ref, **{**REF_STYLE, "label": r"$\hat{X}$"})
    twin.set_ylabel(r"$\hat{X}$ [m]")
    _legend_below(ax, twin)


def _pressure_figure(panels: Sequence[tuple[FeedforwardDesign, str]], path: Path,
                     suptitle: str = "") -> Path:
    """One :func:`_pressures` panel per (design, title), side by side on a shared pressure axis."""
    fig, axes = _new_figure(1, len(panels), sharey=True)
    for ax, (design, title) in zip(axes, panels, strict=True):
        _pressures(ax, design, title)
        ax.label_outer()
    if suptitle:
        fig.suptitle(suptitle)
    return _save(fig, path)


# ----------------------------------------------------------------------------- Figs. 4, 14
def _tracking(ax: Axes, runs: Sequence[tuple[SimulationResult, str]], t_from: float = 0.0
              ) -> None:
    """X [m] of each run and X̂ of the first against time from ``t_from``; impulses marked."""
    first = runs[0][0]
    w = first.t >= t_from
    ax.plot(first.t[w], first.x_ref[w], **REF_STYLE, zorder=3)
    for i, (res, label) in enumerate(runs):
        ax.plot(res.t[w], res.x[w], color=f"C{i}", lw=1.4, label=label)
    for d in first.scenario.disturbances:
        if d.t_s >= t_from:
            ax.axvline(d.t_s, color="C1", lw=2.0, alpha=0.5,
                       label=f"impulse {d.force_N:g} N for {d.duration_s:g} s")
    ax.set(xlabel="time [s]", ylabel="X [m]", xlim=(t_from, first.t[-1]))


def _fig4(letter: str, scenario: str, params: Params, out: Path) -> Path:
    res = simulate(scenario, params)
    fig, (ax,) = _new_figure()
    _tracking(ax, [(res, "X (simulated)")])
    what = res.scenario.description.removeprefix(f"Fig. 4({letter}), ")
    ax.set_title(f"Fig. 4({letter}) simulated: {what}", fontsize="medium")
    _legend_below(ax)
    return _save(fig, out / f"fig04{letter}_{scenario}.png")


def _fig14(params: Params, out: Path) -> Path:
    runs = [(simulate(name, params), f"X, {KHAT[kind]} design")
            for name, kind in (("load_1kg", "kmax"), ("load_1kg_kmin", "kmin"))]
    t_from = runs[0][0].t[-1] - 2 * runs[0][0].scenario.reference.period
    fig, (ax_x, ax_e) = _new_figure(2, 1, sharex=True)
    _tracking(ax_x, runs, t_from)
    ax_x.set(xlabel="", title=f"Fig. 14 simulated: +1 kg at the hip, {KHAT['kmax']} vs "
             f"{KHAT['kmin']} inputs (last 2 periods)")
    ax_x.legend(loc="upper center", bbox_to_anchor=(0.5, -0.04), ncol=3, frameon=False)
    for i, (res, label) in enumerate(runs):
        w = res.t >= t_from
        ax_e.plot(res.t[w], 1e3 * res.error[w], color=f"C{i}",
                  label=f"{label.removeprefix('X, ')}: RMSE {1e3 * res.rmse_m:.1f} mm (last 3 T)")
    ax_e.axhline(0.0, color="k", lw=0.8)
    ax_e.set(xlabel="time [s]", ylabel=r"X − $\hat{X}$ [mm]")
    _legend_below(ax_e, ncol=1)
    return _save(fig, out / "fig14_load_1kg_kmax_vs_kmin.png")


# ----------------------------------------------------------------------------- Figs. 9, 11
def _sweep(params: Params) -> tuple[np.ndarray, np.ndarray, np.ndarray, StiffnessEnvelope]:
    """The Fig. 9 sweep over one period: t [s], A_f [Pa], k [N/m] (A_f, t) and its envelope."""
    env = StiffnessEnvelope("kmax", REFERENCE, params=params)
    t = np.linspace(0.0, REFERENCE.period, N_T)
    return t, env.amps, stiffness_sweep(REFERENCE, env.pf_mean, env.amps, t, params), env


def _k_curves(ax: Axes, t: np.ndarray, amps: np.ndarray, k: np.ndarray, grey: bool = False
              ) -> None:
    """k(t) [N/m] for each A_f: grey, or coloured blue (A_f < 0) to red (A_f > 0) with a legend."""
    colour = colormaps["coolwarm"](np.linspace(0.0, 1.0, amps.size))
    for a, kk, c in zip(amps, k, colour, strict=True):
        ax.plot(t, kk, lw=1.0, color="0.65" if grey else c,
                label=None if grey else f"$A_f$ = {a / BAR:+.1f} bar")
    ax.set(xlabel="time [s]", ylabel="k [N/m]", xlim=(t[0], t[-1]))


def _fig9(params: Params, out: Path) -> Path:
    t, amps, k, env = _sweep(params)
    fig = Figure(figsize=(12.0, 4.6), dpi=120, layout="constrained")
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    tt, aa = np.meshgrid(t, amps / BAR)
    ax3.plot_surface(tt, aa, k, cmap="viridis", rstride=1, cstride=10, linewidth=0.2,
                     edgecolor="k")
    ax3.set(xlabel="time [s]", ylabel="$A_f$ [bar]", zlabel="k [N/m]",
            title="(a) k over t and $A_f$")
    ax3.view_init(elev=25, azim=-60)
    ax = fig.add_subplot(1, 2, 2)
    _k_curves(ax, t, amps, k)
    ax.set_title("(b) projection onto the t-k plane")
    ax.legend(loc="upper right", fontsize="x-small", ncol=2)
    fig.suptitle(f"Fig. 9 simulated: joint stiffness k (Eq. 23) with $P'_{{f0}}$ = "
                 f"{env.pf_mean / BAR:g} bar, " r"$P'_f = P'_{f0} + A_f \sin\omega t$")
    return _save(fig, out / "fig09_stiffness_sweep.png")


def _fig11(params: Params, out: Path) -> Path:
    t, amps, k, env = _sweep(params)
    fig, (ax,) = _new_figure()
    _k_curves(ax, t, amps, k, grey=True)
    ax.plot([], [], color="0.65", label=f"Fig. 9(b) sweep, {amps.size} values of $A_f$")
    for kind, colour, limit in (("kmax", "C3", "upper"), ("kmin", "C0", "lower")):
        ax.plot(t, replace(env, kind=kind)(t), color=colour, lw=2.0, ls="--",
                label=f"{KHAT[kind]} ({limit} limit)")
    ax.set_title(f"Fig. 11 simulated: designed {KHAT['kmax']} and {KHAT['kmin']} from Fig. 9(b)")
    _legend_below(ax)
    return _save(fig, out / "fig11_kmax_kmin.png")


# ----------------------------------------------------------------------------- entry point
def make_figures(out_dir: str | Path, params: Params = DEFAULT_PARAMS) -> list[Path]:
    """Write the simulated counterparts of the paper's figures as PNGs into ``out_dir``.

    Parameters
    ----------
    out_dir : directory for the PNGs; created if missing.
    params : the nominal (design) model; the scenarios of Figs. 4 and 14 perturb their plant as
        their YAML files in ``configs/scenarios`` say.

    Returns
    -------
    The paths written, in figure order: fig03, fig04a-d, fig08a-c, fig09, fig11, fig12, fig14.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig3 = load_scenario("nominal").design(params)
    pf_bar = float(fig3.flexor_pressure(0.0)) / BAR
    paths = [_pressure_figure(
        [(fig3, f"Fig. 3 simulated: designed $P'_e$ (Eq. 16) with $P'_f$ = {pf_bar:g} bar")],
        out / "fig03_inputs_pf_const.png")]
    paths += [_fig4(letter, scenario, params, out) for letter, scenario in FIG4.items()]
    for mode, letter in ((1, "a"), (2, "b"), (3, "c")):
        design = Inputs(mode=mode).design(REFERENCE, params)
        paths.append(_pressure_figure(
            [(design, f"Fig. 8({letter}) simulated: mode {mode} of Table 1")],
            out / f"fig08{letter}_mode{mode}.png"))
    paths += [_fig9(params, out), _fig11(params, out)]
    paths.append(_pressure_figure(
        [(load_scenario(kind).design(params), f"{KHAT[kind]} design (Eq. 25)")
         for kind in ("kmax", "kmin")], out / "fig12_inputs_kmax_kmin.png",
        suptitle=f"Fig. 12 simulated: $P'_e$ and $P'_f$ from {KHAT['kmax']} and {KHAT['kmin']}"))
    paths.append(_fig14(params, out))
    return paths
