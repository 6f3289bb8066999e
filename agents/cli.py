"""The `mpa-gym` command (docs/design.md#cli): the paper's tools, training, evaluation and the rig.

Every subcommand prints a readable table by default and one JSON object with ``--json``.
SI units in JSON unless a key says ``_bar``; pressures are given and shown in bar.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import mpa_gym
from mpa_gym.analysis.scenario import Inputs
from mpa_gym.design import FeedforwardDesign, Reference, feasible_stiffness_range
from mpa_gym.files import check_out_dir
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, check_range

# The design flags' defaults are the dataclasses' (one definition); the name each flag's value
# goes by in their error messages, to say which flag was wrong.
REFERENCE, INPUTS = Reference(), Inputs()
FLAG_FIELDS = {"--x0": "reference.x0_m", "--amp": "reference.amp_m",
               "--period": "reference.period_s", "--pf-mean": "inputs.pf_mean_bar",
               "--pf-amp": "inputs.pf_amp_bar", "--p-max": "inputs.p_max_bar",
               "--stiffness-const": "inputs.stiffness_const_N_per_m"}

# the optional dependencies a subcommand may need, and the extra (pyproject.toml) that brings each
EXTRAS = {"torch": "train", "stable_baselines3": "train", "optuna": "train",
          "tensorboard": "train", "tqdm": "train", "rich": "train", "rliable": "stats",
          "psycopg2": "postgres"}

PERIOD_MAX_S = 60.0  # [s] longest reference period the CLI accepts (20 × the paper's 3 s)


class Interrupted(KeyboardInterrupt):
    """SIGTERM, raised where Python would raise KeyboardInterrupt for Ctrl-C, so that every
    ``finally`` / ``except BaseException`` (venting the rig, saving a model) runs for it too."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class CommandStopped(Exception):
    """A command that ran but stopped early: ``out`` is still printed, then ``message`` on
    stderr, and the process exits with ``code``."""

    def __init__(self, out: dict[str, Any] | None, message: str, code: int) -> None:
        super().__init__(message)
        self.out, self.message, self.code = out, message, code


def _add_design_flags(p: argparse.ArgumentParser, samples: bool = True) -> None:
    """The flags of `design` and `analyze` (which integrates a period: no --samples)."""
    g = p.add_argument_group("reference (Eq. 21) and inputs (Eq. 22 / Table 1 / Eq. 25)")
    g.add_argument("--x0", type=float, default=REFERENCE.x0, metavar="M",
                   help="X̂0 [m] (default %(default)s)")
    g.add_argument("--amp", type=float, default=REFERENCE.amp, metavar="M",
                   help="Â [m] (default %(default)s)")
    g.add_argument("--period", type=float, default=REFERENCE.period, metavar="S",
                   help=f"T [s] in [0.1, {PERIOD_MAX_S:g}] (default %(default)s)")
    g.add_argument("--pf-mean", type=float, default=INPUTS.pf_mean_bar, metavar="BAR",
                   help="P'_f0 [bar] (default %(default)s, Fig. 3)")
    g.add_argument("--pf-amp", type=float, default=INPUTS.pf_amp_bar, metavar="BAR",
                   help="A_f [bar] (default %(default)s)")
    x = g.add_mutually_exclusive_group()
    x.add_argument("--mode", type=int, choices=(1, 2, 3), help="Table 1 preset for P'_f0, A_f")
    x.add_argument("--stiffness", choices=("kmax", "kmin"),
                   help="Eq. (25) design for the Fig. 11 envelope instead of Eq. (22)")
    x.add_argument("--stiffness-const", type=float, metavar="N_PER_M",
                   help="Eq. (25) design for a constant k̂ [N/m]")
    if samples:
        g.add_argument("--samples", type=int, default=61, metavar="N",
                       help="samples over one period (default %(default)s)")
    g.add_argument("--p-max", type=float, default=INPUTS.p_max_bar, metavar="BAR",
                   help="upper pressure limit [bar] (default %(default)s)")


def _design_from_args(a: argparse.Namespace) -> FeedforwardDesign:
    """The design of the flags, built and checked by the dataclasses a scenario uses; an error
    names the flag."""
    check_range("--period", a.period, 0.1, PERIOD_MAX_S, unit="s",
                note="the analysis integrates one period: its cost grows with T")
    try:
        ref = Reference(x0=a.x0, amp=a.amp, period=a.period)
        inputs = Inputs(pf_mean_bar=a.pf_mean, pf_amp_bar=a.pf_amp, mode=a.mode,
                        stiffness=a.stiffness, stiffness_const_N_per_m=a.stiffness_const,
                        p_max_bar=a.p_max)
    except ValueError as e:
        msg = str(e)
        for flag, name in FLAG_FIELDS.items():
            msg = msg.replace(f"{name}=", f"{flag}=")
        raise ValueError(msg) from None
    return inputs.design(ref)


def _check_samples(n: int) -> int:
    if not 2 <= n <= 100_000:
        raise ValueError(f"--samples={n} is outside the allowed range [2, 100000]")
    return n


def _table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = "  ".join(f"{{:>{w}}}" for w in widths)
    return "\n".join([fmt.format(*header), fmt.format(*("-" * w for w in widths)),
                      *(fmt.format(*r) for r in rows)])


def cmd_design(a: argparse.Namespace) -> dict[str, Any]:
    d = _design_from_args(a)
    n = _check_samples(a.samples)
    t = np.linspace(0.0, d.period, n)
    s = d.sample(t)
    rep = d.feasibility(n_samples=max(n, 601), p_max=a.p_max * BAR)
    out: dict[str, Any] = {
        "t": t.tolist(), "x_ref": s.x_ref.tolist(), "v_ref": s.v_ref.tolist(),
        "pe_bar": (s.pe / BAR).tolist(), "pf_bar": (s.pf / BAR).tolist(), "k": s.k.tolist(),
        "feasible": rep.feasible, "violations": [v.describe() for v in rep.violations],
    }
    if d.stiffness is not None:
        r = d.reference
        lo, hi = feasible_stiffness_range(r.position(t), r.velocity(t), r.acceleration(t),
                                          d.params, a.p_max * BAR)
        out["k_feasible_min"] = [None if np.isnan(v) else float(v) for v in lo]
        out["k_feasible_max"] = [None if np.isnan(v) else float(v) for v in hi]
    return out


def show_design(o: dict[str, Any]) -> str:
    idx = np.unique(np.linspace(0, len(o["t"]) - 1, min(len(o["t"]), 13)).round().astype(int))
    rows = [[f"{o['t'][i]:.3f}", f"{o['x_ref'][i]:.4f}", f"{o['pe_bar'][i]:.3f}",
             f"{o['pf_bar'][i]:.3f}", f"{o['k'][i]:.1f}"] for i in idx]
    text = _table(rows, ["t [s]", "X̂ [m]", "P'_e [bar]", "P'_f [bar]", "k [N/m]"])
    verdict = "feasible" if o["feasible"] else "INFEASIBLE:\n  " + "\n  ".join(o["violations"])
    return f"{text}\n\ndesign is {verdict}"


def cmd_analyze(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.analysis.stability import analyze

    d = _design_from_args(a)
    rep = analyze(d)
    return {
        "int_a1": rep.int_a1,
        "theorem1_holds": rep.theorem1_holds,
        "floquet_multipliers": [[float(m.real), float(m.imag)] for m in rep.multipliers],
        "floquet_moduli": [float(abs(m)) for m in rep.multipliers],
        "monodromy_det": float(np.linalg.det(rep.monodromy)),
        "exp_int_a1": float(np.exp(rep.int_a1)),
        "stable": rep.stable,
        "feasible": d.feasibility(p_max=a.p_max * BAR).feasible,
    }


def show_analyze(o: dict[str, Any]) -> str:
    mults = ", ".join(f"{re:+.6f}{im:+.6f}j (|μ| = {abs(complex(re, im)):.6f})"
                      for re, im in o["floquet_multipliers"])
    return "\n".join([
        f"Theorem 1: ∫_0^T a1 dt = {o['int_a1']:.6f}  "
        f"({'< 0, holds' if o['theorem1_holds'] else '>= 0, violated'})",
        f"Floquet multipliers: {mults}",
        f"Liouville: det Φ(T) = {o['monodromy_det']:.10f}, exp(∫a1) = {o['exp_int_a1']:.10f}",
        f"periodic motion is {'asymptotically stable' if o['stable'] else 'NOT stable'}"
        f"; design is {'feasible' if o['feasible'] else 'infeasible'}",
    ])


def cmd_simulate(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.analysis.simulate import DT_MAX_S, DT_MIN_S, SimulationError, simulate

    check_range("--dt", a.dt, DT_MIN_S, DT_MAX_S, unit="s")  # before --output-dt's
    check_range("--output-dt", a.output_dt, a.dt, 60.0, unit="s", note="at least --dt")
    try:
        return simulate(a.scenario, DEFAULT_PARAMS, dt=a.dt, output_dt=a.output_dt).to_json()
    except SimulationError as e:  # the scenario drives the model out of its domain: its input
        raise ValueError(str(e)) from None


def show_simulate(o: dict[str, Any]) -> str:
    x, xr, t = np.array(o["x"]), np.array(o["x_ref"]), np.array(o["t"])
    idx = np.unique(np.linspace(0, t.size - 1, 11).round().astype(int))
    rows = [[f"{t[i]:.2f}", f"{x[i]:.5f}", f"{xr[i]:.5f}", f"{(x[i] - xr[i]) * 1e3:+.3f}"]
            for i in idx]
    return (f"scenario {o['scenario']}\n"
            + _table(rows, ["t [s]", "X [m]", "X̂ [m]", "X − X̂ [mm]"])
            + f"\n\nlast 3 periods: RMSE {o['rmse_m'] * 1e3:.4f} mm, "
              f"max |X − X̂| {o['max_abs_err_m'] * 1e3:.4f} mm")


def cmd_figures(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.figures import make_figures

    check_out_dir("--out", a.out)
    return {"files": [str(p) for p in make_figures(a.out)]}


def show_figures(o: dict[str, Any]) -> str:
    return "wrote:\n  " + "\n  ".join(o["files"])


def _only_with(a: argparse.Namespace, mode: str, flags: tuple[str, ...]) -> None:
    """Refuse each of ``flags`` given (other than its default) where ``mode`` runs, which
    would ignore it."""
    for flag in flags:
        dest = flag.lstrip("-").replace("-", "_")
        if getattr(a, dest) != a.parser.get_default(dest):
            raise ValueError(f"{flag}={getattr(a, dest)!r} does not go with {mode}, which "
                             "would ignore it")


BENCH_MODES = {"--loop": ("--control-hz", "--loop-s", "--repeats", "--rig"),
               "--inference": ("--actions", "--no-emulator"),
               "the step-rate benchmark": ("--seconds", "--sizes")}


def cmd_bench(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym import bench

    if a.gains is not None and a.loop is None:
        raise ValueError(f"--gains {a.gains!r} goes with --loop (the controller it tunes)")
    if a.loop is not None and a.inference is not None:
        raise ValueError("--loop and --inference are two benchmarks; give one")
    mode = ("--loop" if a.loop is not None else "--inference" if a.inference is not None
            else "the step-rate benchmark")
    _only_with(a, mode, tuple(f for m, fs in BENCH_MODES.items() if m != mode for f in fs))
    if a.loop is not None:
        from mpa_gym.agents.rig.rollout import LoopStopped, loop_benchmark

        try:
            return {"loop": loop_benchmark(a.loop, a.control_hz, a.loop_s, a.repeats, a.rig,
                                           gains=_gains(a))}
        except LoopStopped as e:  # the emulated rig failed a safety check: vented, code 3
            raise CommandStopped(None, f"STOPPED, rig vented: {e}", 3) from None
    if a.inference is not None:
        from mpa_gym.agents.rig.bench import benchmark

        if not 100 <= a.actions <= 10_000_000:
            raise ValueError(f"--actions={a.actions} is outside the allowed range [100, 1e7]")
        if not Path(a.inference).is_dir():
            raise ValueError(f"--inference {a.inference!r} is not a folder: give a run folder "
                             "(mpa-gym train --run-dir)")
        return {"inference": benchmark(a.inference, a.actions, max(100, a.actions // 10),
                                       emulator=not a.no_emulator)}
    check_range("--seconds", a.seconds, 0.05, 60.0, unit="s")
    for n in a.sizes:
        if not 1 <= n <= 65536:
            raise ValueError(f"--sizes: {n} is outside the allowed range [1, 65536]")
    return bench.run(a.seconds, tuple(a.sizes))


def show_bench(o: dict[str, Any]) -> str:
    from mpa_gym import bench

    if "loop" in o:
        from mpa_gym.agents.rig.rollout import show_loop_benchmark

        return show_loop_benchmark(o["loop"])
    if "inference" in o:
        from mpa_gym.agents.rig.bench import show_benchmark

        return show_benchmark(o["inference"])
    return bench.show(o)


def cmd_train(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.agents.learned.config import MAX_TIMESTEPS, SEED_MAX
    from mpa_gym.agents.learned.runs import read_eval_history, zip_timesteps
    from mpa_gym.agents.training.train import TrainingStopped, train

    if a.n_timesteps is not None and not 1 <= a.n_timesteps <= MAX_TIMESTEPS:
        raise ValueError(f"--n-timesteps={a.n_timesteps} must be in [1, {MAX_TIMESTEPS:.0e}]")
    if a.seed is not None and not 0 <= a.seed <= SEED_MAX:
        raise ValueError(f"--seed={a.seed} must be in [0, {SEED_MAX}]")
    if a.config is not None and a.resume is not None:
        raise ValueError("--config and --resume exclude each other: a resumed run keeps the "
                         "config.yaml of its folder")
    if a.seed is not None and a.resume is not None:
        raise ValueError("--seed and --resume exclude each other: a resumed run keeps the seed "
                         "of its config.yaml")
    if a.scenario is not None and a.resume is not None:
        raise ValueError("--scenario and --resume exclude each other: a resumed run keeps the "
                         "training scenario of its config.yaml")
    if a.seeds is None and a.jobs is not None:
        raise ValueError(f"--jobs={a.jobs} goes with --seeds (processes at once); one run "
                         "trains in this process")
    if a.seeds is not None:
        from mpa_gym.agents.evaluation.seeds import SeedsFailed, train_seeds

        if a.seed is not None or a.resume is not None:
            raise ValueError("--seeds trains new runs; it goes without --seed and --resume")
        try:
            return {"runs": train_seeds(a.seeds, a.config, a.run_dir, a.n_timesteps, a.jobs,
                                        a.scenario, a.eval_worker)}
        except SeedsFailed as e:  # the runs that finished are kept; each failure in one line
            raise CommandStopped({"runs": e.done} if e.done else None, str(e), 1) from None
    try:
        run = train(a.config, a.run_dir, a.seed, a.resume, a.n_timesteps,
                    progress=not a.no_progress, scenario=a.scenario, eval_worker=a.eval_worker)
    except TrainingStopped as e:
        code = 128 + e.signum if e.signum is not None else 1
        raise CommandStopped(None, e.reason, code) from None
    hist = run / "eval"
    last = read_eval_history(hist)[0][-1:] if (hist / "evaluations.json").is_file() else []
    return {"run_dir": str(run), "timesteps": zip_timesteps(run / "model.zip"),
            "last_evaluation": last[0] if last else None}


def show_train(o: dict[str, Any]) -> str:
    if "runs" in o:
        return "\n\n".join(show_train(r) for r in o["runs"])
    lines = [f"run folder: {o['run_dir']}  ({o['timesteps']} env steps)"]
    if o["last_evaluation"]:
        lines.append(f"held-out evaluation at {o['last_evaluation']['timesteps']} steps:")
        for name, m in o["last_evaluation"]["scenarios"].items():
            lines.append(f"  {name:<18} position RMSE {m['position_rmse_mm']:.3f} mm, "
                         f"stiffness error {m['stiffness_rmse_pct']:.2f} %")
    return "\n".join(lines)


def cmd_evaluate(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.agents.evaluation.evaluate import (
        HELDOUT_SCENARIOS,
        PAPER_SCENARIOS,
        evaluate,
        hand_over_lines,
        write_report,
    )

    check_out_dir("--out", a.out)
    if not 0 <= a.seed <= 2**32 - 1:
        raise ValueError(f"--seed={a.seed} must be in [0, 4294967295]")
    from mpa_gym.agents.evaluation.rigs import MAX_RIGS, RIGS_SEED

    if not 0 <= a.random_rigs <= MAX_RIGS:
        raise ValueError(f"--random-rigs={a.random_rigs} must be in [0, {MAX_RIGS}] (0: none)")
    if a.rigs_seed is None:
        a.rigs_seed = RIGS_SEED
    if not 0 <= a.rigs_seed <= 2**32 - 1:
        raise ValueError(f"--rigs-seed={a.rigs_seed} must be in [0, 4294967295]")
    scenarios = a.scenarios or [*PAPER_SCENARIOS, *HELDOUT_SCENARIOS]
    report = evaluate(a.policy, scenarios, a.seed, robustness=not a.no_robustness,
                      plots_dir=Path(a.out) / "plots", gains=_gains(a),
                      random_rigs=a.random_rigs, rigs_seed=a.rigs_seed)
    paths = write_report(report, a.out)
    data = json.loads(paths["json"].read_text())
    return {"summary": data["summary"], "results": data["results"],
            "robustness": data.get("robustness"),
            "groups": data.get("groups") or {}, "no_harm": data.get("no_harm") or {},
            "stages": data.get("stages") or {}, "hand_overs": hand_over_lines(report),
            "random_rigs": data.get("random_rigs"), "report_json": str(paths["json"]),
            "report_md": str(paths["markdown"]),
            "plots": str(paths["plots"])}


def show_evaluate(o: dict[str, Any]) -> str:
    res, groups = o["results"], o.get("groups") or {}
    grouped = {r for g in groups.values() for r in g["runs"]}
    ctrls = [c for c in next(iter(res.values())) if c not in grouped]

    def iv(a: dict[str, Any], key: str, fmt: str) -> str:
        lo, hi = a[f"{key}_ci"]
        return f"{a[key]:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"

    def took(m: dict[str, Any]) -> str:  # a figure a fallback had a hand in
        return " ‡" if m.get("fallback_s") is not None else ""

    rows = [[sc] + [f"{row[c]['position_rmse_mm']:.3f} / {row[c]['stiffness_rmse_pct']:.1f}"
                    + took(row[c]) for c in ctrls]
            + [f"{iv(g['results'][sc], 'position_rmse_mm', '.3f')} / "
               f"{iv(g['results'][sc], 'stiffness_rmse_pct', '.1f')}"
               + (f" ‡{g['results'][sc]['fallback_runs']}/{g['results'][sc]['n_runs']}"
                  if g["results"][sc].get("fallback_runs") else "") for g in groups.values()]
            for sc, row in res.items()]
    handed = [f"  {line}" for line in o.get("hand_overs") or []]
    handed += [f"  {g} on {sc}: a fallback drove in {a['fallback_runs']} of {a['n_runs']} runs"
               + (f" (chosen on the model in {a['chosen_runs']})" if a.get("chosen_runs")
                  else "") for g, v in groups.items()
               for sc, a in v["results"].items() if a.get("fallback_runs")]
    levels = (o.get("robustness") or {}).get("levels") or {}
    extra = ""
    if levels:
        lrows = [[lv] + [("terminated" if m["terminated"] else f"{m['position_rmse_mm']:.3f}"
                          + (" unstable" if m["unstable"] else "")) + took(m)
                         for m in per.values()]
                 for lv, per in levels.items()]
        extra = ("\n\nrobustness levels, position RMSE [mm] (grids in the report)\n"
                 + _table(lrows, ["level", *next(iter(levels.values()))]))
    rr = o.get("random_rigs")
    if rr:
        extra += (f"\n\nrandom rigs ({rr['n']}, seed {rr['seed']}), median position RMSE [mm]: "
                  + ", ".join(f"{c} {'unstable' if v is None else f'{v:.3f}'}"
                              for c, v in rr["median_mm"].items()))
        for ctrl, a in rr["audit"].items():
            extra += (f"\n  {ctrl}: supervised within {rr['ratio']:g}x the better of the policy "
                      f"alone and the best classical on {a['supervised_within']:.0%} of the rigs"
                      f" (undominated, with stiffness, on {a['supervised_undominated']:.0%})"
                      + ("" if a["alone_within_pid"] is None else
                         f", the policy alone within {rr['ratio']:g}x pid on "
                         f"{a['alone_within_pid']:.0%}")
                      + f", hand-overs on {len(a['hand_overs'])}"
                      + f", a fallback chosen on the model on {len(a.get('chosen') or [])}")
    for ctrl, a in (o.get("no_harm") or {}).items():
        extra += (f"\nno harm: {ctrl} breaks a bound on {len(a['harm'])} of {a['checked']} "
                  "cases" + (" (listed in the report)" if a["harm"] else ""))
    if o.get("stages"):
        extra += ("\nfallbacks that drove, handed the loop or chosen on the model (‡: the "
                  "supervised loop's figure, not the policy's; "
                  "'<run> (alone)': the policy without its supervisor): "
                  + ("\n" + "\n".join(handed) if handed else "none, the policies drove "
                     "every step"))
    head = "position RMSE [mm] / stiffness RMSE [% of k̂], last 3 periods"
    if groups:
        head += "; several runs of one config: IQM [95 % CI] over the runs"
    return (head + "\n"
            + _table(rows, ["scenario", *ctrls,
                            *(f"{g} ({len(v['runs'])} runs)" for g, v in groups.items())])
            + extra + "\n\n" + show_summary(o["summary"])
            + f"\n\nreport: {o['report_md']} (and {o['report_json']}, plots in {o['plots']})")


def _gains(a: argparse.Namespace) -> Any:
    """The baselines' gains of ``--gains FILE`` (``mpa_gym.agents.controllers.gains``)."""
    from mpa_gym.agents.controllers.gains import load_gains

    return load_gains(a.gains, "--gains")


def show_summary(summ: dict[str, Any]) -> str:
    """``evaluate``'s summary (``mpa_gym.agents.evaluation.evaluate.summary``) as a table: every
    controller's means per scenario group, the best of each group starred, then the best of
    each group in words with who drove."""
    from mpa_gym.agents.evaluation.evaluate import KINDS, summary_cell, who_drove_text

    groups = summ["groups"]
    first = next(iter(groups.values()))["controllers"]
    rows = []
    for row, e0 in first.items():
        cells = []
        for g in groups.values():
            e = g["controllers"][row]
            cells.append(summary_cell(e, "position_rmse_mm", ".3f") + " / "
                         + summary_cell(e, "stiffness_rmse_pct", ".1f")
                         + (f" ‡{e['fallback_episodes']}/{e['episodes']}"
                            if e["fallback_episodes"] else "")
                         + (" *" if g["best"] == row else ""))
        rows.append([row, KINDS.get(e0["kind"], e0["kind"]), *cells])
    lines = ["summary: mean over each group's scenarios, position RMSE [mm] / stiffness RMSE "
             "[% of k̂] (several runs: IQM [95 % CI] over the runs); * best of the group; "
             "‡k/n: a fallback drove in k of n episodes, handed the loop or chosen on the "
             "model (the supervised loop's figure)",
             _table(rows, ["controller", "who drove", *(f"{g['title']} ({len(g['scenarios'])})"
                                                         for g in groups.values())])]
    for g in groups.values():
        best = g["best"]
        if best is None:
            lines.append(f"best on {g['title']}: none (every controller terminated somewhere)")
            continue
        e = g["controllers"][best]
        stiff = ("" if e.get("stiffness_rmse_pct") is None else
                 f", {summary_cell(e, 'stiffness_rmse_pct', '.2f')} %")
        lines.append(f"best on {g['title']}: {best}{' ‡' if e['fallback_episodes'] else ''}, "
                     f"{summary_cell(e, 'position_rmse_mm', '.3f')} mm{stiff} "
                     f"({who_drove_text(e)})")
    return "\n".join(lines)


def cmd_tune_baselines(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.agents.learned.config import DEFAULT_CONFIG
    from mpa_gym.agents.training.tune_baselines import tune, write_gains

    out = None if a.out is None else write_gains(None, a.out)  # writable: checked first
    kw = {} if a.episode_s is None else {"episode_s": a.episode_s}
    results = [tune(name, a.config or DEFAULT_CONFIG, a.n_trials, a.n_plants, a.seed, **kw)
               for name in a.policy]
    if out is not None:
        write_gains(results, out)
    return {"results": results, "out": None if out is None else str(out)}


def show_tune_baselines(o: dict[str, Any]) -> str:
    lines = []
    for r in o["results"]:
        gains = ", ".join(f"{k} = {v:.4g}" for k, v in r["gains"].items())
        lines.append(f"{r['policy']}: {gains}\n  mean position RMSE "
                     f"{r['mean_position_rmse_mm']:.3f} mm (defaults: "
                     f"{r['default_mean_position_rmse_mm']:.3f} mm) over "
                     f"{r['tuned_on']['n_plants']} training plants (and as many undamped "
                     f"twins) of {r['tuned_on']['config']}, "
                     f"{r['tuned_on']['budget']}")
    if o.get("out"):
        lines.append(f"wrote {o['out']} (evaluate / rollout / bench --loop --gains FILE, "
                     "a run config's supervisor.gains)")
    return "\n".join(lines)


def cmd_calibrate(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.agents.evaluation import calibrate as cal

    if not (Path(a.run_dir) / "config.yaml").is_file():
        raise ValueError(f"RUN_DIR={a.run_dir!r} is not a run folder (needs config.yaml)")
    found = cal.calibrate(a.run_dir, **{k: v for k, v in (("n_plants", a.n_plants),
                                                           ("episode_s", a.episode_s))
                                         if v is not None})
    return {**found.as_dict(), "written": str(cal.write(a.run_dir, found)) if a.write else None}


def show_calibrate(o: dict[str, Any]) -> str:
    order = ", ".join(f"{f['controller']} {f['mean_position_rmse_mm']:.3f} mm"
                      for f in o["fallback_order"])
    peaks = ", ".join(f"{k} {v:.3f} mm" for k, v in o["peaks_mm"].items())
    return (f"fallback order (mean position RMSE over the {o['ordered_on_plants']} of "
            f"{o['n_plants']} training plants a fallback is for): "
            f"{order}\nthe policy keeps {o['kept_plants']} of {o['n_plants']} plants (it tracks "
            f"them at least as well as {o['fallback_order'][0]['controller']}); the monitors' "
            f"highest RMS there: {peaks}"
            + (f"; dropped (cannot stay quiet there): {', '.join(o['dropped'])}"
               if o["dropped"] else "")
            + f"\nrule: {o['rule']}"
            + (f"\nwritten into {o['written']}" if o["written"] else
               "\n(--write puts it into the run's config.yaml)"))


def cmd_tune(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.agents.training import tune

    if a.best is not None:
        if a.out is None:
            raise ValueError("--best STUDY needs --out FILE.yaml")
        return tune.write_best(a.storage, a.best, a.out, a.trial)
    if a.out is not None or a.trial is not None:
        raise ValueError("--out and --trial go with --best STUDY")
    try:
        return tune.tune(a.config, a.storage, a.study_name, a.n_trials, a.max_total_trials,
                         a.seeds_per_trial, a.n_timesteps, a.objective, a.heartbeat, a.out_dir,
                         a.heldout)
    except tune.TuneStopped as e:
        raise CommandStopped(None, str(e), 128 + e.signum) from None


def show_tune(o: dict[str, Any]) -> str:
    if "out" in o:
        return (f"wrote {o['out']}: trial {o['trial']} of {o['study_name']} "
                f"(values {', '.join(f'{v:.4g}' for v in o['values'])})")
    lines = [f"study {o['study_name']}: {o['n_trials']} trials "
             + ", ".join(f"{n} {k.lower()}" for k, n in sorted(o["states"].items()))
             + f"; {o['by_this_worker']} finished by this worker",
             f"best trials ({' / '.join(o['objectives'])}, of the policy alone):"]
    for t in o["pareto_front"]:
        vals = ", ".join(f"{k} {v:.4f}" for k, v in t["values"].items())
        hand = t.get("hand_overs")
        lines.append(f"  #{t['number']}: {vals}; {t['wall_s']:.0f} s; "
                     + ("" if hand is None else f"supervised: {hand} held-out episode(s) "
                        "handed to the fallback; ") + f"{t['params']}")
    return "\n".join(lines)


# emulate's fault-injection flags: (flag, mpa_gym.hardware.emulator.LinkFaults field, unit)
FAULT_FLAGS = (("--latency", "latency_s", "s"), ("--jitter", "jitter_s", "s"),
               ("--drop", "drop_prob", "probability"), ("--late", "late_prob", "probability"),
               ("--corrupt", "corrupt_prob", "probability"),
               ("--position-noise", "position_noise_m", "m"))


def cmd_emulate(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.hardware.emulator import Emulator, LinkFaults
    from mpa_gym.hardware.transport import PtyPair, TransportError, UDPServer

    if a.duration is not None:
        check_range("--duration", a.duration, 0.0, 1e7, low_open=True, unit="s")
    check_range("--watchdog", a.watchdog, 1e-3, 10.0, unit="s")
    if not 0 <= a.port <= 65535:
        raise ValueError(f"--port={a.port} must be in [0, 65535]")
    if a.serial:
        _only_with(a, "--serial (a pseudo-terminal)", ("--host", "--port"))
    try:
        faults = LinkFaults(**{field: getattr(a, flag[2:].replace("-", "_"))
                               for flag, field, _ in FAULT_FLAGS})
    except ValueError as e:  # LinkFaults names its fields: name the flags instead
        msg = str(e)
        for flag, field, _ in FAULT_FLAGS:
            msg = msg.replace(f"faults.{field}", flag)
        raise ValueError(msg) from None
    try:
        link = UDPServer(a.host, a.port) if a.udp else PtyPair()
    except TransportError as e:  # a bad --host / --port: the user's input
        raise ValueError(f"--host {a.host!r} --port {a.port}: {e}") from None
    where = (f"udp://{link.address[0]}:{link.address[1]}" if a.udp
             else f"serial://{link.slave_path}")
    try:
        emu = Emulator(link, a.scenario, faults=faults, watchdog_s=a.watchdog)
    except BaseException:
        link.close()
        raise
    try:  # from the first word on, a signal stops the emulator through the handler below
        print(f"emulating the rig at {where} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        from mpa_gym.hardware.realtime import realtime

        with realtime(sched_fifo=a.realtime) as rt:  # the collector off in any case
            for note in rt["notes"]:
                print(f"mpa-gym emulate: {note}", file=sys.stderr, flush=True)
            emu.run(a.duration)
    except KeyboardInterrupt as e:  # Ctrl-C is how an emulator is meant to stop (exit 0)
        emu.stop()
        stopped_by = e
    else:
        stopped_by = None
    finally:
        link.close()
    s = emu.stats
    out = {"device": where, "commands": s.commands, "telemetry_sent": s.telemetry_sent,
           "watchdog_vents": s.watchdog_vents, "corrupt_received": s.corrupt_received}
    if isinstance(stopped_by, Interrupted):  # SIGTERM: the documented 128 + 15
        raise CommandStopped(out, f"interrupted by {stopped_by}; emulator stopped",
                             128 + signal.SIGTERM)
    return out


def _check_device(device: str) -> None:
    """``--device`` before any work: a URL the link can parse (``open_transport``'s forms), and
    a serial device that exists on this machine (a missing one is a typo, not a rig fault)."""
    import urllib.parse

    if not device.strip():
        raise ValueError(f"--device {device!r} is empty: give serial:///dev/ttyX or "
                         "udp://HOST:PORT")
    serial = "://" not in device or device.lower().startswith("serial://")
    path = urllib.parse.urlsplit(device).path if "://" in device else device
    if serial and path and not path.lstrip("/").upper().startswith("COM") \
            and not Path(path).exists():
        raise ValueError(f"--device {device!r}: no serial device {path!r} on this machine "
                         "(serial:///dev/ttyX or udp://HOST:PORT)")


def cmd_rollout(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.agents.rig.rollout import rollout

    gains = _gains(a)  # checked before the emulator starts
    emu = link = None
    device = a.device
    if a.dry_run and device is not None:
        raise ValueError(f"--device {device!r} and --dry-run exclude each other: --dry-run "
                         "starts its own emulator")
    if a.dry_run:
        from mpa_gym.hardware.emulator import Emulator
        from mpa_gym.hardware.transport import UDPServer

        link = UDPServer("127.0.0.1", 0)
        try:
            emu = Emulator(link, a.scenario)
        except BaseException:  # a bad --scenario: close the socket before saying so
            link.close()
            raise
        thread = emu.start_thread()
        device = f"udp://127.0.0.1:{link.address[1]}"
    elif device is None:
        raise ValueError("--device is required unless --dry-run (serial:///dev/ttyX or "
                         "udp://HOST:PORT)")
    else:
        _check_device(device)
    from mpa_gym.hardware.env import HardwareFault
    from mpa_gym.hardware.transport import TransportError

    try:
        out = rollout(a.policy, device, a.log, a.episodes, a.scenario, a.control_hz,
                      a.episode_s, realtime=a.realtime, gains=gains)
    except (HardwareFault, TransportError) as e:  # the rig is vented; the log is on disk
        raise CommandStopped(None, f"STOPPED, rig vented: {e} (log: {a.log})", 3) from None
    except KeyboardInterrupt as e:
        signum = getattr(e, "signum", signal.SIGINT)
        raise CommandStopped(None, f"interrupted by {signal.Signals(signum).name}; rig vented "
                             f"(log: {a.log})", 128 + signum) from None
    finally:
        if emu is not None:
            emu.stop()
            thread.join(timeout=2.0)
            link.close()
    if "stopped" in out:
        raise CommandStopped(out, f"STOPPED, rig vented: {out['stopped']} (log: {a.log})", 3)
    return out


def show_rollout(o: dict[str, Any]) -> str:
    lines = [f"log: {o['log']}"]
    if o.get("told_delays_s") is not None:  # a policy that observes the rig's delays
        dead, lag = o["told_delays_s"]
        lines.append(f"the policy was told the rig's dead time {dead * 1e3:g} ms and lag "
                     f"{lag * 1e3:g} ms (scenario {o['scenario']!r}'s plant; roll out with the "
                     "scenario `mpa-gym identify --out` wrote for this rig to tell it the rig's)")
    if o.get("predicted_mm"):  # the supervisor's start, chosen on the scenario's plant
        pct = o.get("predicted_stiffness_pct") or {}
        lines.append("predicted on the model (scenario " + repr(o["scenario"]) + "'s plant), "
                     "position RMSE [mm]" + (" / stiffness RMSE [%]" if pct else "") + ": "
                     + ", ".join(f"{c} " + ("unstable" if v is None else f"{v:.3f}" + (
                         f" / {pct[c]:.2f}" if pct.get(c) is not None else ""))
                         for c, v in o["predicted_mm"].items()))
    for i, m in enumerate(o["episodes"]):
        lines.append(f"episode {i}: position RMSE {m['position_rmse_mm']:.3f} mm, max "
                     f"{m['position_max_mm']:.3f} mm, stiffness RMSE "
                     f"{m['stiffness_rmse_pct']:.2f} %, saturation {m['saturation_pct']:.1f} %"
                     + (f", STOPPED: {m['fault']}" if "fault" in m else ""))
        if o.get("stages"):  # a supervised run: who drove
            lines.append(f"  hand-over: {m['hand_overs']} (the figures above are the "
                         "supervised loop's)" if m.get("hand_overs") else
                         "  no hand-over: the policy drove every step")
    t = o["timing"]
    ms = lambda v: "–" if v is None or v != v else f"{v:.3f} ms"  # noqa: E731
    lines.append(f"loop {t['control_hz']:g} Hz: {t['overruns']} overruns in {t['steps']} steps, "
                 f"p99 jitter {ms(t['p99_jitter_ms'])}, median command latency "
                 f"{ms(t['median_latency_ms'])}")
    if t.get("realtime") is not None:
        rt = t["realtime"]
        lines.append(f"real-time scheduling: {'SCHED_FIFO' if rt['sched_fifo'] else 'no'}"
                     + "".join(f"; {n}" for n in rt["notes"]))
    return "\n".join(lines)


IDENTIFY_MODES = {"--log": ("--out", "--scenario", "--plot", "--holdout", "--session"),
                  "--coverage": ("--seed", "--episode-s", "--jobs", "--coverage-dir")}


def cmd_identify(a: argparse.Namespace) -> dict[str, Any]:
    if a.coverage is not None:
        from mpa_gym.agents.rig.coverage import coverage

        if a.log is not None:
            raise ValueError("--coverage draws its own rigs and logs; give it without --log")
        _only_with(a, "--coverage", IDENTIFY_MODES["--log"])
        if a.coverage_dir is not None:
            check_out_dir("--coverage-dir", a.coverage_dir)
        return coverage(a.coverage, a.seed, a.episode_s, a.jobs, a.coverage_dir)
    from mpa_gym.agents.rig.identify import identify

    if a.log is None:
        raise ValueError("--log is required (a rollout log; or --coverage N)")
    _only_with(a, "--log (one fit)", IDENTIFY_MODES["--coverage"])
    # the outputs, before the fit: a folder, a name matplotlib would extend, an unwritable place
    plot = a.plot if a.plot is not None else str(Path(a.log).with_suffix(".identify.png"))
    for flag, path, kinds in (("--out", a.out, (".yaml", ".yml")),
                              ("--plot", plot, (".png", ".pdf", ".svg"))):
        if path is None:
            continue
        if Path(path).is_dir() or Path(path).suffix.lower() not in kinds:
            raise ValueError(f"{flag} {path!r} must be a file name ending in "
                             f"{' or '.join(kinds)}")
        check_out_dir(flag, str(Path(path).parent))
        if Path(path).exists():
            try:
                Path(path).open("a").close()  # appending changes nothing
            except OSError as e:
                raise ValueError(f"{flag} {path!r} cannot be written: {e.strerror}") from None
    return identify(a.log, a.out, a.scenario, plot, a.holdout, session=a.session)


def show_identify(o: dict[str, Any]) -> str:
    if "coverage" in o:
        from mpa_gym.agents.rig.coverage import show as show_coverage

        return show_coverage(o)
    from mpa_gym.agents.rig.identify import show

    return show(o)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mpa-gym",
        description="McKibben-actuated leg: analytic design, stability analysis, simulation, "
                    "training, evaluation and the rig.")
    parser.add_argument("--version", action="version",
                        version=f"mpa-gym {mpa_gym.__version__} (Python {sys.version.split()[0]})")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, help_: str, run: Any, show: Any) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
        p.set_defaults(run=run, show=show, parser=p)
        return p

    _add_design_flags(add("design", "feedforward pressures (Eq. 16/22/25) and stiffness (Eq. 23) "
                          "over one period", cmd_design, show_design))
    _add_design_flags(add("analyze", "Theorem 1 and Floquet multipliers of a design",
                          cmd_analyze, show_analyze), samples=False)
    p = add("simulate", "run the nominal feedforward against a scenario's plant", cmd_simulate,
            show_simulate)
    p.add_argument("--scenario", required=True, metavar="NAME_OR_YAML_PATH",
                   help="a name in configs/scenarios (nominal, initial_error, impulse, "
                        "gamma_mismatch, mass_mismatch, kmax, kmin, load_1kg, load_1kg_kmin) "
                        "or a YAML file")
    p.add_argument("--dt", type=float, default=5e-3, metavar="S", help="RK4 step [s]")
    p.add_argument("--output-dt", type=float, default=0.01, metavar="S",
                   help="spacing of the printed samples [s]")
    p = add("figures", "write the paper's figures, reproduced in simulation, as PNGs",
            cmd_figures, show_figures)
    p.add_argument("--out", default="figures", metavar="DIR", help="output folder")
    p = add("train", "train PPO from an rl-zoo style config (default configs/ppo_residual.yaml)",
            cmd_train, show_train)
    p.add_argument("--config", default=None, metavar="YAML", help="training config")
    p.add_argument("--run-dir", default=None, metavar="DIR",
                   help="run folder (default runs/<env>-<time>-s<seed>)")
    p.add_argument("--seed", type=int, default=None, help="overrides the config's seed")
    p.add_argument("--scenario", default=None, metavar="NAME_OR_YAML",
                   help="train on this scenario instead of the config's (e.g. the plant of "
                        "`mpa-gym identify --out`, randomised over its uncertainty)")
    p.add_argument("--resume", default=None, metavar="RUN_DIR",
                   help="continue a run (step count, model, normaliser, evaluations)")
    p.add_argument("--n-timesteps", type=int, default=None, metavar="N",
                   help="env steps to train (default: the config's, or what remains on resume)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, metavar="SEED",
                   help="train one run per seed, in parallel processes, into <run-dir>-s<SEED>")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="with --seeds: processes at once (default: the cores)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--eval-worker", action=argparse.BooleanOptionalAction, default=None,
                   help="held-out evaluations in a second process while training goes on "
                        "(default: when this process may use two cores and the budget spans "
                        "two evaluation intervals of at least 10,000 env steps)")
    p = add("evaluate", "every controller on the paper's scenarios and held-out plants",
            cmd_evaluate, show_evaluate)
    p.add_argument("--policy", nargs="+", default=["ff", "pid", "mbfb"],
                   metavar="RUN_DIR|ff|pid|mbfb|afc|rc|module:Class",
                   help="controllers (default ff pid mbfb); module:Class: your own "
                        "(docs/design.md, \"Your own controller\")")
    p.add_argument("--gains", default=None, metavar="FILE.yaml",
                   help="the baselines' gains (`mpa-gym tune-baselines --out` writes one)")
    p.add_argument("--scenarios", nargs="+", default=None, metavar="NAME_OR_YAML",
                   help="default: the paper's scenarios and the held-out plants")
    p.add_argument("--out", default="runs/eval", metavar="DIR", help="report folder")
    from mpa_gym.agents.learned.config import EVAL_SEED

    p.add_argument("--seed", type=int, default=EVAL_SEED,
                   help="episode seed (default %(default)s: no training env uses seeds this high)")
    p.add_argument("--no-robustness", action="store_true",
                   help="skip the robustness sweep (grids of dead time x load and hysteresis x "
                        "slider friction, easy/medium/hard levels; ~7 s per controller)")
    p.add_argument("--random-rigs", type=int, default=0, metavar="N",
                   help="also run every controller on N real-rig plants drawn at random from "
                        "configs/rigs/random.yaml (reference periods 2-4 s; ~0.3 s per rig and "
                        "controller) and audit the supervisor and the policy alone on them")
    p.add_argument("--rigs-seed", type=int, default=None, metavar="S",
                   help="the random rigs' draws (default: rigs.RIGS_SEED, beyond the seeds of "
                        "training, evaluation and calibration)")
    p = add("tune-baselines", "tune the pid / mbfb / rc gains on a PPO config's training plants "
            "and their undamped twins (Optuna TPE, mean position RMSE; unstable counts as "
            "failed)", cmd_tune_baselines, show_tune_baselines)
    p.add_argument("--policy", nargs="+", default=["pid", "mbfb"], choices=["pid", "mbfb", "rc"],
                   help="the baselines to tune (default: pid mbfb; rc's search space is its "
                        "learning gain and delay margin)")
    p.add_argument("--config", default=None, metavar="YAML",
                   help="PPO config whose training scenario gives the plants (default: the "
                        "default PPO config, mpa_gym.agents.learned.config.DEFAULT_CONFIG)")
    p.add_argument("--n-trials", type=int, default=80, metavar="N", help="Optuna trials each")
    p.add_argument("--n-plants", type=int, default=16, metavar="N",
                   help="plants drawn from the training ranges (each adds its undamped twin)")
    p.add_argument("--seed", type=int, default=0, help="plant draws and sampler seed")
    p.add_argument("--episode-s", type=float, default=None, metavar="S",
                   help="episode length per plant (default 15 s; rc learns over periods: "
                        "its gains were tuned with 30)")
    p.add_argument("--out", default=None, metavar="FILE.yaml",
                   help="also write the tuned gains as a gains file (evaluate / rollout / "
                        "bench --loop --gains FILE, a run config's supervisor.gains)")
    p = add("calibrate", "choose a run's supervisor levels and fallback order on its training "
            "plants (mpa_gym.agents.evaluation.calibrate)", cmd_calibrate, show_calibrate)
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run folder of mpa-gym train")
    p.add_argument("--n-plants", type=int, default=None, metavar="N",
                   help="draws of the run's training randomisation (default 48)")
    p.add_argument("--episode-s", type=float, default=None, metavar="S",
                   help="episode length on each plant [s] (default 24)")
    p.add_argument("--write", action="store_true",
                   help="write the levels and order into RUN_DIR/config.yaml")
    p = add("tune", "tune hyper-parameters on Optuna; workers sharing --storage and --study-name "
            "share the study", cmd_tune, show_tune)
    p.add_argument("--config", default=None, metavar="YAML",
                   help="base config with its search space in mpa_gym.tune (default "
                        "configs/ppo_residual.yaml)")
    p.add_argument("--storage", default="sqlite:///runs/optuna.db", metavar="URL",
                   help="sqlite:///FILE (default runs/optuna.db), any SQLAlchemy URL "
                        "(postgresql://USER@HOST:PORT/DB) or journal:FILE (a shared disk)")
    p.add_argument("--study-name", default="ppo_residual", metavar="NAME")
    p.add_argument("--n-trials", type=int, default=10, metavar="N",
                   help="trials this worker runs at most (default 10)")
    p.add_argument("--max-total-trials", type=int, default=None, metavar="M",
                   help="cap on the study's trials over all workers")
    p.add_argument("--seeds-per-trial", type=int, default=1, metavar="S",
                   help="each trial trains S seeds and averages them (default 1)")
    p.add_argument("--n-timesteps", type=int, default=None, metavar="T",
                   help="env steps per seed (default: the config's)")
    p.add_argument("--objective", choices=["both", "position"], default="both",
                   help="both: Pareto front of held-out position RMSE and stiffness error, no "
                        "pruning; position: position RMSE alone, median pruning")
    p.add_argument("--heartbeat", type=int, default=60, metavar="S",
                   help="SQL storages: a worker silent for 2 S is dead, its trial FAIL")
    p.add_argument("--heldout", nargs="+", default=None, metavar="NAME_OR_YAML",
                   help="scenarios of the objectives (default heldout_a/b/c/bladder)")
    p.add_argument("--out-dir", default=None, metavar="DIR",
                   help="trial run folders (default runs/tune/<study>)")
    p.add_argument("--best", default=None, metavar="STUDY",
                   help="write the config of STUDY's best trial (with --out) and exit")
    p.add_argument("--trial", type=int, default=None, metavar="N",
                   help="with --best: this trial instead of the lowest position RMSE")
    p.add_argument("--out", default=None, metavar="FILE.yaml", help="with --best")
    p = add("emulate", "play the rig (plant in real time, wire protocol, watchdog) on a pty or UDP",
            cmd_emulate, lambda o: json.dumps(o))
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--serial", action="store_true", help="on a pseudo-terminal (prints its path)")
    g.add_argument("--udp", action="store_true", help="on UDP (prints host:port)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0, help="UDP port (0: any free one)")
    p.add_argument("--scenario", default="nominal", metavar="NAME_OR_YAML",
                   help="the plant the emulator plays")
    from mpa_gym.hardware.emulator import WATCHDOG_S

    p.add_argument("--watchdog", type=float, default=WATCHDOG_S, metavar="S",
                   help="vent after this long without commands [s] (default %(default)s)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S s")
    p.add_argument("--realtime", action="store_true",
                   help="real-time (SCHED_FIFO) priority, as a device's firmware has, if "
                        "permitted")
    for flag, _, kind in FAULT_FLAGS:
        p.add_argument(flag, type=float, default=0.0, help=f"fault injection ({kind})")
    p = add("rollout", "roll a controller out on the rig (or, --dry-run, on the emulator)",
            cmd_rollout, show_rollout)
    p.add_argument("--policy", required=True,
                   metavar="RUN_DIR|ff|pid|mbfb|afc|rc|excite|module:Class",
                   help="a run folder, a baseline, your own controller class, or excite: the "
                        "safe excitation whose log `mpa-gym identify` fits")
    p.add_argument("--gains", default=None, metavar="FILE.yaml",
                   help="the baselines' gains (`mpa-gym tune-baselines --out` writes one)")
    p.add_argument("--device", default=None, metavar="serial:///dev/ttyX|udp://HOST:PORT")
    p.add_argument("--dry-run", action="store_true", help="start an emulator and use it")
    p.add_argument("--scenario", default="nominal", metavar="NAME_OR_YAML",
                   help="reference and feedforward design (the plant is the rig)")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--episode-s", type=float, default=None, metavar="S")
    from mpa_gym.hardware.env import CONTROL_HZ

    p.add_argument("--control-hz", type=float, default=CONTROL_HZ, metavar="HZ",
                   help="control rate (default %(default)s; at most 500)")
    p.add_argument("--log", default="runs/rollout.jsonl", metavar="FILE",
                   help="per-step JSON-lines log, written as it happens")
    p.add_argument("--realtime", action="store_true",
                   help="real-time (SCHED_FIFO) priority for the episodes, as far as "
                        "permitted (the timing report says what was granted; the garbage "
                        "collector is off during them in any case)")
    p = add("identify", "fit the plant (mass, γ, C1, C2, regulator lag, dead time and slew, "
            "friction) to a rollout log, with intervals; validate on a held-out stretch",
            cmd_identify, show_identify)
    p.add_argument("--log", default=None, metavar="LOG",
                   help="a rollout log, best of `mpa-gym rollout --policy excite`")
    p.add_argument("--out", default=None, metavar="FILE.yaml",
                   help="write a scenario whose plant is the estimate and whose randomize "
                        "draws from the intervals (for train, evaluate, emulate --scenario)")
    p.add_argument("--scenario", default="nominal", metavar="NAME_OR_YAML",
                   help="reference and inputs of the written scenario, and the nominal values "
                        "the fit starts from (default nominal)")
    p.add_argument("--plot", default=None, metavar="PNG",
                   help="logged vs simulated on the held-out stretch (default LOG.identify.png)")
    p.add_argument("--holdout", type=float, default=0.2, metavar="FRAC",
                   help="share of the log held out for validation (default 0.2)")
    p.add_argument("--session", type=int, default=None, metavar="K",
                   help="which session of the log to fit (index, negative from the end; "
                        "default the newest)")
    g = p.add_argument_group("coverage check (agents/rig/coverage.py): instead of --log, draw N "
                             "rigs from configs/rigs/coverage.yaml, excite each on an emulator "
                             "process in real time, identify, print the share whose intervals "
                             "hold the truth")
    g.add_argument("--coverage", type=int, default=None, metavar="N", help="rigs to draw")
    g.add_argument("--seed", type=int, default=0, help="of the draws (default 0)")
    g.add_argument("--episode-s", type=float, default=30.0, metavar="S",
                   help="excitation per rig [s] (default 30; at least 12)")
    g.add_argument("--jobs", type=int, default=1, metavar="J",
                   help="rigs at a time (default 1; each needs a core in real time)")
    g.add_argument("--coverage-dir", default=None, metavar="DIR",
                   help="logs, fits and coverage.jsonl (default a new temporary folder)")
    p = add("bench", "step rates of the envs beside CartPole-v1 and Pendulum-v1, same run",
            cmd_bench, show_bench)
    p.add_argument("--seconds", type=float, default=1.0, metavar="S",
                   help="time per measurement [s] (default 1)")
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 1024, 4096], metavar="N",
                   help="vector env sizes (default 1 64 1024 4096)")
    p.add_argument("--inference", default=None, metavar="RUN_DIR",
                   help="instead: time per action of a trained run, deployed (compiled) path "
                        "against SB3's predict, with a device emulator in another process")
    p.add_argument("--actions", type=int, default=20_000, metavar="N",
                   help="--inference: actions timed on the deployed path (SB3: N/10)")
    p.add_argument("--no-emulator", action="store_true",
                   help="--inference: without the emulator process")
    p.add_argument("--loop", default=None, metavar="RUN_DIR|ff|pid|mbfb|afc|rc|module:Class",
                   help="instead: the rig loop's overruns, jitter and latency against a device "
                        "emulator in another process, each run beside the machine's floor (the "
                        "same wait with no work)")
    p.add_argument("--control-hz", type=float, default=100.0, metavar="HZ",
                   help="--loop: control rate (default 100)")
    p.add_argument("--loop-s", type=float, default=10.0, metavar="S",
                   help="--loop: seconds per run (default 10)")
    p.add_argument("--repeats", type=int, default=3, metavar="N",
                   help="--loop: floor/loop pairs (default 3)")
    p.add_argument("--rig", default="nominal", metavar="NAME_OR_YAML",
                   help="--loop: the plant the emulator plays (default nominal)")
    p.add_argument("--gains", default=None, metavar="FILE.yaml",
                   help="--loop: the baselines' gains (`mpa-gym tune-baselines --out`)")
    return parser


def _refuse_unknown_flags(parser: argparse.ArgumentParser, argv: list[str]) -> None:
    """Name a flag the subcommand does not have, before argparse's own check of the required
    ones (which would otherwise be the only error shown: '--scenario is required' for
    ``simulate --scenari x``)."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    if not argv or argv[0] not in sub.choices:
        return
    p = sub.choices[argv[0]]
    known = {s for act in p._actions for s in act.option_strings}
    for tok in argv[1:]:
        flag = tok.split("=", 1)[0]
        if flag.startswith("--") and flag != "--" and not any(k.startswith(flag) for k in known):
            p.error(f"unrecognized arguments: {tok}")


def _refuse_empty(a: argparse.Namespace) -> None:
    """An empty string given to a text option (a path, a name, a URL) is refused by name: read
    as 'not given', ``--config ""`` would train the default config and ``--run-dir ""`` would
    write into the working folder."""
    for act in a.parser._actions:
        value = getattr(a, act.dest, None)
        if act.type is None and (value == "" or (isinstance(value, list) and "" in value)):
            name = act.option_strings[-1] if act.option_strings else act.metavar or act.dest
            raise ValueError(f"{name} is empty: expected {act.metavar or act.dest.upper()}")


def _terminate(signum: int, frame: Any) -> None:
    raise Interrupted(signum)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one subcommand. Exit codes: 0 done; 2 bad input (the message names the field, the
    value and the allowed range); 1 training stopped by its NaN guard; 3 a rollout stopped by a
    safety check (rig vented); 130 / 143 interrupted by Ctrl-C / SIGTERM (what was reached is
    saved, the rig vented)."""
    parser = build_parser()
    _refuse_unknown_flags(parser, list(sys.argv[1:] if argv is None else argv))
    a = parser.parse_args(argv)
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        _refuse_empty(a)
        out = a.run(a)
    except ModuleNotFoundError as e:
        top = (e.name or "").split(".")[0]
        # only an optional package that is not installed at all: a submodule missing from an
        # installed one is a genuine fault, whose traceback must show
        if top not in EXTRAS or importlib.util.find_spec(top) is not None:
            raise
        print(f"mpa-gym {a.command}: error: needs {top}, which the '{EXTRAS[top]}' extra "
              f"installs: pip install 'mpa-gym[{EXTRAS[top]}]'", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError) as e:  # bad input: names the field, value and range
        print(f"mpa-gym {a.command}: error: {e}", file=sys.stderr)
        return 2
    except CommandStopped as e:
        if e.out is not None:
            print(json.dumps(e.out) if a.json else a.show(e.out), flush=True)
        print(f"mpa-gym {a.command}: {e.message}", file=sys.stderr)
        return e.code
    except KeyboardInterrupt as e:
        signum = getattr(e, "signum", signal.SIGINT)
        print(f"mpa-gym {a.command}: interrupted by {signal.Signals(signum).name}",
              file=sys.stderr)
        return 128 + signum
    except OSError as e:  # the machine's side (disk full, permissions): one line, no traceback
        print(f"mpa-gym {a.command}: error: {e}", file=sys.stderr)
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    print(json.dumps(out) if a.json else a.show(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
