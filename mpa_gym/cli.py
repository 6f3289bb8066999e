"""The `mpa-gym` command: design, analyze, simulate and figures (DESIGN.md's CLI contract).

Every subcommand prints a readable table by default and one JSON object with ``--json``.
SI units in JSON unless a key says ``_bar``; pressures are given and shown in bar.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from mpa_gym.design import (
    P_MAX_DEFAULT,
    ConstantStiffness,
    FeedforwardDesign,
    FlexorPattern,
    Reference,
    StiffnessEnvelope,
    feasible_stiffness_range,
    mode_pattern,
)
from mpa_gym.model.params import BAR, DEFAULT_PARAMS, check_range


def _add_design_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("reference (Eq. 21) and inputs (Eq. 22 / Table 1 / Eq. 25)")
    g.add_argument("--x0", type=float, default=0.8, metavar="M", help="X̂0 [m] (default 0.8)")
    g.add_argument("--amp", type=float, default=0.02, metavar="M", help="Â [m] (default 0.02)")
    g.add_argument("--period", type=float, default=3.0, metavar="S", help="T [s] (default 3)")
    g.add_argument("--pf-mean", type=float, default=0.5, metavar="BAR",
                   help="P'_f0 [bar] (default 0.5, Fig. 3)")
    g.add_argument("--pf-amp", type=float, default=0.0, metavar="BAR", help="A_f [bar] (default 0)")
    x = g.add_mutually_exclusive_group()
    x.add_argument("--mode", type=int, choices=(1, 2, 3), help="Table 1 preset for P'_f0, A_f")
    x.add_argument("--stiffness", choices=("kmax", "kmin"),
                   help="Eq. (25) design for the Fig. 11 envelope instead of Eq. (22)")
    x.add_argument("--stiffness-const", type=float, metavar="N_PER_M",
                   help="Eq. (25) design for a constant k̂ [N/m]")
    g.add_argument("--samples", type=int, default=61, metavar="N",
                   help="samples over one period (default 61)")
    g.add_argument("--p-max", type=float, default=P_MAX_DEFAULT / BAR, metavar="BAR",
                   help="upper pressure limit [bar] (default 7)")


def _design_from_args(a: argparse.Namespace) -> FeedforwardDesign:
    check_range("--x0", a.x0, 0.0, low_open=True, unit="m")
    check_range("--amp", a.amp, 0.0, unit="m")
    check_range("--period", a.period, 0.0, low_open=True, unit="s")
    check_range("--p-max", a.p_max, 0.0, low_open=True, unit="bar")
    check_range("--pf-mean", a.pf_mean, 0.0, a.p_max, unit="bar")
    check_range("--pf-amp", a.pf_amp, -a.pf_mean, a.pf_mean, unit="bar",
                note="Eq. 22: |A_f| <= P'_f0")
    ref = Reference(x0=a.x0, amp=a.amp, period=a.period)
    if a.stiffness is not None:
        return FeedforwardDesign(ref, stiffness=StiffnessEnvelope(a.stiffness, ref))
    if a.stiffness_const is not None:
        return FeedforwardDesign(ref, stiffness=ConstantStiffness(a.stiffness_const))
    if a.mode is not None:
        return FeedforwardDesign(ref, flexor=mode_pattern(a.mode, a.period))
    return FeedforwardDesign(ref, flexor=FlexorPattern(a.pf_mean * BAR, a.pf_amp * BAR, a.period))


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
    from mpa_gym.analysis.simulate import simulate

    return simulate(a.scenario, DEFAULT_PARAMS, dt=a.dt, output_dt=a.output_dt).to_json()


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

    return {"files": [str(p) for p in make_figures(a.out)]}


def show_figures(o: dict[str, Any]) -> str:
    return "wrote:\n  " + "\n  ".join(o["files"])


def cmd_bench(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym import bench

    if not 0.05 <= a.seconds <= 60:
        raise ValueError(f"--seconds={a.seconds} is outside the allowed range [0.05, 60] s")
    return bench.run(a.seconds, tuple(a.sizes))


def show_bench(o: dict[str, Any]) -> str:
    from mpa_gym import bench

    return bench.show(o)


def cmd_train(a: argparse.Namespace) -> dict[str, Any]:
    from agents.train import train

    if a.n_timesteps is not None and a.n_timesteps < 1:
        raise ValueError(f"--n-timesteps={a.n_timesteps} must be >= 1")
    run = train(a.config, a.run_dir, a.seed, a.resume, a.n_timesteps, progress=not a.no_progress)
    from stable_baselines3 import PPO

    steps = int(PPO.load(run / "model.zip", device="cpu").num_timesteps)
    hist = run / "eval" / "evaluations.json"
    last = json.loads(hist.read_text())[-1] if hist.is_file() else None
    return {"run_dir": str(run), "timesteps": steps, "last_evaluation": last}


def show_train(o: dict[str, Any]) -> str:
    lines = [f"run folder: {o['run_dir']}  ({o['timesteps']} env steps)"]
    if o["last_evaluation"]:
        lines.append(f"held-out evaluation at {o['last_evaluation']['timesteps']} steps:")
        for name, m in o["last_evaluation"]["scenarios"].items():
            lines.append(f"  {name:<18} position RMSE {m['position_rmse_mm']:.3f} mm, "
                         f"stiffness error {m['stiffness_rmse_pct']:.2f} %")
    return "\n".join(lines)


def cmd_evaluate(a: argparse.Namespace) -> dict[str, Any]:
    from agents.evaluate import HELDOUT_SCENARIOS, PAPER_SCENARIOS, evaluate, write_report

    scenarios = a.scenarios or [*PAPER_SCENARIOS, *HELDOUT_SCENARIOS]
    report = evaluate(a.policy, scenarios, a.seed)
    paths = write_report(report, a.out)
    return {"results": json.loads(paths["json"].read_text())["results"],
            "report_json": str(paths["json"]), "report_md": str(paths["markdown"]),
            "plots": str(paths["plots"])}


def show_evaluate(o: dict[str, Any]) -> str:
    res = o["results"]
    ctrls = list(next(iter(res.values())))
    rows = [[sc] + [f"{row[c]['position_rmse_mm']:.3f} / {row[c]['stiffness_rmse_pct']:.1f}"
                    for c in ctrls] for sc, row in res.items()]
    return ("position RMSE [mm] / stiffness RMSE [% of k̂], last 3 periods\n"
            + _table(rows, ["scenario", *ctrls])
            + f"\n\nreport: {o['report_md']} (and {o['report_json']}, plots in {o['plots']})")


def cmd_emulate(a: argparse.Namespace) -> dict[str, Any]:
    from mpa_gym.hardware.emulator import Emulator, LinkFaults
    from mpa_gym.hardware.transport import PtyPair, UDPServer

    faults = LinkFaults(latency_s=a.latency, jitter_s=a.jitter, drop_prob=a.drop,
                        late_prob=a.late, corrupt_prob=a.corrupt,
                        position_noise_m=a.position_noise)
    link = UDPServer(a.host, a.port) if a.udp else PtyPair()
    where = (f"udp://{link.address[0]}:{link.address[1]}" if a.udp
             else f"serial://{link.slave_path}")
    print(f"emulating the rig at {where} (Ctrl-C to stop)", file=sys.stderr, flush=True)
    emu = Emulator(link, a.scenario, faults=faults, watchdog_s=a.watchdog)
    try:
        emu.run(a.duration)
    except KeyboardInterrupt:  # Ctrl-C is how an emulator is meant to stop
        emu.stop()
    finally:
        link.close()
    s = emu.stats
    return {"device": where, "commands": s.commands, "telemetry_sent": s.telemetry_sent,
            "watchdog_vents": s.watchdog_vents, "corrupt_received": s.corrupt_received}


def cmd_rollout(a: argparse.Namespace) -> dict[str, Any]:
    from agents.rollout import rollout

    emu = link = None
    device = a.device
    if a.dry_run:
        from mpa_gym.hardware.emulator import Emulator
        from mpa_gym.hardware.transport import UDPServer

        link = UDPServer("127.0.0.1", 0)
        emu = Emulator(link, a.scenario)
        thread = emu.start_thread()
        device = f"udp://127.0.0.1:{link.address[1]}"
    elif device is None:
        raise ValueError("--device is required unless --dry-run (serial:///dev/ttyX or "
                         "udp://HOST:PORT)")
    from mpa_gym.hardware.env import HardwareFault
    from mpa_gym.hardware.transport import TransportError

    try:
        return rollout(a.policy, device, a.log, a.episodes, a.scenario, a.control_hz,
                       a.episode_s)
    except (HardwareFault, TransportError) as e:  # the rig is vented; the log is on disk
        print(f"mpa-gym rollout: stopped, rig vented: {e} (log: {a.log})", file=sys.stderr)
        raise SystemExit(3) from None
    finally:
        if emu is not None:
            emu.stop()
            thread.join(timeout=2.0)
            link.close()


def show_rollout(o: dict[str, Any]) -> str:
    lines = [f"log: {o['log']}"]
    for i, m in enumerate(o["episodes"]):
        lines.append(f"episode {i}: position RMSE {m['position_rmse_mm']:.3f} mm, max "
                     f"{m['position_max_mm']:.3f} mm, stiffness RMSE "
                     f"{m['stiffness_rmse_pct']:.2f} %, saturation {m['saturation_pct']:.1f} %"
                     + (f", STOPPED: {m['fault']}" if "fault" in m else ""))
    t = o["timing"]
    ms = lambda v: "–" if v is None or v != v else f"{v:.3f} ms"  # noqa: E731
    lines.append(f"loop {t['control_hz']:g} Hz: {t['overruns']} overruns, p99 jitter "
                 f"{ms(t['p99_jitter_ms'])}, median command latency "
                 f"{ms(t['median_latency_ms'])}")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mpa-gym",
        description="McKibben-actuated leg: analytic design, stability analysis, simulation.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, help_: str, run: Any, show: Any) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
        p.set_defaults(run=run, show=show)
        return p

    _add_design_flags(add("design", "feedforward pressures (Eq. 16/22/25) and stiffness (Eq. 23) "
                          "over one period", cmd_design, show_design))
    _add_design_flags(add("analyze", "Theorem 1 and Floquet multipliers of a design",
                          cmd_analyze, show_analyze))
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
    p.add_argument("--resume", default=None, metavar="RUN_DIR",
                   help="continue a run (step count, model, normaliser, evaluations)")
    p.add_argument("--n-timesteps", type=int, default=None, metavar="N",
                   help="env steps to train (default: the config's, or what remains on resume)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p = add("evaluate", "every controller on the paper's scenarios and held-out plants",
            cmd_evaluate, show_evaluate)
    p.add_argument("--policy", nargs="+", default=["ff", "pid", "mbfb"],
                   metavar="RUN_DIR|ff|pid|mbfb", help="controllers (default ff pid mbfb)")
    p.add_argument("--scenarios", nargs="+", default=None, metavar="NAME_OR_YAML",
                   help="default: the paper's scenarios and the held-out plants")
    p.add_argument("--out", default="runs/eval", metavar="DIR", help="report folder")
    p.add_argument("--seed", type=int, default=1_000_000,
                   help="episode seed (no training env uses seeds this high)")
    p = add("emulate", "play the rig (plant in real time, wire protocol, watchdog) on a pty or UDP",
            cmd_emulate, lambda o: json.dumps(o))
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--serial", action="store_true", help="on a pseudo-terminal (prints its path)")
    g.add_argument("--udp", action="store_true", help="on UDP (prints host:port)")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0, help="UDP port (0: any free one)")
    p.add_argument("--scenario", default="nominal", metavar="NAME_OR_YAML",
                   help="the plant the emulator plays")
    p.add_argument("--watchdog", type=float, default=0.04, metavar="S",
                   help="vent after this long without commands [s] (default 0.04)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S s")
    for flag, kind in (("--latency", "s"), ("--jitter", "s"), ("--drop", "probability"),
                       ("--late", "probability"), ("--corrupt", "probability"),
                       ("--position-noise", "m")):
        p.add_argument(flag, type=float, default=0.0, help=f"fault injection ({kind})")
    p = add("rollout", "roll a controller out on the rig (or, --dry-run, on the emulator)",
            cmd_rollout, show_rollout)
    p.add_argument("--policy", required=True, metavar="RUN_DIR|ff|pid|mbfb")
    p.add_argument("--device", default=None, metavar="serial:///dev/ttyX|udp://HOST:PORT")
    p.add_argument("--dry-run", action="store_true", help="start an emulator and use it")
    p.add_argument("--scenario", default="nominal", metavar="NAME_OR_YAML",
                   help="reference and feedforward design (the plant is the rig)")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--episode-s", type=float, default=None, metavar="S")
    p.add_argument("--control-hz", type=float, default=100.0, metavar="HZ")
    p.add_argument("--log", default="runs/rollout.jsonl", metavar="FILE",
                   help="per-step JSON-lines log, written as it happens")
    p = add("bench", "step rates of the envs beside CartPole-v1 and Pendulum-v1, same run",
            cmd_bench, show_bench)
    p.add_argument("--seconds", type=float, default=1.0, metavar="S",
                   help="time per measurement [s] (default 1)")
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 1024, 4096], metavar="N",
                   help="vector env sizes (default 1 64 1024 4096)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    a = parser.parse_args(argv)
    try:
        out = a.run(a)
    except (ValueError, FileNotFoundError) as e:  # bad input: names the field, value and range
        print(f"mpa-gym {a.command}: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(out) if a.json else a.show(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
