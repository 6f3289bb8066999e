"""Robustness sweep: per-leg plants in one batch, the instability criterion, the report."""

from __future__ import annotations

import dataclasses
import json

import gymnasium as gym
import numpy as np
import pytest
from numpy.testing import assert_allclose

import mpa_gym  # noqa: F401
from agents.baselines import make_baseline
from agents.evaluate import evaluate, metrics, run_episode, write_report
from agents.robustness import Grid, cell_metrics, held_out, robustness, run_batch, run_batches
from mpa_gym.analysis.scenario import Impulse

SHORT = {"name": "short", "duration_s": 9.0}  # three periods: the metric window is the episode
PLANTS = [{"pressure_dead_time_s": 0.0137, "pressure_lag_s": 0.03, "extra_mass_kg": 0.5},
          {"braid_friction_ratio": 0.03, "slider_friction_N": 1.5, "pressure_lag_s": 0.02},
          {"pressure_slew_bar_per_s": 5.0, "slider_viscous_Ns_per_m": 4.0},
          {}]


def test_vector_env_takes_one_plant_per_leg_and_matches_single_envs():
    # reset(options={"plant": [dict per leg]}): leg i steps exactly as a single env reset with
    # options={"plant": plants[i]} (and the same seed), through dead time, slew, friction.
    venv = gym.make_vec("MPALegResidual-v0", num_envs=len(PLANTS),
                        vectorization_mode="vector_entry_point", scenario=SHORT)
    vobs, _ = venv.reset(seed=5, options={"plant": PLANTS})
    singles = [gym.make("MPALegResidual-v0", scenario=SHORT) for _ in PLANTS]
    sobs = [s.reset(seed=5 + i, options={"plant": p})[0] for i, (s, p) in
            enumerate(zip(singles, PLANTS, strict=True))]
    rng = np.random.default_rng(1)
    for _ in range(120):
        acts = rng.uniform(-0.3, 0.3, (len(PLANTS), 2))
        vobs, *_ = venv.step(acts)
        sobs = [s.step(a)[0] for s, a in zip(singles, acts, strict=True)]
        assert np.array_equal(np.array(sobs), vobs)
    with pytest.raises(ValueError, match=r"options\['plant'\]\[0\]: \['pressure_quantum_bar'\] "
                                         "belong to the whole rig"):
        venv.reset(options={"plant": [{"pressure_quantum_bar": 0.02}, {}, {}, {}]})
    with pytest.raises(ValueError, match="one dict of plant fields per leg"):
        venv.reset(options={"plant": [{}]})


def test_a_grid_cell_is_the_episode_a_single_env_runs_on_that_plant():
    # The batch is only a faster way to run the cells: pid's RMSE per cell equals that of one
    # episode of the single env on the cell's plant (same metric window, same seed).
    grid = Grid("g", "pressure_dead_time_s", (0.0, 0.0137), "slider_friction_N", (0.0, 1.5),
                base={"pressure_lag_s": 0.03})
    rob = robustness(["mbfb"], SHORT, seed=3, grids=(grid,), levels={})
    cells = rob["grids"]["g"]["controllers"]["mbfb"]
    for r, dead in enumerate(grid.row_values):
        for c, fric in enumerate(grid.col_values):
            plant = {"pressure_lag_s": 0.03, "pressure_dead_time_s": dead,
                     "slider_friction_N": fric}
            env = gym.make("MPALegResidual-v0", scenario=SHORT)
            tr = run_episode(env, make_baseline("mbfb", SHORT), 3 + 2 * r + c,
                             options={"plant": plant})
            assert not tr.terminated and not cells[r][c]["terminated"]
            want = metrics(tr, 3.0, None)["position_rmse_mm"]
            assert_allclose(cells[r][c]["position_rmse_mm"], want, rtol=1e-12)
            assert cells[r][c]["held_out"] is None  # a baseline has no training plants


def test_instability_criterion_separates_limit_cycles_from_periodic_errors():
    # Three periods of 300 steps: a periodic error (a 20 mm sag plus a 5 mm error at the
    # reference's frequency) is a stable closed loop; a 2 mm oscillation at 6.83 Hz (a limit
    # cycle's frequency is set by the loop, not by the reference) is not, nor is a terminated
    # episode.
    t = 0.01 * np.arange(1, 901)
    periodic = -0.02 + 0.005 * np.sin(2 * np.pi * t / 3.0)
    cycle = 0.002 * np.sin(2 * np.pi * 6.83 * t + 0.3)
    run = {"t": t, "x": 0.8 + np.stack([periodic, cycle, cycle], 1),
           "x_ref": np.full((900, 3), 0.8), "terminated": np.array([False, False, True])}
    m = cell_metrics(run, 3.0, 0.01)
    assert not m[0]["unstable"] and m[0]["aperiodic_rmse_mm"] < 1e-9
    assert_allclose(m[0]["position_rmse_mm"], 1e3 * np.sqrt(np.mean(periodic**2)), rtol=1e-12)
    assert m[1]["unstable"] and m[1]["aperiodic_rmse_mm"] > 1.0
    assert m[2]["unstable"] and m[2]["terminated"] and m[2]["position_rmse_mm"] is None


def test_held_out_marks_values_the_training_scenario_never_draws():
    ranges = {"extra_mass_kg": (0.0, 1.2), "pressure_lag_s": (0.0, 0.04)}
    assert held_out({"extra_mass_kg": 1.0, "pressure_lag_s": 0.03}, ranges) is False
    assert held_out({"extra_mass_kg": 1.6}, ranges) is True
    # a field training leaves at its default (0) is held out at any other value
    assert held_out({"pressure_dead_time_s": 0.02}, ranges) is True
    assert held_out({"pressure_dead_time_s": 0.0}, ranges) is False
    assert held_out({"extra_mass_kg": 9.0}, None) is None


def test_report_holds_the_sweep_in_json_markdown_and_heatmaps(tmp_path):
    small = (Grid("tiny", "pressure_dead_time_s", (0.0, 0.02), "extra_mass_kg", (0.0, 1.6),
                  base={"pressure_lag_s": 0.03}),)
    rep = evaluate(["ff", "pid"], [SHORT])
    rep["robustness"] = robustness(  # what evaluate(robustness=True) adds, on a short run
        ["ff", "pid"], SHORT, grids=small,
        levels={"hard": {"pressure_dead_time_s": 0.03, "extra_mass_kg": 1.6}},
        kick=Impulse(t_s=2.0, force_N=30.0, duration_s=0.05))
    paths = write_report(rep, tmp_path)
    data = json.loads(paths["json"].read_text())["robustness"]
    tiny = data["grids"]["tiny"]
    assert tiny["rows"] == {"field": "pressure_dead_time_s", "values": [0.0, 0.02]}
    assert set(tiny["controllers"]) == {"ff", "pid"}
    assert {"position_rmse_mm", "unstable", "terminated"} <= set(tiny["controllers"]["ff"][0][0])
    assert set(data["levels"]["hard"]) == {"ff", "pid"}
    md = paths["markdown"].read_text()
    assert "## Robustness sweep" in md and "### tiny" in md and "| hard |" in md
    assert paths["plot_robustness_tiny"].stat().st_size > 10_000


def test_run_batch_stops_counting_a_leg_when_it_terminates():
    # A stiff PID (Kp 80 bar/m, Ki 3000 bar/(m s), Kd 12 bar s/m) on a 40 ms dead time leaves
    # the bounds; its leg stops being counted (NaN after it), and the other leg of the batch,
    # on the ideal plant, runs to the end of its episode.
    stiff = dataclasses.replace(make_baseline("pid", SHORT), kp_bar_per_m=80.0,
                                ki_bar_per_m_s=3000.0, kd_bar_s_per_m=12.0, tf_s=0.0)
    run = run_batch(stiff, gym.make("MPALegResidual-v0", scenario=SHORT).unwrapped.plan
                    .scenario, [{"pressure_dead_time_s": 0.04, "pressure_lag_s": 0.03}, {}], 0)
    assert run["terminated"].tolist() == [True, False]
    assert np.isnan(run["x"][-1, 0]) and np.isfinite(run["x"][:, 1]).all()
    assert run["x"].shape[0] == 900


def test_controllers_sharing_one_batch_step_as_each_does_alone():
    # run_batches puts ff, pid, mbfb and a stiff PID that leaves the bounds in one vector env,
    # a block of legs each: every block's traces are bit-identical to that controller's own
    # batch (same seeds per leg, same plants), including the terminated leg's NaN tail and a
    # run that ends (all legs terminated) while the other blocks go on.
    sc = gym.make("MPALegResidual-v0", scenario=SHORT).unwrapped.plan.scenario
    stiff = dataclasses.replace(make_baseline("pid", SHORT), kp_bar_per_m=80.0,
                                ki_bar_per_m_s=3000.0, kd_bar_s_per_m=12.0, tf_s=0.0)
    plants = [{"pressure_dead_time_s": 0.04, "pressure_lag_s": 0.03}, *PLANTS]
    specs = [make_baseline(n, SHORT) for n in ("ff", "pid", "mbfb")] + [stiff]
    together = run_batches(specs, sc, plants, 3)
    assert together[3]["terminated"][0] and not together[1]["terminated"].any()
    for spec, run in zip(specs, together, strict=True):
        alone = run_batch(spec, sc, plants, 3)
        n = alone["x"].shape[0]
        assert np.array_equal(run["terminated"], alone["terminated"])
        assert np.array_equal(run["x"][:n], alone["x"], equal_nan=True)
        assert np.array_equal(run["x_ref"][:n], alone["x_ref"], equal_nan=True)
        assert np.isnan(run["x"][n:]).all()  # after the lone run ended: nothing recorded
