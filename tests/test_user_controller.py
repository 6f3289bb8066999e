"""Your own controller in every command (``module:Class``), and gains files: a class defined
here, imported by its module path, evaluated (report and sweep) and rolled out against the
device emulator in another process; bad specs refused by name; ``tune-baselines --out`` →
``evaluate --gains`` gives the numbers of the controller built with the file's gains."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import textwrap

import gymnasium as gym
import pytest
import yaml
from conftest import REALTIME

import mpa_gym  # noqa: F401
from mpa_gym.agents.cli import main
from mpa_gym.agents.controllers.baselines import make_baseline
from mpa_gym.agents.evaluation.episodes import metrics, run_episode
from mpa_gym.agents.evaluation.evaluate import evaluate
from mpa_gym.agents.evaluation.robustness import Grid, robustness
from mpa_gym.agents.learned.config import parse_config
from mpa_gym.agents.learned.policies import supervise
from mpa_gym.hardware.emulator import EmulatorProcess

# A user's controller module: a proportional law whose gain depends on the scenario's plan (its
# reference period), so that a report which ran one scenario's object on another's rows would
# give other numbers; and a class without predict.
MODULE = textwrap.dedent('''
    import numpy as np

    from mpa_gym.task.contract import OBS_X, OBS_XREF


    class Proportional:
        """u = K (3 s / T) e [bar], e = X̂ − X; residual (+u, −u)."""

        gain_bar_per_m = 10.0

        def __init__(self, plan, params):
            self.scale = plan.cfg.residual_scale_bar
            self.k = self.gain_bar_per_m * 3.0 / plan.design.reference.period

        def predict(self, observation, state=None, episode_start=None, deterministic=True):
            obs = np.atleast_2d(observation)
            u = self.k * (obs[:, OBS_XREF] - obs[:, OBS_X])
            a = np.clip(np.stack([u, -u], axis=-1) / self.scale, -1.0, 1.0).astype(np.float32)
            return (a[0] if np.ndim(observation) == 1 else a), state


    class NoPredict:
        def __init__(self, plan, params):
            pass
''')
SPEC = "my_controllers:Proportional"
LOADED = {"name": "loaded", "duration_s": 9.0, "plant": {"extra_mass_kg": 1.0}}
FAST = {"name": "fast", "duration_s": 8.0, "plant": {"extra_mass_kg": 0.5},
        "reference": {"x0_m": 0.8, "amp_m": 0.02, "period_s": 2.0}}
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """The module on sys.path here and on PYTHONPATH for child processes."""
    (tmp_path / "my_controllers.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tmp_path), os.environ.get("PYTHONPATH", REPO)])}
    yield env
    sys.modules.pop("my_controllers", None)


def _alone(scenario, seed):
    """[mm] the class built for ``scenario`` and run on its own env: not through any spec."""
    import my_controllers

    from mpa_gym.task.plan import make_plan

    policy = my_controllers.Proportional(make_plan(scenario), None)
    tr = run_episode(gym.make("MPALegResidual-v0", scenario=scenario), policy, seed)
    period = scenario.get("reference", {}).get("period_s", 3.0)
    return metrics(tr, period, None)["position_rmse_mm"]


def test_a_user_class_is_evaluated_per_scenario_like_a_baseline(user_module):
    # Two scenarios of different periods: each row's numbers are its own scenario's object's
    # (the class cannot be stacked: evaluation runs one object per scenario), in the report, in
    # the no-harm audit (as a controller under test) and in the sweep.
    report = evaluate([SPEC, "ff", "pid"], [LOADED, FAST])
    for sc in (LOADED, FAST):
        got = report["results"][sc["name"]][SPEC]["position_rmse_mm"]
        assert got == pytest.approx(_alone(sc, report["seed"]), rel=1e-12), sc["name"]
    # the loop acts: the feedforward's sag under the load (10-20 mm) cut by its loop gain
    # (~0.7 at DC: to ~0.6 of it)
    for sc in ("loaded", "fast"):
        row = report["results"][sc]
        assert row[SPEC]["position_rmse_mm"] < 0.75 * row["ff"]["position_rmse_mm"], sc
    assert report["no_harm"][SPEC]["checked"] == 2
    assert "your own controller" in report["controllers"][SPEC]
    grid = Grid("g", "pressure_lag_s", (0.0, 0.03), "extra_mass_kg", (0.0, 1.0))
    rob = robustness([SPEC], grids=(grid,), levels={}, kicks={})
    cells = rob["grids"]["g"]["controllers"][SPEC]
    assert [len(r) for r in cells] == [2, 2]
    assert cells[0][0]["position_rmse_mm"] < 0.01  # the nominal cell: nothing to correct


@pytest.mark.parametrize("argv, said", [
    (["evaluate", "--policy", "nosuch_module:Ctrl"], ["--policy", "nosuch_module:Ctrl",
                                                      "no module named 'nosuch_module'"]),
    (["evaluate", "--policy", "my_controllers:Nope"], ["--policy", "my_controllers:Nope",
                                                       "has no 'Nope'"]),
    (["evaluate", "--policy", "my_controllers:NoPredict"],
     ["--policy", "my_controllers:NoPredict", "not a controller class"]),
    (["rollout", "--policy", "nosuch_module:Ctrl", "--dry-run"],
     ["--policy", "nosuch_module:Ctrl", "no module named"]),
    (["bench", "--loop", "my_controllers:NoPredict", "--repeats", "1"],
     ["--loop", "my_controllers:NoPredict", "not a controller class"]),
])
def test_a_bad_spec_exits_2_naming_the_flag_and_value(user_module, tmp_path, capsys, argv,
                                                       said):
    code = main([*argv, *(["--out", str(tmp_path / "ev")] if argv[0] == "evaluate" else []),
                 *(["--log", str(tmp_path / "r.jsonl")] if argv[0] == "rollout" else [])])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert all(s in err for s in said), err
    assert not (tmp_path / "r.jsonl").exists()  # refused before the log was opened


@REALTIME
def test_a_user_class_rolls_out_against_the_emulator_process(user_module, tmp_path):
    # The rig: the emulator in another process playing the 1 kg leg; the controller: the class
    # imported in a third (the rollout command, the module on its PYTHONPATH). Its loop holds the
    # sag under 0.75 of the feedforward's on that plant in the simulator (~0.6 in simulation).
    ff = metrics(run_episode(gym.make("MPALegResidual-v0", scenario=LOADED),
                             make_baseline("ff", LOADED), 0), 3.0, None)["position_rmse_mm"]
    log = tmp_path / "r.jsonl"
    with EmulatorProcess(LOADED, ("--watchdog", "0.5")) as emu:
        out = subprocess.run(
            [sys.executable, "-m", "mpa_gym.agents.cli", "rollout", "--policy", SPEC,
             "--device", emu.url, "--episode-s", "9", "--log", str(log), "--json"],
            env=user_module, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert res["episodes"][0]["position_rmse_mm"] < 0.75 * ff
    session = json.loads(log.read_text().splitlines()[0])
    assert session["event"] == "session" and session["policy"] == SPEC


def test_tuned_gains_file_round_trip(tmp_path, capsys):
    # tune-baselines --out writes the study's best gains (those it prints); evaluate --gains
    # runs pid with a file's gains: the same numbers as pid built here with them (read with
    # PyYAML, not the loader). A budget of a few trials keeps the enqueued defaults as the
    # best, so the file's kp is then doubled: evaluate must follow the file, not the defaults.
    path = tmp_path / "gains.yaml"
    assert main(["tune-baselines", "--policy", "pid", "--n-trials", "2", "--n-plants", "1",
                 "--episode-s", "12", "--out", str(path), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)["results"][0]
    data = yaml.safe_load(path.read_text())
    assert data["gains"]["pid"] == printed["gains"]
    assert data["tuned_on"]["pid"]["mean_position_rmse_mm"] == printed["mean_position_rmse_mm"]
    data["gains"]["pid"]["kp_bar_per_m"] *= 2.0
    path.write_text(yaml.safe_dump(data))
    gains = data["gains"]["pid"]
    default = make_baseline("pid", LOADED)
    assert main(["evaluate", "--policy", "pid", "--gains", str(path), "--scenarios",
                 str(_scenario_file(tmp_path)), "--no-robustness",
                 "--out", str(tmp_path / "ev")]) == 0
    report = json.loads((tmp_path / "ev" / "report.json").read_text())
    mine, theirs = (metrics(run_episode(gym.make("MPALegResidual-v0", scenario=LOADED), pol,
                                        report["seed"]), 3.0, None)
                    for pol in (dataclasses.replace(default, **gains), default))
    got = report["results"]["loaded"]["pid"]
    for k in ("position_rmse_mm", "stiffness_rmse_pct", "return"):
        assert got[k] == pytest.approx(mine[k], rel=1e-12), k
    assert got["position_rmse_mm"] != pytest.approx(theirs["position_rmse_mm"], rel=1e-3)
    assert "given with --gains" in report["controllers"]["pid"]
    # a run config's supervisor reads the same file: its pid fallback runs with those gains
    raw = yaml.safe_load(open(os.path.join(REPO, "configs", "ppo_residual.yaml")))
    raw["mpa_gym"]["supervisor"] = {
        "gains": str(path), "stages": [{"controller": "policy", "monitors": ["divergence"]},
                                       {"controller": "pid"}]}
    sup = supervise(make_baseline("ff"), parse_config(raw, "cfg.yaml"))
    assert {k: getattr(sup.controllers[0], k) for k in gains} == gains


def test_a_bad_gains_file_exits_2_naming_it(tmp_path, capsys):
    path = tmp_path / "g.yaml"
    for text, said in (("gains: {pid: {kp: 3}}", "unknown key(s) ['kp']"),
                       ("gains: {pid: {kp_bar_per_m: -1}}", "kp_bar_per_m=-1"),
                       ("gains: {zz: {}}", "unknown key(s) ['zz']"),
                       ("[1, 2", "not valid YAML")):
        path.write_text(text)
        code = main(["evaluate", "--policy", "pid", "--gains", str(path), "--out",
                     str(tmp_path / "ev")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and "--gains" in err and said in err, err


def _scenario_file(tmp_path):
    p = tmp_path / "loaded.yaml"
    p.write_text(yaml.safe_dump(LOADED))
    return p
