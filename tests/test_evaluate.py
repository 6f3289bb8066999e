"""Who drove (mpa_gym.agents.evaluation.evaluate, robustness, seeds): a supervised run whose
fallback takes over is reported as the supervised system, with the share of steps its policy
drove and the hand-over marked, beside the same run without its supervisor, `<run> (alone)`,
whose figures are the policy's own.

The situation is built deterministically: two tiny trained runs (a few hundred steps; their
quality does not matter) whose config's divergence monitor is a hair trigger (the error's RMS
over 0.5 s passing 0.05 mm), on a plant 0.1 kg off the nominal one behind a 30 ms regulator lag
(whoever drives, the error is millimetres). The policy drives the first steps, pid the rest."""

from __future__ import annotations

import json
import re

import gymnasium as gym
import numpy as np
import pytest
import yaml
from conftest import tiny_config

import mpa_gym  # noqa: F401
from mpa_gym.agents.cli import main
from mpa_gym.agents.controllers.supervisor import Supervised
from mpa_gym.agents.evaluation.episodes import metrics, run_episode
from mpa_gym.agents.evaluation.evaluate import (
    evaluate,
    hand_over_lines,
    markdown,
    scenario_figure,
)
from mpa_gym.agents.evaluation.robustness import Grid, cell_metrics, no_harm, robustness
from mpa_gym.agents.evaluation.robustness import markdown as robustness_markdown
from mpa_gym.agents.learned.policies import ALONE, load_policy
from mpa_gym.agents.training.train import train

DT, PERIOD = 0.01, 0.5
TRIP = {"name": "trip", "duration_s": 2.0,
        "reference": {"x0_m": 0.8, "amp_m": 0.02, "period_s": PERIOD},
        "plant": {"mass_kg": 4.1, "pressure_lag_s": 0.03}}
HAIR_TRIGGER = {"level_mm": 0.05, "window_s": 0.5, "clip_mm": None, "arm_periods": 0}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two runs (seeds 0 and 1) of the default config with a hair-trigger divergence monitor
    handing over to pid, named ``w-s0`` and ``w-s1`` (one group)."""
    tmp = tmp_path_factory.mktemp("who")

    def hair_trigger(cfg):
        sup = cfg["mpa_gym"]["supervisor"]
        sup["monitors"]["divergence"] = HAIR_TRIGGER
        sup["stages"] = [{"controller": "policy", "monitors": ["divergence"]},  # pid first
                         {"controller": "pid", "monitors": ["divergence"], "grace_periods": 1},
                         {"controller": "afc"}]
        sup["select"] = None  # the policy starts: a monitor hands over (a start chosen on the
        # model is tests/test_select.py's)

    path = tiny_config(tmp, hair_trigger, n_timesteps=256, n_epochs=1)
    return [str(train(path, tmp / f"w-s{s}", s, progress=False)) for s in (0, 1)]


def _table(md: str, title: str) -> dict[str, dict[str, str]]:
    """A Markdown section's table: scenario → column → cell (the rule line left out)."""
    lines = [ln for ln in md.split(f"## {title}\n")[1].split("\n## ")[0].splitlines()
             if ln.startswith("| ")]  # the header and the rows
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    return {cells[0]: dict(zip(head[1:], cells[1:], strict=True))
            for cells in ([c.strip() for c in ln.strip("|").split("|")] for ln in lines[1:])}


def test_a_supervised_run_is_reported_beside_its_policy_alone(runs):
    run = runs[0]
    rep = evaluate([run, "ff", "pid"], [TRIP])
    row = rep["results"]["trip"]
    assert list(row) == ["w-s0", "w-s0 (alone)", "ff", "pid"]
    sup, alone = row["w-s0"], row["w-s0 (alone)"]
    # the fallback took over, and the latch holds: the policy drove exactly the steps before
    # it (step i ends at (i + 1) dt)
    assert 0.0 < sup["fallback_s"] < TRIP["duration_s"]
    n = round(TRIP["duration_s"] / DT)
    assert sup["policy_share"] == pytest.approx((sup["fallback_s"] / DT - 1) / n, abs=1e-9)
    assert 0.0 < sup["policy_share"] < 1.0
    # nothing took over anything else: the policy alone, the baselines
    for m in (alone, row["ff"], row["pid"]):
        assert m["policy_share"] == 1.0 and m["fallback_s"] is None
    assert alone["position_rmse_mm"] != pytest.approx(sup["position_rmse_mm"], rel=1e-3)
    # the (alone) row is the policy by itself: the model and normaliser of the run, in a single
    # env of its own (not the report's batch), with no supervisor anywhere, told the
    # scenario's delays (delay_observation)
    policy, _, cfg = load_policy(run + ALONE, {"scenario": TRIP})
    assert not isinstance(policy, Supervised)
    env = gym.make(cfg.env_id, scenario=TRIP, task={k: v for k, v in
                                                    cfg.env_kwargs["task"].items()
                                                    if k != "episode_s"})
    own = metrics(run_episode(env, policy, rep["seed"]), PERIOD, None)
    for key in ("position_rmse_mm", "position_max_mm", "stiffness_rmse_pct", "return"):
        np.testing.assert_allclose(alone[key], own[key], rtol=1e-9)
    # ... and what `RUN_DIR:alone` evaluated on its own gives, with no supervisor in the report
    by_itself = evaluate([run + ALONE], [TRIP])
    assert by_itself["results"]["trip"]["w-s0 (alone)"] == alone
    assert by_itself["supervisors"] == {}
    assert isinstance(load_policy(run)[0], Supervised)
    assert not isinstance(load_policy(run, supervised=False)[0], Supervised)

    # Markdown: the supervised cells are marked with who drove from when, the others are not
    md = markdown(rep)
    cells = _table(md, "position RMSE [mm]")["trip"]
    policy_said = f"; policy {sup['policy_share'] * 100:.0f} % of steps"
    assert f"‡ pid from {sup['fallback_s']:.1f} s" in cells["w-s0"]
    assert cells["w-s0"].endswith(policy_said)
    assert all("‡" not in cells[c] for c in ("w-s0 (alone)", "ff", "pid"))
    assert "‡: a supervisor's fallback drove part of this episode" in md
    share = _table(md, "share of steps the learned policy drove")["trip"]
    assert float(share["w-s0"]) == pytest.approx(sup["policy_share"], abs=5e-4)
    assert float(share["ff"]) == 1.0
    [line] = hand_over_lines(rep)
    assert line.startswith(f"w-s0 on trip: pid from {sup['fallback_s']:.1f} s")
    assert line.endswith(policy_said)

    # the plot: X and an error panel in mm, and the hand-over drawn where it happened
    fig = scenario_figure("trip", rep["traces"]["trip"], rep["stages"])
    pos, err = fig.axes[:2]
    assert pos.get_ylabel() == "X [mm]" and err.get_ylabel() == "X − X̂ [mm]"
    xs = {ln.get_label(): ln for ln in pos.get_lines()}
    np.testing.assert_allclose(xs["ff"].get_ydata(), rep["traces"]["trip"]["ff"].x * 1e3)
    lines = {ln.get_label(): ln for ln in err.get_lines()}
    tr = rep["traces"]["trip"]["ff"]
    np.testing.assert_allclose(lines["ff"].get_ydata(), (tr.x - tr.x_ref) * 1e3)
    handed = [ln for lab, ln in lines.items() if "from" in lab]
    # the hair-trigger monitor judges pid's loop too, after its grace of one period of the
    # trip's reference (0.5 s: the supervisor is built for the scenario), and afc follows
    assert sup["last_resort_s"] is not None
    assert [ln.get_label() for ln in handed] == [f"w-s0: pid from {sup['fallback_s']:.1f} s",
                                                 f"w-s0: afc from {sup['last_resort_s']:.1f} s"]
    assert list(handed[0].get_xdata()) == [sup["fallback_s"]] * 2
    assert list(handed[1].get_xdata()) == [sup["last_resort_s"]] * 2

    # the no-harm audit checks both
    assert set(rep["no_harm"]) == {"w-s0", "w-s0 (alone)"}


def test_groups_and_the_sweep_hold_the_supervised_system_and_the_policy_alone(runs):
    rep = evaluate([*runs, "ff"], [TRIP])
    g = rep["groups"]
    assert set(g) == {"w", "w (alone)"}
    assert g["w (alone)"]["runs"] == ["w-s0 (alone)", "w-s1 (alone)"]
    row = rep["results"]["trip"]
    sup, alone = g["w"]["results"]["trip"], g["w (alone)"]["results"]["trip"]
    assert sup["fallback_runs"] == 2 and alone["fallback_runs"] == 0
    assert alone["policy_share"] == 1.0 and sup["policy_share"] < 1.0
    # two runs: the IQM is their mean, each group over its own rows
    for grp, labels in ((alone, ["w-s0 (alone)", "w-s1 (alone)"]), (sup, ["w-s0", "w-s1"])):
        assert grp["position_rmse_mm"] == pytest.approx(
            np.mean([row[lab]["position_rmse_mm"] for lab in labels]), rel=1e-12)
    cells = _table(markdown(rep), "position RMSE [mm]")["trip"]
    assert cells["w (IQM [95 % CI])"].endswith("‡ a fallback drove in 2 of 2 runs")
    assert "‡" not in cells["w (alone) (IQM [95 % CI])"]

    # the sweep: every cell says who drove; the policy alone is swept beside the supervised run
    grid = Grid("load", "extra_mass_kg", (0.5, 1.0), "pressure_lag_s", (0.03,))
    rob = robustness([runs[0], "ff"], scenario=TRIP, grids=(grid,), levels={}, kicks={})
    ctrls = rob["grids"]["load"]["controllers"]
    assert list(ctrls) == ["w-s0", "w-s0 (alone)", "ff"]
    for c, cells_of in ctrls.items():
        for m in (m for r in cells_of for m in r):
            if c == "w-s0":
                assert 0.0 < m["policy_share"] < 1.0 and m["fallback_s"] is not None
            else:
                assert m["policy_share"] == 1.0 and m["fallback_s"] is None
    m = ctrls["w-s0"][0][0]
    said = f"‡{m['fallback_s']:.1f} s" + ("" if m["last_resort_s"] is None else
                                          f" §{m['last_resort_s']:.1f} s")
    assert f"{said} (policy {m['policy_share'] * 100:.0f} %)" in \
        "\n".join(robustness_markdown(rob))
    # the count of hand-overs per grid: of the supervised run alone (every one of its cells
    # here), none for the policy alone and a baseline
    assert rob["grids"]["load"]["hand_overs"] == {"w-s0": 2}
    assert "**w-s0** (its supervisor handed over on 2 of 2 cells)" in \
        robustness_markdown(rob)


def test_the_summary_says_who_drove_the_sweep_too(runs):
    """A hand-over on a robustness level or grid cell is listed beside the scenarios' and the
    terminal's levels table marks the level: the main job's summary said "none, the policies
    drove every step" above a hard level its fallback had driven."""
    from mpa_gym.agents.cli import show_evaluate

    grid = Grid("load", "extra_mass_kg", (0.5, 1.0), "pressure_lag_s", (0.03,))
    rob = robustness([runs[0], "ff"], scenario=TRIP, grids=(grid,),
                     levels={"heavy": {"extra_mass_kg": 1.0}}, kicks={})
    rep = evaluate([runs[0], "ff"], [TRIP])
    rep["robustness"] = rob
    lv = rob["levels"]["heavy"]["w-s0"]
    assert lv["fallback_s"] is not None and rob["levels"]["heavy"]["ff"]["fallback_s"] is None
    lines = hand_over_lines(rep)
    assert f"w-s0 on level heavy: pid from {lv['fallback_s']:.1f} s" in "\n".join(lines)
    assert "w-s0 on grid load: 2 of 2 cells" in lines
    assert not any(ln.startswith(("ff ", "w-s0 (alone)")) for ln in lines)
    text = show_evaluate({**rep, "hand_overs": lines, "groups": {}, "no_harm": {},
                          "report_md": "r.md", "report_json": "r.json", "plots": "p"})
    [row] = [ln for ln in text.splitlines() if ln.split()[:1] == ["heavy"]]
    cells = re.split(r"\s{2,}", row.strip())  # heavy | w-s0 | w-s0 (alone) | ff
    assert cells[1].endswith(" ‡") and "‡" not in "".join(cells[2:])
    assert "none, the policies drove every step" not in text


def test_no_harm_audits_the_sweep_of_both(runs):
    grid = Grid("load", "extra_mass_kg", (0.5, 1.0), "pressure_lag_s", (0.03,))
    rob = robustness([runs[0], "ff", "pid"], scenario=TRIP, grids=(grid,), levels={},
                     kicks={})
    audit = no_harm({}, rob, ["w-s0", "w-s0 (alone)"])
    assert set(audit) == {"w-s0", "w-s0 (alone)"}
    assert all(a["checked"] == 2 for a in audit.values())


def test_a_cell_counts_the_share_over_its_own_steps():
    # A leg that terminated after 40 of 100 steps, its fallback driving from step 30: the policy
    # drove 30 of its 40 steps (the padding after its end is no one's).
    t = DT * np.arange(1, 101)
    fb = np.zeros((100, 1), dtype=np.int8)
    fb[30:40] = 1
    run = {"t": t, "x": np.full((100, 1), np.nan), "x_ref": np.zeros((100, 1)),
           "terminated": np.array([True]), "fallback": fb, "steps": np.array([40])}
    m = cell_metrics(run, 3.0, DT)[0]
    assert m["policy_share"] == pytest.approx(0.75) and m["fallback_s"] == pytest.approx(0.31)


def test_the_evaluate_summary_prints_the_hand_overs(runs, tmp_path, capsys):
    scen = tmp_path / "trip.yaml"
    scen.write_text(yaml.safe_dump(TRIP))
    assert main(["evaluate", "--policy", runs[0], "pid", "--scenarios", str(scen),
                 "--no-robustness", "--out", str(tmp_path / "rep")]) == 0
    text = capsys.readouterr().out
    row = json.loads((tmp_path / "rep" / "report.json").read_text())["results"]["trip"]
    fb, lr = row["w-s0"]["fallback_s"], row["w-s0"]["last_resort_s"]
    assert f"w-s0 on trip: pid from {fb:.1f} s, afc from {lr:.1f} s; policy " in text
    assert "w-s0 (alone)" in text.splitlines()[1]  # a column of the table
    # the table's supervised cell is marked, the policy alone's is not
    table = next(ln for ln in text.splitlines() if ln.split()[:1] == ["trip"])
    assert table.count("‡") == 1


def test_the_summary_gives_the_best_per_scenario_group_and_who_drove(runs, monkeypatch):
    """The summary's figures recomputed from the report's own per-scenario rows: one
    controller's mean over a group's scenarios, a group of two runs' IQM (of two values, their
    mean) with its interval around it, the fallback's episodes counted, the best the lowest
    mean of the rows that never terminated. (500 bootstrap samples: what is checked of the
    interval holds for any number.)"""
    from mpa_gym.agents.evaluation import seeds
    from mpa_gym.agents.evaluation.evaluate import summary, summary_markdown

    monkeypatch.setattr(seeds, "BOOTSTRAP_REPS", 500)

    # heldout_a's plant, shortened: a scenario of the held-out group (grouped by name)
    held = {**yaml.safe_load(open("configs/scenarios/heldout_a.yaml")), "duration_s": 2.0,
            "reference": TRIP["reference"]}
    rep = evaluate([*runs, "ff", "pid"], [TRIP, held])
    res, summ = rep["results"], rep["summary"]["groups"]
    assert list(summ) == ["held_out", "other"]
    assert summ["other"]["scenarios"] == ["trip"] and summ["held_out"]["scenarios"] == ["heldout_a"]
    g = summ["other"]["controllers"]
    assert set(g) == {"w", "w (alone)", "ff", "pid"}  # the seeds' rows are their group's
    assert g["ff"]["position_rmse_mm"] == res["trip"]["ff"]["position_rmse_mm"]
    assert g["ff"]["kind"] == "baseline" and g["w (alone)"]["kind"] == "alone"
    both = [res["trip"][r]["position_rmse_mm"] for r in ("w-s0", "w-s1")]
    w = g["w"]
    assert w["kind"] == "supervised" and w["n_runs"] == 2
    np.testing.assert_allclose(w["position_rmse_mm"], np.mean(both), rtol=1e-12)
    lo, hi = w["position_rmse_mm_ci"]
    assert min(both) - 1e-12 <= lo <= w["position_rmse_mm"] <= hi <= max(both) + 1e-12
    # the hair trigger hands both runs to pid on trip; the policy alone has no fallback
    assert w["fallback_episodes"] == 2 and g["w (alone)"]["fallback_episodes"] == 0
    np.testing.assert_allclose(w["policy_share"], np.mean(
        [res["trip"][r]["policy_share"] for r in ("w-s0", "w-s1")]), rtol=1e-12)
    for grp in summ.values():
        ok = {r: e["position_rmse_mm"] for r, e in grp["controllers"].items()
              if not e["terminated"]}
        assert grp["best"] == min(ok, key=ok.get)

    # a supervised row that a fallback drove is never named best without its mark, and the
    # policy alone's figure stands beside it (the rows' figures set by hand to make it best)
    crafted = {"results": {"trip": {
        "r": {**res["trip"]["w-s0"], "position_rmse_mm": 0.01},
        "r (alone)": {**res["trip"]["w-s0 (alone)"], "position_rmse_mm": 5.0},
        "pid": {**res["trip"]["pid"], "position_rmse_mm": 1.0}}},
        "kinds": {"r": "supervised", "r (alone)": "alone", "pid": "baseline"}, "groups": {}}
    crafted["summary"] = summary(crafted)
    md = markdown({**crafted, "seed": 0})
    first = md.split("## Summary\n")[1].split("\n\n| controller")[0]  # the best per group
    best_row = _table(f"## Summary\n{first}", "Summary")["other scenarios (1)"]
    assert best_row["best"] == "**r ‡**"
    assert "a fallback drove in 1 of 1 episodes" in best_row["who drove"]
    assert "the policy alone, r (alone): 5.000 mm" in best_row["who drove"]
    # ... and a supervised loop that its fallback drove to the fallback's own figure (equal to
    # the printed decimals) does not take the title from the fallback itself
    tie = crafted["results"]["trip"]
    tie["r"]["position_rmse_mm"], tie["pid"]["position_rmse_mm"] = 0.2553941, 0.2553944
    assert summary(crafted)["groups"]["other"]["best"] == "pid"

    # the sweep's levels are a group too: position only, a terminated cell has no figure and
    # cannot be best (cells as robustness.cell_metrics writes them)
    def cell(mm, terminated=False):
        return {"position_rmse_mm": None if terminated else mm, "terminated": terminated,
                "unstable": terminated, "fallback_s": None, "last_resort_s": None,
                "policy_share": 1.0}

    crafted["robustness"] = {"levels": {
        "easy": {"r": cell(0.5), "r (alone)": cell(0.7), "pid": cell(0.4)},
        "hard": {"r": cell(2.0), "r (alone)": cell(0, terminated=True), "pid": cell(3.0)}}}
    lv = summary(crafted)["groups"]["levels"]
    assert lv["scenarios"] == ["easy", "hard"]
    assert lv["controllers"]["r"]["position_rmse_mm"] == pytest.approx(1.25, rel=1e-12)
    assert lv["controllers"]["pid"]["position_rmse_mm"] == pytest.approx(1.7, rel=1e-12)
    assert lv["controllers"]["r (alone)"]["position_rmse_mm"] is None
    assert lv["controllers"]["r (alone)"]["terminated"] == 1
    assert "stiffness_rmse_pct" not in lv["controllers"]["r"] and lv["best"] == "r"
    crafted["summary"] = summary(crafted)
    json.dumps(crafted["summary"], allow_nan=False)  # report.json's rule: no NaN, no inf
    assert "| robustness levels (2) | **r** | 1.250 | – |" in "\n".join(
        summary_markdown(crafted["summary"]))


def test_evaluate_json_and_table_carry_the_summary(runs, tmp_path, capsys):
    scen = tmp_path / "trip.yaml"
    scen.write_text(yaml.safe_dump(TRIP))
    args = ["evaluate", "--policy", runs[0], "pid", "--scenarios", str(scen), "--no-robustness",
            "--out", str(tmp_path / "rep")]
    assert main([*args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    on_disk = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert out["summary"] == on_disk["summary"]
    best = out["summary"]["groups"]["other"]["best"]
    assert main(args) == 0
    text = capsys.readouterr().out
    mark = " ‡" if out["summary"]["groups"]["other"]["controllers"][best]["fallback_episodes"] \
        else ""
    assert f"best on other scenarios: {best}{mark}, " in text
    md = (tmp_path / "rep" / "report.md").read_text()
    assert md.index("## Summary") < md.index("## position RMSE [mm]")
