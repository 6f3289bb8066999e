"""Robustness sweep: per-leg plants in one batch, the instability criterion, the report."""

from __future__ import annotations

import dataclasses
import json

import gymnasium as gym
import numpy as np
import pytest
from numpy.testing import assert_allclose

import mpa_gym  # noqa: F401
from mpa_gym.agents.controllers.baselines import make_baseline
from mpa_gym.agents.evaluation.episodes import metrics, run_episode
from mpa_gym.agents.evaluation.evaluate import evaluate, write_report
from mpa_gym.agents.evaluation.robustness import (
    Grid,
    _scenario,
    cell_metrics,
    held_out,
    no_harm,
    no_harm_markdown,
    robustness,
    run_batch,
    run_batches,
)
from mpa_gym.analysis.scenario import Impulse, load_scenario
from mpa_gym.analysis.simulate import metric_window, whole_periods

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
        kick=Impulse(t_s=2.0, force_N=30.0, duration_s=0.05),
        kicks={"load": {"extra_mass_kg": 1.6}})
    paths = write_report(rep, tmp_path)
    data = json.loads(paths["json"].read_text())["robustness"]
    tiny = data["grids"]["tiny"]
    assert tiny["rows"] == {"field": "pressure_dead_time_s", "values": [0.0, 0.02]}
    assert set(tiny["controllers"]) == {"ff", "pid"}
    assert {"position_rmse_mm", "unstable", "terminated"} <= set(tiny["controllers"]["ff"][0][0])
    assert set(data["levels"]["hard"]) == {"ff", "pid"}
    # the kick alone on a 1.6 kg load: pid brings the error back under 1 mm, ff never does
    # (its sag under the load is ~34 mm)
    kick = data["kicks"]["load"]
    assert kick["ff"]["recovery_s"] == "never" and 0.0 < kick["pid"]["recovery_s"] < 7.0
    assert data["kicks_plants"] == {"load": {"extra_mass_kg": 1.6}}
    md = paths["markdown"].read_text()
    assert "## Robustness sweep" in md and "### tiny" in md and "| hard |" in md
    assert "### Kicks" in md and "| load | extra_mass_kg 1.6 |" in md
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


def test_no_harm_audit_names_every_broken_bound_and_nothing_else():
    # Made-up figures [mm] with a known answer per case: the bounds are ff's RMSE and 1.5× the
    # best of pid / mbfb, each raised to 0.05 mm, and stability where ff is stable.
    def m(rmse, unstable=False):
        return {"position_rmse_mm": rmse, "unstable": unstable, "terminated": rmse is None}

    results = {
        "fine": {"ff": m(0.0), "pid": m(0.001), "mbfb": m(0.03), "run": m(0.049)},  # floor
        "worse_than_ff": {"ff": m(0.1), "pid": m(0.2), "mbfb": m(0.3), "run": m(0.12)},
        "over_ratio": {"ff": m(10.0), "pid": m(0.5), "mbfb": m(0.9), "run": m(0.76)},
        "at_ratio": {"ff": m(10.0), "pid": m(0.5), "mbfb": m(0.9), "run": m(0.75)},
    }
    rob = {"grids": {"g": {"rows": {"field": "pressure_dead_time_s", "values": [0.02]},
                           "cols": {"field": "extra_mass_kg", "values": [0.0, 0.5]},
                           "controllers": {"ff": [[m(1.0), m(10.0)]],
                                           "pid": [[m(9.0, True), m(0.4)]],
                                           "mbfb": [[m(None), m(0.3)]],
                                           "run": [[m(0.9, True), m(None)]]}}},
           "levels": {}, "kicks": {"k": {"ff": m(30.0), "pid": m(0.5), "mbfb": m(0.04),
                                         "run": m(0.07)}}}
    audit = no_harm(results, rob, ["run"])["run"]
    assert audit["checked"] == 7
    got = {h["case"]: h["reasons"] for h in audit["harm"]}
    ratio = "over 1.5× the best feedback baseline"
    assert got == {
        "scenario worse_than_ff": ["worse than ff"],
        "scenario over_ratio": [ratio],
        # stable-looking figures do not excuse a limit cycle the feedforward does not have
        "g pressure_dead_time_s 0.02, extra_mass_kg 0": ["unstable where ff is stable"],
        "g pressure_dead_time_s 0.02, extra_mass_kg 0.5": ["worse than ff", ratio],
        "kick k": [ratio],  # 0.07 > max(1.5 × 0.04, 0.05)
    }
    term = next(h for h in audit["harm"] if h["case"].endswith("extra_mass_kg 0.5"))
    assert term["position_rmse_mm"] is None and term["best_feedback_mm"] == 0.3
    md = "\n".join(no_harm_markdown({"run": audit}))
    assert "**run**: 5 of 7 cases break a bound." in md
    assert "| g pressure_dead_time_s 0.02, extra_mass_kg 0.5 | terminated | 10.000 | 0.300 |" \
        in md
    # nothing to audit without the feedforward or a feedback baseline in the report
    assert no_harm({"s": {"pid": m(0.1), "run": m(9.0)}}, None, ["run"]) == {}
    assert no_harm(results, rob, []) == {}


def test_tuned_pid_is_stable_on_a_slow_regulator_that_undid_the_old_gains():
    # The slow-regulator plant (docs/design.md#reference-plants): 20 ms regulator dead time,
    # 30 ms lag, a 0.02 bar quantum and a 0.5 kg load, and the same regulator on the unloaded
    # leg (a lighter leg is the less stable one). The gains tuned with undamped twins hold both,
    # on the loaded leg with an error under a tenth of the feedforward's (~10.5 mm); the gains
    # tuned on the draws alone (Kd ~13× the leg's critical damping) oscillate on the unloaded
    # one, the check that these plants tell the two apart.
    sc = _scenario(load_scenario({"name": "slow", "duration_s": 15.0}), "slow",
                   {"pressure_quantum_bar": 0.02})
    slow = {"pressure_dead_time_s": 0.02, "pressure_lag_s": 0.03}
    plants = [{**slow, "extra_mass_kg": 0.5}, slow]
    tuned = make_baseline("pid", sc)
    old = dataclasses.replace(tuned, kp_bar_per_m=16.25, ki_bar_per_m_s=759.8,
                              kd_bar_s_per_m=7.886, tf_s=1.56e-4)
    now, before, ff = (cell_metrics(r, 3.0, 0.01) for r in
                       run_batches([tuned, old, make_baseline("ff", sc)], sc, plants, 0))
    assert not now[0]["unstable"] and not now[1]["unstable"]
    assert now[0]["position_rmse_mm"] < 0.1 * ff[0]["position_rmse_mm"]
    assert before[1]["unstable"] and not ff[1]["unstable"]


def test_sweep_in_a_second_process_gives_the_same_numbers_and_errors():
    # evaluate runs the sweep in a spawned worker beside the report's batch: a fresh
    # interpreter that loads the controllers from their specs. Its report must be the
    # in-process one exactly (the episodes are deterministic), and its errors the same.
    import os

    from mpa_gym.agents.evaluation.evaluate import sweep_in_background

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("a single core: evaluate runs the sweep in its own process")
    kwargs = dict(scenario=SHORT, grids=(Grid("tiny", "pressure_dead_time_s", (0.0, 0.02),
                                              "extra_mass_kg", (0.0, 1.6)),),
                  levels={}, kicks={})
    there = sweep_in_background(["ff", "pid"], **kwargs).result()
    assert there == robustness(["ff", "pid"], **kwargs)
    with pytest.raises(ValueError, match="no_such_controller") as there:
        sweep_in_background(["no_such_controller"], **kwargs).result()
    with pytest.raises(ValueError) as here:
        robustness(["no_such_controller"], **kwargs)
    assert str(there.value) == str(here.value)


def test_scenario_plots_are_drawn_while_the_sweep_finishes(tmp_path):
    # with plots_dir, evaluate draws the scenario plots between its batch and the sweep's
    # result; write_report then keeps them (not drawn twice) and adds the sweep's own
    import os

    from mpa_gym.agents.evaluation.evaluate import evaluate, write_report

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("a single core: the sweep runs after the batch, nothing to overlap")
    rep = evaluate(["ff"], [{"name": "a", "duration_s": 1.0}], robustness=True,
                   plots_dir=tmp_path / "plots")
    assert rep["plots"] == [tmp_path / "plots" / "a.png"]
    drawn = rep["plots"][0].stat().st_mtime_ns
    paths = write_report(rep, tmp_path)
    assert paths["plot_a"] == rep["plots"][0] and rep["plots"][0].stat().st_mtime_ns == drawn
    assert len(list((tmp_path / "plots").glob("*.png"))) > 1  # and the sweep's heatmaps
    assert "robustness" in json.loads(paths["json"].read_text())


def test_every_report_takes_the_same_window():
    # the report, simulate and rollouts take t_end − 3T ≤ t ≤ t_end; the sweep the same window
    # less its first sample (exactly three periods, to average them sample by sample)
    for t, per in ((0.01 * np.arange(1, 1801), 300), (0.005 * np.arange(0, 4001), 600)):
        mask = metric_window(t, 3.0)
        idx = np.flatnonzero(mask)
        assert idx.size == 3 * per + 1 and idx[-1] == t.size - 1
        np.testing.assert_allclose(t[idx[0]], t[-1] - 9.0, atol=1e-9)
        np.testing.assert_array_equal(np.arange(t.size)[whole_periods(t, 3.0)], idx[1:])
    short = 0.01 * np.arange(1, 451)  # shorter than three periods: all of it
    assert metric_window(short, 3.0).all()
    assert np.arange(short.size)[whole_periods(short, 3.0)].size == short.size
