"""The supervisor's calibration on a run's training plants (agents/evaluation/calibrate.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from mpa_gym.agents.controllers.supervisor import (
    DEFAULT_MONITORS,
    Persistent,
    Stage,
    Supervised,
    SupervisorSpec,
)
from mpa_gym.agents.evaluation.calibrate import running_rms
from mpa_gym.task.contract import OBS_X, OBS_XREF, obs_names
from tests.conftest import tiny_config

DT = 0.01


class _Zero:
    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        return np.zeros((np.atleast_2d(obs).shape[0], 2), dtype=np.float32), state


def test_the_replay_is_the_supervisors_own_running_rms():
    # the offline replay of a monitor over an episode's errors is, step by step, the running
    # RMS the supervisor computes online (its monitor state, until the monitor trips and the
    # next stage restarts it), for every kind of monitor, on errors the replay did not make:
    # a sag, a growing oscillation off the reference period and a kick
    n_period, steps = 100, 1000
    t = np.arange(steps) * DT
    e = np.stack([1.3e-3 * Persistent().level_mm * np.ones(steps),  # trips the default
                  3e-4 * np.exp(t / 3) * np.sin(2 * np.pi * t / 0.7),
                  np.where((t > 2) & (t < 2.1), 2e-2, 0.0)], axis=1)
    tripped = False
    for m in DEFAULT_MONITORS:
        spec = SupervisorSpec((m,) if m.name == "divergence" else (DEFAULT_MONITORS[0], m),
                              (Stage("policy", (m.name,)), Stage("ff")))
        sup = Supervised(_Zero(), _Zero(), DT, n_period * DT, spec)
        obs = np.zeros((3, len(obs_names(residual=True))))
        state = None
        online = np.full((steps, 3), np.nan)
        for k in range(steps):
            obs[:, OBS_XREF] = 0.8
            obs[:, OBS_X] = 0.8 - e[k]
            _, state = sup.predict(obs, state, np.full(3, k == 0))
            policy = state.monitor.stage == 0
            online[k, policy] = np.sqrt(state.monitor.mean_sq[m.name][policy]) * 1e3
        seen = ~np.isnan(online)
        assert seen[-1].any()  # rows the policy keeps to the end
        tripped |= not seen.all()
        # online, e is X̂ − X of an observation X = 0.8 − e: one ulp of 0.8 m (1.1e-16 m) per
        # sample against errors of 1e-4 m and more, accumulated over 1000 steps: < 1e-9
        np.testing.assert_allclose(running_rms(m, e, n_period, DT)[seen], online[seen],
                                   rtol=1e-9, atol=1e-12)
    assert tripped  # and the comparison covered rows up to their trip


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from mpa_gym.agents.training.train import train

    folder = tmp_path_factory.mktemp("cal")
    return train(tiny_config(folder), folder / "run", progress=False)


def test_calibrated_levels_keep_quiet_on_the_plants_the_policy_keeps(tiny_run):
    # --write puts the levels and order into the run's config (the old one kept): each level at
    # least the margin over the highest running RMS on the plants the policy keeps (the replay
    # above is the supervisor's own), the fallbacks in the measured order; calibrating again
    # from the written config finds the same
    from mpa_gym.agents.evaluation import calibrate as cal
    from mpa_gym.agents.learned.config import load_config

    out = subprocess.run([sys.executable, "-m", "mpa_gym.agents.cli", "calibrate",
                          str(tiny_run), "--n-plants", "6", "--episode-s", "9", "--write",
                          "--json"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    o = json.loads(out.stdout)
    order = [f["mean_position_rmse_mm"] for f in o["fallback_order"]]
    assert order == sorted(order) and len(order) == len(cal.CANDIDATES)
    assert (tiny_run / "config.before-calibration.yaml").is_file()
    spec = load_config(tiny_run / "config.yaml").supervisor
    assert spec.fallback == o["fallback_order"][0]["controller"]
    for m in spec.monitors:
        assert m.level_mm >= max(cal.MARGIN * o["peaks_mm"][m.name], cal.FLOOR_MM) - 1e-3
    again = cal.calibrate(tiny_run, n_plants=6, episode_s=9.0)  # same draws, same figures
    assert again.kept == o["kept_plants"] and again.peaks_mm == pytest.approx(o["peaks_mm"])
    written = yaml.safe_load((tiny_run / "config.yaml").read_text())["mpa_gym"]["supervisor"]
    assert written == again.section()


def test_calibration_measures_and_keeps_the_supervisors_gains(tiny_run, tmp_path):
    # a run whose supervisor has gains of its own (a gains file's mapping, inline): its
    # fallbacks are measured with them, and --write keeps them. The pid given here is a
    # proportional gain of 1e4 bar/m with no integral or derivative action, which no plant
    # survives (each of its episodes counts FAILED_MM), so its mean is FAILED_MM exactly;
    # with its default gains pid tracks these four plants (24 s episodes, as calibrate runs)
    import shutil

    from mpa_gym.agents.evaluation import calibrate as cal
    from mpa_gym.agents.learned.config import load_config

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    assert dict(cal.calibrate(run, n_plants=4).order)["pid"] < cal.FAILED_MM
    data = yaml.safe_load((run / "config.yaml").read_text())
    gains = {"pid": {"kp_bar_per_m": 1e4, "ki_bar_per_m_s": 0.0, "kd_bar_s_per_m": 0.0}}
    data["mpa_gym"]["supervisor"]["gains"] = gains
    (run / "config.yaml").write_text(yaml.safe_dump(data))
    found = cal.calibrate(run, n_plants=4)
    assert dict(found.order)["pid"] == cal.FAILED_MM
    cal.write(run, found)
    spec = load_config(run / "config.yaml").supervisor
    assert spec.gains == gains and spec.select == found.spec.select


def test_calibrate_refuses_what_is_not_a_run(tmp_path):
    out = subprocess.run([sys.executable, "-m", "mpa_gym.agents.cli", "calibrate",
                          str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "is not a run folder" in out.stderr


def test_the_hand_over_rate_is_a_training_metric(tmp_path):
    # each held-out evaluation of a supervised run records, beside the policy alone's figures,
    # when the supervised policy's fallback took over on each scenario, as evaluate finds it on
    # the saved model, and the share of scenarios with a hand-over
    from mpa_gym.agents.evaluation.evaluate import evaluate
    from mpa_gym.agents.training.train import train

    def held_out(cfg):
        cfg["mpa_gym"]["eval_scenarios"] = ["heldout_a", "load_1kg"]
        # the training metric counts the monitors' hand-overs of the policy's own loop (it
        # starts every held-out episode); evaluate starts it too with no start chosen on the
        # model (the choice is tests/test_select.py's)
        cfg["mpa_gym"]["supervisor"]["select"] = None

    run = train(tiny_config(tmp_path, held_out), tmp_path / "run", progress=False)
    last = json.loads((run / "eval" / "evaluations.json").read_text())[-1]
    scen = last["scenarios"]
    got = [scen[s]["supervised_fallback_s"] for s in ("heldout_a", "load_1kg")]
    assert last["hand_over_rate"] == np.mean([g is not None for g in got])
    res = evaluate([str(run)], ["heldout_a", "load_1kg"], robustness=False)["results"]
    for s, g in zip(("heldout_a", "load_1kg"), got, strict=True):
        assert res[s]["run"]["fallback_s"] == g
