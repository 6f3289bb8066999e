"""`mpa-gym tune`: search spaces, storages, bad input, and two real worker processes sharing a
study on a real PostgreSQL server."""

from __future__ import annotations

import glob
import json
import os
import pwd
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import optuna
import pytest
import yaml
from optuna.trial import TrialState

from mpa_gym.agents.cli import main
from mpa_gym.agents.evaluation.evaluate import evaluate
from mpa_gym.agents.learned.config import ConfigError, load_config
from mpa_gym.agents.learned.policies import ALONE
from mpa_gym.agents.training.tune import (
    DEFAULT_SPACE,
    OBJECTIVES,
    apply_params,
    current_params,
    fail_orphans,
    open_storage,
    parse_space,
    tune,
    write_best,
)

ENV = "MPALegResidual-v0"


def tiny_tune_config(path: Path, space: dict | None = None) -> Path:
    """The default config shrunk to seconds per trial (4 envs, 0.5 s training episodes, one
    3 s evaluation scenario), with a two-entry search space."""
    cfg = yaml.safe_load(open("configs/ppo_residual.yaml"))
    hp = cfg[ENV]
    hp.update(n_envs=4, n_timesteps=128, n_steps=32, batch_size=64, n_epochs=1,
              learning_rate="lin_3e-4")  # inside the space below: trial 0 is this config
    hp["env_kwargs"]["task"]["episode_s"] = 0.5
    cfg["mpa_gym"].update(
        eval_scenarios=[{"name": "ev", "duration_s": 1.0}], eval_freq=128, checkpoint_freq=10**6,
        tune=space or {"learning_rate": {"float": [1e-4, 1e-3], "log": True},
                       "ForceStiffnessAction.rate_penalty": {"float": [0.1, 1.0]}})
    path.write_text(yaml.safe_dump(cfg))
    return path


def short_heldout(path: Path) -> Path:
    path.write_text(yaml.safe_dump({
        "name": "short_heldout", "duration_s": 3.0,
        # the shortest period the default supervisor's rc fallback is built for is ~0.8 s
        "reference": {"x0_m": 0.8, "amp_m": 0.02, "period_s": 1.0},
        "plant": {"mass_kg": 4.1, "pressure_lag_s": 0.03}}))
    return path


def test_default_space_holds_todays_config_and_round_trips():
    data = yaml.safe_load(open("configs/ppo_residual.yaml"))
    space = parse_space(DEFAULT_SPACE)
    base = current_params(data, ENV, space)
    assert base is not None and set(base) == set(DEFAULT_SPACE)
    # putting a config's own values back changes nothing a training run reads
    again = apply_params(data, ENV, base)
    a, b = load_config_from(again), load_config_from(data)
    lr = lambda c: float(c.ppo_kwargs.pop("learning_rate")[4:])  # noqa: E731  lin_3e-4 == lin_0.0003
    assert lr(a) == lr(b)
    assert (a.ppo_kwargs, a.policy_kwargs, a.action_wrapper, a.n_envs) == \
        (b.ppo_kwargs, b.policy_kwargs, b.action_wrapper, b.n_envs)
    new = apply_params(data, ENV, {"learning_rate": 5e-4, "policy_kwargs.log_std_init": -1.5,
                                   "ForceStiffnessAction.rate_penalty": 0.2, "n_envs": 64})
    c = load_config_from(new)
    assert c.ppo_kwargs["learning_rate"] == "lin_0.0005"  # the schedule is kept
    assert c.policy_kwargs["log_std_init"] == -1.5 and c.n_envs == 64
    assert c.action_wrapper["rate_penalty"] == 0.2
    assert c.action_wrapper["force_N"] == b.action_wrapper["force_N"]


def load_config_from(doc):
    from mpa_gym.agents.learned.config import parse_config

    return parse_config(json.loads(json.dumps(doc)))


@pytest.mark.parametrize("space, match", [
    ({"lr": {"float": [1e-3, 1e-4]}}, r"lr\.float=\[0\.001, 0\.0001\] must be \[low, high\]"),
    ({"lr": {"float": [0.0, 1.0], "log": True}}, "log=true needs low > 0"),
    ({"lr": {"uniform": [0, 1]}}, "needs exactly one of float / int / categorical"),
    ({"n_envs": {"categorical": []}}, "n_envs.categorical=.* non-empty list"),
    ({"n_epochs": {"int": [1.5, 4]}}, "must be whole numbers"),
    ({"net.x": {"float": [0, 1]}}, "dotted name must start with policy_kwargs"),
    ({}, "non-empty mapping"),
])
def test_malformed_search_space_is_named(space, match):
    with pytest.raises(ConfigError, match=match):
        parse_space(space)


def test_bad_input_exits_2_naming_it_and_keeps_the_study(tmp_path, capsys):
    db = f"sqlite:///{tmp_path}/s.db"
    cfg = tiny_tune_config(tmp_path / "c.yaml")
    held = short_heldout(tmp_path / "h.yaml")
    out = tune(cfg, db, "s", n_trials=1, heldout=[str(held)], out_dir=tmp_path / "runs")
    assert out["states"] == {"COMPLETE": 1}
    # a study name that exists with another search space
    other = tiny_tune_config(tmp_path / "o.yaml",
                             {"learning_rate": {"float": [1e-4, 2e-3], "log": True}})
    assert main(["tune", "--config", str(other), "--storage", db, "--study-name", "s"]) == 2
    err = capsys.readouterr().err
    assert "--study-name='s' exists with a different search space" in err
    assert "['learning_rate', 'ForceStiffnessAction.rate_penalty']" in err or \
        "learning_rate" in err
    # an unreachable database (nothing listens on the port we just released)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"postgresql://nobody@127.0.0.1:{port}/x"
    assert main(["tune", "--config", str(cfg), "--storage", url]) == 2
    err = capsys.readouterr().err
    assert f"--storage='{url}': cannot open the study storage" in err and "refused" in err
    # a malformed search space
    bad = tiny_tune_config(tmp_path / "b.yaml", {"n_epochs": {"int": [3, 1]}})
    assert main(["tune", "--config", str(bad), "--storage", db, "--study-name", "s"]) == 2
    assert "mpa_gym.tune.n_epochs.int=[3, 1] must be [low, high]" in capsys.readouterr().err
    assert main(["tune", "--storage", db, "--n-trials", "0"]) == 2
    assert "--n-trials=0 must be a whole number in [1, 1000000]" in capsys.readouterr().err
    # nothing already in the study was lost
    study = optuna.load_study(study_name="s", storage=db)
    assert [t.state for t in study.trials] == [TrialState.COMPLETE]


def test_best_writes_a_config_that_trains(tmp_path):
    db = f"sqlite:///{tmp_path}/s.db"
    cfg = tiny_tune_config(tmp_path / "c.yaml")
    held = short_heldout(tmp_path / "h.yaml")
    tune(cfg, db, "s", n_trials=2, heldout=[str(held)], out_dir=tmp_path / "runs")
    study = optuna.load_study(study_name="s", storage=db)
    first = study.trials[0]
    assert first.user_attrs["base_config"] is True  # trial 0 is the config as written
    assert first.params["learning_rate"] == pytest.approx(3e-4)
    assert first.user_attrs["wall_s"] > 0 and len(first.values) == 2
    res = write_best(db, "s", tmp_path / "best.yaml")
    best = min(study.best_trials, key=lambda t: t.values[0])
    assert res["trial"] == best.number
    loaded = load_config(tmp_path / "best.yaml")
    assert loaded.ppo_kwargs["learning_rate"] == f"lin_{best.params['learning_rate']!r}"
    assert loaded.action_wrapper["rate_penalty"] == best.params[
        "ForceStiffnessAction.rate_penalty"]


def test_a_combination_ppo_refuses_is_pruned_and_named(tmp_path):
    # The default space holds n_steps 32 with n_envs 16 and batch_size 1024: a 512-sample
    # rollout that PPO cannot split into 1024-sample minibatches. Such a trial is pruned
    # before training, with the config's own message, and the worker goes on to the next.
    # (The tiny config's rollout is 4 x 32 = 128 samples: batch_size 64 fits, 256 does not;
    # the two 256 trials are queued, as a sampler would draw them.)
    db = f"sqlite:///{tmp_path}/s.db"
    cfg = tiny_tune_config(tmp_path / "c.yaml", {"batch_size": {"categorical": [64, 256]}})
    study = optuna.create_study(storage=db, study_name="bad",
                                directions=["minimize"] * len(OBJECTIVES["both"]))
    for _ in range(2):
        study.enqueue_trial({"batch_size": 256})
    tune(cfg, db, "bad", n_trials=2, heldout=[str(short_heldout(tmp_path / "h.yaml"))],
         out_dir=tmp_path / "runs")
    trials = optuna.load_study(study_name="bad", storage=db).trials
    assert len(trials) == 2
    for t in trials:
        assert t.state == TrialState.PRUNED and t.params["batch_size"] == 256
        assert "batch_size=256 must be <= n_steps * n_envs" in t.user_attrs["invalid"]
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").rglob("model.zip"))


def test_a_space_no_trial_can_satisfy_is_refused_before_any_trial(tmp_path):
    # every point pruned would be a study that exits 0 having tuned nothing
    db = f"sqlite:///{tmp_path}/s.db"
    cfg = tiny_tune_config(tmp_path / "c.yaml", {"batch_size": {"categorical": [256]}})
    with pytest.raises(ConfigError, match=r"no point of the search space makes a valid config"
                       r".*batch_size=256 must be <= n_steps \* n_envs = 128"):
        tune(cfg, db, "bad", n_trials=2, heldout=[str(short_heldout(tmp_path / "h.yaml"))],
             out_dir=tmp_path / "runs")
    assert optuna.get_all_study_names(db) == []


def test_position_objective_reports_and_prunes_per_seed_step(tmp_path):
    db = f"sqlite:///{tmp_path}/s.db"
    cfg = tiny_tune_config(tmp_path / "c.yaml")
    held = short_heldout(tmp_path / "h.yaml")
    tune(cfg, db, "p", n_trials=1, seeds_per_trial=2, objective="position",
         heldout=[str(held)], out_dir=tmp_path / "runs")
    t = optuna.load_study(study_name="p", storage=db).trials[0]
    # seed 0 evaluated at 0 and 128 steps, seed 1 at 129 + 0 and 129 + 128
    assert sorted(t.intermediate_values) == [0, 128, 129, 257]
    assert len(t.user_attrs["per_seed"]) == 2 and t.user_attrs["stiffness_err_pct"] > 0


def test_a_trial_scores_its_policy_alone_and_counts_its_hand_overs(tmp_path):
    # A supervisor with a hair trigger (the error's RMS over 0.5 s passing 0.05 mm) hands the
    # held-out episode (a plant 0.1 kg off, behind a 30 ms lag) to pid. The
    # trial's values are the policy's own: its run evaluated without the supervisor, in a
    # report of its own; the supervised run's hand-over is recorded.
    path = tiny_tune_config(tmp_path / "c.yaml")
    doc = yaml.safe_load(path.read_text())
    doc["mpa_gym"]["supervisor"]["monitors"]["divergence"] = {
        "level_mm": 0.05, "window_s": 0.5, "clip_mm": None, "arm_periods": 0}
    path.write_text(yaml.safe_dump(doc))
    held = str(short_heldout(tmp_path / "h.yaml"))
    db = f"sqlite:///{tmp_path}/s.db"
    out = tune(path, db, "h", n_trials=1, heldout=[held], out_dir=tmp_path / "runs")
    t = optuna.load_study(study_name="h", storage=db).trials[0]
    assert t.user_attrs["hand_overs"] == 1 and t.user_attrs["per_seed"][0]["hand_overs"] == 1
    assert out["pareto_front"][0]["hand_overs"] == 1
    run = t.user_attrs["run_dirs"][0]
    seed = load_config(Path(run) / "config.yaml").eval_seed
    alone = evaluate([run + ALONE], [held], seed)["results"]["short_heldout"]
    supervised = evaluate([run], [held], seed)["results"]["short_heldout"]
    assert t.values[0] == alone[f"{Path(run).name} (alone)"]["position_rmse_mm"]
    assert t.values[1] == alone[f"{Path(run).name} (alone)"]["stiffness_rmse_pct"]
    assert supervised[Path(run).name]["fallback_s"] is not None
    assert t.values[0] != supervised[Path(run).name]["position_rmse_mm"]


# ------------------------------------------------------------------------ PostgreSQL

def _pg_bin() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    return Path(found[-1]).parent if found else None


@pytest.fixture
def postgres():
    """A PostgreSQL server in a temporary data directory on a free loopback port, run as the
    ``postgres`` user (the server refuses root); stopped and removed afterwards."""
    bindir = _pg_bin()
    if bindir is None:
        if os.environ.get("CI") == "true":
            pytest.fail("CI=true but no PostgreSQL under /usr/lib/postgresql/*/bin (.ci/run "
                        "installs Debian's postgresql package)")
        pytest.skip("PostgreSQL binaries not installed (/usr/lib/postgresql/*/bin/initdb); "
                    "`apt-get install postgresql`")
    user = "postgres" if os.geteuid() == 0 else pwd.getpwuid(os.geteuid()).pw_name
    # under /tmp itself: pytest's tmp_path is private to root, the server user cannot reach it
    home = Path(tempfile.mkdtemp(prefix="mpa-gym-pg-"))
    if os.geteuid() == 0:
        shutil.chown(home, user)
        run_as = ["runuser", "-u", user, "--"]
    else:
        run_as = []
    data = home / "data"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    def pg(*args: str) -> None:
        r = subprocess.run([*run_as, *args], capture_output=True, text=True)
        assert r.returncode == 0, f"{args[0]} failed: {r.stdout}{r.stderr}"

    opts = f"-p {port} -k {home} -c listen_addresses=127.0.0.1 -c fsync=off"
    try:
        pg(str(bindir / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres",
           "--no-sync")
        pg(str(bindir / "pg_ctl"), "-D", str(data), "-o", opts, "-l", str(home / "log"), "-w",
           "-t", "30", "start")
        yield f"postgresql://postgres@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run([*run_as, str(bindir / "pg_ctl"), "-D", str(data), "-m", "immediate",
                        "stop"], capture_output=True)
        shutil.rmtree(home, ignore_errors=True)


def test_two_workers_share_a_postgresql_study_up_to_the_cap(tmp_path, postgres):
    cfg = tiny_tune_config(tmp_path / "c.yaml")
    held = short_heldout(tmp_path / "h.yaml")
    cap = 4
    cmd = [sys.executable, "-m", "mpa_gym.agents.cli", "tune", "--config", str(cfg), "--storage",
           postgres, "--study-name", "pg", "--n-trials", "3", "--max-total-trials", str(cap),
           "--heldout", str(held), "--out-dir", str(tmp_path / "runs"), "--json"]
    env = {**os.environ, "MPLBACKEND": "Agg"}
    t0 = time.monotonic()
    workers = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=env) for _ in range(2)]
    outs = [w.communicate(timeout=300) for w in workers]
    for w, (_out, err) in zip(workers, outs, strict=True):
        assert w.returncode == 0, err
    print(f"two workers: {time.monotonic() - t0:.1f} s")
    study = optuna.load_study(study_name="pg", storage=postgres.replace(
        "postgresql://", "postgresql+psycopg2://"))
    trials = study.get_trials(deepcopy=False)
    done = [t for t in trials if t.state == TrialState.COMPLETE]
    # exactly the cap finished; anything else is a trial closed untrained beyond the cap
    assert len(done) == cap
    extra = [t for t in trials if t not in done]
    assert all(t.state == TrialState.FAIL and t.user_attrs.get("over_cap") for t in extra)
    # no trial lost or duplicated: numbers 0..n-1 once each, each complete one with its values
    assert sorted(t.number for t in trials) == list(range(len(trials)))
    assert all(len(t.values) == 2 for t in done)
    params = [tuple(sorted(t.params.items())) for t in done]
    assert len(set(params)) == cap
    # both workers contributed, and each says how many of the finished trials it ran
    workers_of = {t.user_attrs["worker"] for t in done}
    assert len(workers_of) == 2
    summaries = [json.loads(out) for out, _ in outs]
    assert sum(s["by_this_worker"] for s in summaries) == cap


def test_postgresql_without_its_driver_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "psycopg2", None)  # import psycopg2 raises ImportError
    with pytest.raises(ValueError, match=r"postgresql://u@127.0.0.1:9/db.*postgres extra"):
        open_storage("postgresql://u@127.0.0.1:9/db")


def test_journal_file_storage(tmp_path):
    cfg = tiny_tune_config(tmp_path / "c.yaml")
    held = short_heldout(tmp_path / "h.yaml")
    log = tmp_path / "journal.log"
    out = tune(cfg, f"journal:{log}", "j", n_trials=1, heldout=[str(held)],
               out_dir=tmp_path / "runs")
    assert out["states"] == {"COMPLETE": 1}
    study = optuna.load_study(study_name="j", storage=open_storage(f"journal:{log}"))
    assert study.trials[0].state == TrialState.COMPLETE


# ------------------------------------------------------------------------ seeds and intervals

def test_iqm_and_ci_match_an_independent_trimmed_mean():
    from scipy.stats import trim_mean

    from mpa_gym.agents.evaluation.seeds import iqm_ci

    rng = np.random.default_rng(0)
    scores = rng.lognormal(size=(8, 3))
    point, ci = iqm_ci(scores)
    # rliable's IQM is the 25 %-trimmed mean of each task's runs
    np.testing.assert_allclose(point, trim_mean(scores, 0.25, axis=0), rtol=1e-12)
    assert np.all(ci[0] <= point) and np.all(point <= ci[1])
    assert np.all(ci[0] >= scores.min(axis=0)) and np.all(ci[1] <= scores.max(axis=0))
    # more runs from the same distribution: a narrower interval
    _, ci_many = iqm_ci(rng.lognormal(size=(64, 3)))
    assert np.all(ci_many[1] - ci_many[0] < ci[1] - ci[0])


def test_train_seeds_makes_sibling_runs_that_evaluate_as_one_group(tmp_path, monkeypatch,
                                                                    capsys):
    cfg = tiny_tune_config(tmp_path / "c.yaml")
    assert main(["train", "--config", str(cfg), "--seeds", "3", "4", "--run-dir",
                 str(tmp_path / "r"), "--n-timesteps", "128", "--json"]) == 0
    runs = [tmp_path / "r-s3", tmp_path / "r-s4"]
    for r, seed in zip(runs, (3, 4), strict=True):
        assert yaml.safe_load((r / "config.yaml").read_text())["mpa_gym"]["seed"] == seed
        assert (r / "model.zip").is_file()
    held = short_heldout(tmp_path / "h.yaml")
    # without the stats extra: refused before any episode, naming the extra
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "rliable", None)  # import rliable raises ImportError
        assert main(["evaluate", "--policy", *map(str, runs), "ff", "--scenarios", str(held),
                     "--out", str(tmp_path / "rep"), "--json"]) == 2
    assert "stats" in capsys.readouterr().err
    assert not (tmp_path / "rep" / "report.json").exists()
    assert main(["evaluate", "--policy", *map(str, runs), "ff", "--scenarios", str(held),
                 "--out", str(tmp_path / "rep"), "--json"]) == 0
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())
    g = rep["groups"]["r"]
    assert g["runs"] == ["r-s3", "r-s4"]
    per_run = [rep["results"]["short_heldout"][n]["position_rmse_mm"] for n in g["runs"]]
    a = g["results"]["short_heldout"]
    # two runs: the IQM is their mean, the bootstrap interval spans them
    assert a["position_rmse_mm"] == pytest.approx(np.mean(per_run), rel=1e-12)
    np.testing.assert_allclose(a["position_rmse_mm_ci"], sorted(per_run), rtol=1e-12)
    md = (tmp_path / "rep" / "report.md").read_text()
    table = md.split("## position RMSE")[1].split("##")[0]
    assert "| r (IQM [95 % CI]) |" in table and "r-s3" not in table
    assert (tmp_path / "rep" / "plots" / "learning_curves.png").is_file()
    assert main(["train", "--seeds", "1", "1"]) == 2


def test_a_killed_workers_trial_is_marked_failed_and_the_study_resumes(tmp_path):
    """SIGKILL a worker mid-trial; the next worker marks the silent trial FAIL (heartbeat 1 s,
    grace 2 s), reruns its parameters and leaves the finished trial as it was."""
    cfg = tiny_tune_config(tmp_path / "c.yaml")
    held = short_heldout(tmp_path / "h.yaml")
    db = f"sqlite:///{tmp_path}/s.db"
    base = [sys.executable, "-m", "mpa_gym.agents.cli", "tune", "--config", str(cfg),
            "--storage", db, "--study-name", "k", "--heartbeat", "1", "--heldout", str(held),
            "--out-dir", str(tmp_path / "runs")]
    env = {**os.environ, "MPLBACKEND": "Agg"}
    kw = {"heartbeat_s": 1, "heldout": [str(held)], "out_dir": tmp_path / "runs"}
    tune(cfg, db, "k", n_trials=1, **kw)
    victim = subprocess.Popen([*base, "--n-trials", "1", "--n-timesteps", "100000"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # wait until its trial trains (it trains for long)
        trials = optuna.load_study(study_name="k", storage=db).trials
        if len(trials) == 2 and "worker" in trials[1].user_attrs:  # inside the objective: beating
            break
        time.sleep(0.5)
    else:
        victim.kill()
        pytest.fail("the second worker never started its trial")
    time.sleep(1.0)
    victim.kill()
    victim.wait()
    # past the grace period (2 s): SQLite's CURRENT_TIMESTAMP, which Optuna stamps heartbeats
    # and "now" with, has whole seconds, so a real gap of 2.5 s can read as 2 s (not stale)
    time.sleep(3.5)
    tune(cfg, db, "k", n_trials=1, **kw)
    trials = optuna.load_study(study_name="k", storage=db).trials
    assert [t.state for t in trials] == [TrialState.COMPLETE, TrialState.FAIL,
                                         TrialState.COMPLETE]
    assert trials[2].params == trials[1].params  # the killed trial's parameters, rerun
    assert trials[2].system_attrs.get("failed_trial") == trials[1].number
    assert len(trials[0].values) == 2


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_signalled_worker_says_so_in_one_line_and_queues_its_trial_again(tmp_path, sig):
    """SIGTERM / Ctrl-C inside a trial's training: exit 143 / 130 with one line and no
    traceback (Optuna logs a failed trial with its traceback), the trial FAILED and queued
    again with its parameters, its run folder kept."""
    import signal

    cfg = tiny_tune_config(tmp_path / "c.yaml")
    db = f"sqlite:///{tmp_path}/s.db"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mpa_gym.agents.cli", "tune", "--config", str(cfg), "--storage",
         db, "--study-name", "k", "--heldout", str(short_heldout(tmp_path / "h.yaml")),
         "--out-dir", str(tmp_path / "runs"), "--n-trials", "1", "--n-timesteps", "1000000"],
        env={**os.environ, "MPLBACKEND": "Agg"}, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    deadline = time.monotonic() + 120
    while not glob.glob(str(tmp_path / "runs" / "trial0000-s0" / "tb" / "*")):  # learning
        if time.monotonic() > deadline or proc.poll() is not None:
            proc.kill()
            pytest.fail(f"the trial never started training: {proc.communicate()[1]}")
        time.sleep(0.2)
    time.sleep(1.0)
    proc.send_signal(getattr(signal, sig))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + getattr(signal, sig), err
    assert "Traceback" not in err, err
    line = [ln for ln in err.splitlines() if ln.startswith("mpa-gym tune:")]
    assert line == [ln for ln in err.splitlines() if not ln.startswith("[I ")], err
    assert f"interrupted by {sig} in trial 0" in line[0] and "queued again" in line[0], err
    trials = optuna.load_study(study_name="k", storage=db).trials
    assert [t.state for t in trials] == [TrialState.FAIL, TrialState.WAITING]
    assert trials[1].system_attrs.get("failed_trial") == 0
    assert (tmp_path / "runs" / "trial0000-s0" / "model.zip").is_file()


def test_a_trial_stopped_by_a_signal_is_not_logged_as_a_failure(caplog):
    """Within ``quiet_signalled_trials`` Optuna's failed-trial record (its traceback and the
    "failed with value None" line) is dropped for a trial stopped by Ctrl-C or by an exception
    that carries a signal number, and kept for one that carries none (the NaN guard's)."""
    from mpa_gym.agents.training.trials import quiet_signalled_trials

    class Stopped(Exception):
        def __init__(self, signum):
            super().__init__(f"stopped ({signum})")
            self.signum = signum

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    optuna.logging.enable_propagation()  # to caplog, after the logger's own filters
    try:
        for exc, shown in ((KeyboardInterrupt(), False), (Stopped(15), False),
                           (Stopped(None), True)):
            study = optuna.create_study()

            def objective(trial, exc=exc):
                raise exc

            caplog.clear()
            with quiet_signalled_trials(), pytest.raises(type(exc)):
                study.optimize(objective, n_trials=1)
            traced = any(r.exc_info and r.exc_info[1] is exc for r in caplog.records)
            failed = any("failed with value None" in r.getMessage() for r in caplog.records)
            assert traced is shown and failed is shown, (exc, caplog.text)
            assert study.trials[0].state == TrialState.FAIL
    finally:
        optuna.logging.disable_propagation()


def test_tune_baselines_stopped_by_sigterm_says_so_in_one_line(tmp_path):
    """tune-baselines spends its time inside Optuna trials: a SIGTERM there printed Optuna's
    failed-trial traceback and "failed with value None" above the CLI's line. 10 s is well
    into the 100,000 trials (its set-up takes ~3 s; the study never ends on its own); the
    filter itself is checked in-process above."""
    import signal

    proc = subprocess.Popen(
        [sys.executable, "-m", "mpa_gym.agents.cli", "tune-baselines", "--policy", "pid",
         "--n-trials", "100000", "--n-plants", "1", "--episode-s", "3", "--out",
         str(tmp_path / "g.yaml")],
        env={**os.environ, "MPLBACKEND": "Agg"}, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    time.sleep(10.0)
    assert proc.poll() is None, proc.communicate()[1]
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert err == "mpa-gym tune-baselines: interrupted by SIGTERM\n", err
    assert not (tmp_path / "g.yaml").exists()  # nothing half-tuned written


def test_a_trial_killed_before_its_first_heartbeat_is_failed_and_rerun(tmp_path):
    """A worker killed between Optuna's ask and its first heartbeat leaves a RUNNING trial that
    Optuna never finds stale (it has no heartbeat) and that would count toward the cap for ever.
    Played here by asking for a trial and never running it; the next worker, once the grace
    period (2 × 1 s) has passed, fails it and reruns its parameters."""
    cfg = tiny_tune_config(tmp_path / "c.yaml")
    held = short_heldout(tmp_path / "h.yaml")
    db = f"sqlite:///{tmp_path}/s.db"
    kw = {"heartbeat_s": 1, "heldout": [str(held)], "out_dir": tmp_path / "runs"}
    tune(cfg, db, "o", n_trials=1, **kw)  # creates the study with its space and objectives
    study = optuna.load_study(study_name="o", storage=open_storage(db, 1))
    orphan = study.ask({"learning_rate": optuna.distributions.FloatDistribution(1e-4, 1e-3,
                                                                                 log=True)})
    assert fail_orphans(study, study._storage, grace_s=2.0) == []  # too young: may be alive
    time.sleep(2.5)
    summary = tune(cfg, db, "o", n_trials=1, max_total_trials=2, **kw)
    trials = optuna.load_study(study_name="o", storage=db).trials
    assert [t.state for t in trials] == [TrialState.COMPLETE, TrialState.FAIL,
                                         TrialState.COMPLETE]
    assert trials[1].number == orphan.number
    assert trials[2].system_attrs.get("failed_trial") == orphan.number
    assert trials[2].params["learning_rate"] == orphan.params["learning_rate"]
    # the orphan no longer counts toward the cap of 2: the worker ran one trial
    assert summary["states"] == {"COMPLETE": 2, "FAIL": 1}
