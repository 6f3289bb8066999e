"""Training loses nothing: kills and signals (real subprocesses, real signals), resume from the
newest complete state, atomic artefacts, the NaN guard, damaged files named."""

from __future__ import annotations

import itertools
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
import yaml
from conftest import alive, children, default_sigint, wait_gone
from stable_baselines3 import PPO

from mpa_gym.agents.cli import main
from mpa_gym.agents.learned.config import load_config
from mpa_gym.agents.learned.policies import load_run
from mpa_gym.agents.learned.runs import (
    latest_state,
    read_eval_history,
    write_eval_history,
    zip_timesteps,
)
from mpa_gym.agents.training.train import TrainingStopped, train

EV = {"name": "ev", "duration_s": 0.5}


def tiny_config(tmp_path, n_timesteps=256, checkpoint_freq=256, eval_freq=256, **over):
    cfg = yaml.safe_load(open("configs/ppo_residual.yaml"))
    hp = cfg["MPALegResidual-v0"]
    hp.update(n_envs=4, n_timesteps=n_timesteps, n_steps=32, batch_size=64, n_epochs=1)
    hp["env_kwargs"]["task"]["episode_s"] = 0.5
    hp.update(over)
    cfg["mpa_gym"].update(eval_scenarios=[EV], eval_freq=eval_freq,
                          checkpoint_freq=checkpoint_freq)
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def start(args, **kw):
    return subprocess.Popen([sys.executable, "-m", "mpa_gym.agents.cli", "train", "--no-progress",
                             *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=default_sigint, **kw)


def markers(run):
    return sorted(int(p.name.split("_")[1]) for p in (run / "checkpoints").glob("ppo_*_steps.json"))


def wait_for_checkpoint_after(proc, run, steps, timeout=120.0):
    """Wait until a complete checkpoint beyond ``steps`` exists (the process still running)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if (run / "checkpoints").is_dir() and markers(run) and markers(run)[-1] > steps:
            return markers(run)[-1]
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    raise AssertionError("no new checkpoint within the timeout")


def finite_model(path):
    model = PPO.load(path, device="cpu")
    return all(bool(torch.isfinite(p).all()) for p in model.policy.parameters())


# the kill points of the test below; MPA_TEST_SEED=N explores others
KILL_SEED = int(os.environ.get("MPA_TEST_SEED", "20261201"))


def test_killed_twice_at_random_points_resumes_without_going_back(tmp_path):
    rng = random.Random(KILL_SEED)  # the kill points; the seed is in every failure message
    print(f"kill points: MPA_TEST_SEED={KILL_SEED}")
    run = tmp_path / "run"
    # 16 envs x 32 steps per rollout and one 512-sample batch per update: ~1000 env steps/s on
    # the 2-core machine, so the total is several times what can run within the two kill
    # windows (a checkpoint interval, then at most 0.5 s, after each process's start-up) and
    # both kills land before the run ends
    total = 8192
    proc = start(["--config", str(tiny_config(tmp_path, total, checkpoint_freq=256,
                                              eval_freq=1024, n_envs=16, batch_size=512)),
                  "--run-dir", str(run)])
    reached = []  # the newest complete checkpoint when each kill happened
    errs = []  # stderr of each resumed process
    for _ in range(2):
        wait_for_checkpoint_after(proc, run, reached[-1] if reached else 0)
        time.sleep(rng.uniform(0.0, 0.5))  # a random point: mid-rollout, mid-update, mid-save
        assert proc.poll() is None, (KILL_SEED, "the run ended before the kill: raise total",
                                     proc.communicate())
        os.kill(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        if reached:
            errs.append(err)
        reached.append(markers(run)[-1])
        assert reached[-1] < total, KILL_SEED
        proc = start(["--resume", str(run)])
    print(f"killed after the checkpoints at {reached} of {total} steps")
    _, err = proc.communicate(timeout=300)
    errs.append(err)
    assert proc.returncode == 0, (KILL_SEED, err)
    assert not any("Traceback" in e for e in errs), (KILL_SEED, errs)
    # each resume said where it started, and never below the newest complete checkpoint
    starts = [int(re.search(r"at (\d+) env steps", e).group(1)) for e in errs]
    assert starts == reached, (KILL_SEED, errs)
    final = zip_timesteps(run / "model.zip")
    assert final >= total, KILL_SEED
    assert finite_model(run / "model.zip")
    # the evaluation history's step counts never go backwards, nor beyond the model
    hist, ts, _, _ = read_eval_history(run / "eval")
    assert [h["timesteps"] for h in hist] == ts
    assert all(b > a for a, b in itertools.pairwise(ts)), (KILL_SEED, ts)
    assert ts[-1] <= final
    _, cfg = load_run(run)  # and the run loads like any other
    assert cfg.n_timesteps == total


@pytest.mark.parametrize(("sig", "group"), [(signal.SIGTERM, False), (signal.SIGINT, False),
                                            (signal.SIGINT, True)])
def test_sigterm_and_ctrl_c_save_like_a_normal_end(tmp_path, sig, group):
    """``group``: the signal goes to the whole process group, as a terminal's Ctrl-C does, so
    the evaluation worker gets it too (and ignores it: training decides)."""
    run = tmp_path / "run"
    proc = start(["--config", str(tiny_config(tmp_path, 10**6, checkpoint_freq=128)),
                  "--run-dir", str(run), "--eval-worker"], start_new_session=group)
    newest = wait_for_checkpoint_after(proc, run, 0)
    if group:
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("mpa-gym train:")]
    assert len(lines) == 1 and f"stopped by {signal.Signals(sig).name}" in lines[0], err
    saved = zip_timesteps(run / "model.zip")
    assert saved >= newest and markers(run)[-1] == saved  # the stop wrote a checkpoint too
    assert finite_model(run / "model.zip")
    assert latest_state(run, True)[0] == saved


def _poison_update(monkeypatch, n):
    """The n-th PPO update sets a weight to NaN (a diverging update)."""
    calls = {"n": 0}
    original = PPO.train

    def poisoned(self):
        original(self)
        calls["n"] += 1
        if calls["n"] == n:
            with torch.no_grad():
                next(iter(self.policy.parameters())).fill_(float("nan"))

    monkeypatch.setattr(PPO, "train", poisoned)


def test_nan_guard_stops_and_keeps_the_last_finite_state(tmp_path, monkeypatch):
    _poison_update(monkeypatch, 4)
    run = tmp_path / "run"
    with pytest.raises(TrainingStopped, match="NaN guard") as e:
        train(tiny_config(tmp_path, 4096, checkpoint_freq=128), run, progress=False)
    # updates 1-3 were finite: 3 rollouts of 128 steps, then the 4th rollout ran on the 3rd
    # update's weights before the diverging update
    assert e.value.signum is None and e.value.timesteps == 3 * 128 + 128
    assert markers(run)[-1] == e.value.timesteps
    for p in (run / "checkpoints").glob("ppo_*_steps.zip"):
        assert finite_model(p), p
    assert not (run / "model.zip").exists() or finite_model(run / "model.zip")
    assert "kept the last finite state" in str(e.value)
    # training builds its distributions unchecked (the guard above is what stops a NaN policy);
    # torch's default check is back once train returns, here by an error
    import torch.distributions as td

    assert td.Distribution._validate_args is True


def test_nan_guard_catches_the_last_update(tmp_path, monkeypatch):
    """The update after the last rollout diverges: no rollout follows to run the guard, so
    learn() returns normally; training must still stop, save nothing non-finite, and say so."""
    _poison_update(monkeypatch, 2)  # 256 steps: two rollouts of 128, two updates
    run = tmp_path / "run"
    with pytest.raises(TrainingStopped, match="NaN guard: the last PPO update") as e:
        train(tiny_config(tmp_path, 256, checkpoint_freq=128), run, progress=False)
    # the checkpoint at 256 steps was written during the 2nd rollout, before the bad update
    assert e.value.signum is None and e.value.timesteps == 256 == markers(run)[-1]
    assert "kept the last finite state, checkpoints/ppo_256_steps.zip at 256 steps" in str(e.value)
    for p in (run / "checkpoints").glob("ppo_*_steps.zip"):
        assert finite_model(p), p
    assert not (run / "model.zip").exists()  # never saved non-finite


def kill_after(run, steps):
    """The run folder as a SIGKILL leaves it once the newest complete checkpoint is ``steps``:
    no model.zip, later checkpoints torn (no marker)."""
    (run / "model.zip").unlink(missing_ok=True)
    for m in (run / "checkpoints").glob("ppo_*_steps.json"):
        if int(m.name.split("_")[1]) > steps:
            m.unlink()


def test_the_step_budget_of_n_timesteps_survives_a_kill(tmp_path, capsys):
    """--n-timesteps is written into the run's config.yaml, so a killed run resumed without it
    trains to the budget it was started with, not to the config file's."""
    run = tmp_path / "run"
    train(tiny_config(tmp_path, 512, checkpoint_freq=128), run, n_timesteps=256, progress=False)
    assert load_config(run / "config.yaml").n_timesteps == 256
    kill_after(run, 128)
    train(resume=run, progress=False)
    assert zip_timesteps(run / "model.zip") == 256  # not the file's 512
    # on resume, --n-timesteps N trains N more: the budget becomes the steps done + N
    train(resume=run, n_timesteps=128, progress=False)
    assert "config.yaml: n_timesteps 256 -> 384" in capsys.readouterr().err
    assert load_config(run / "config.yaml").n_timesteps == 384
    kill_after(run, 256)
    train(resume=run, progress=False)
    assert zip_timesteps(run / "model.zip") == 384


@pytest.fixture(scope="module")
def evaluated_run(tmp_path_factory):
    """A finished run: evaluations at 0, 256 and 512 steps, checkpoints every 128."""
    tmp = tmp_path_factory.mktemp("best")
    return train(tiny_config(tmp, 512, checkpoint_freq=128, eval_freq=256), tmp / "run",
                 progress=False)


@pytest.mark.parametrize(("returns", "kept_best"), [([-10.0, 1e9, 2e9], 256),
                                                    ([1e9, -5.0, 2e9], None)])
def test_resume_drops_a_best_model_of_the_discarded_timeline(evaluated_run, tmp_path, capsys,
                                                             returns, kept_best):
    """Killed after the evaluation at 512 steps saved best/ but before the checkpoint at 512:
    the resume cuts that evaluation, and best/ with it. It comes back from the checkpoint at the
    best kept evaluation (256), or, the best kept being the initial policy (no checkpoint at
    step 0), is removed until the next evaluation writes one: here the held-out evaluation at
    the resumed run's last step. The returns are set by hand to make each case (a kept best of
    1e9 no real episode beats)."""
    run = tmp_path / "run"
    shutil.copytree(evaluated_run, run)
    hist, ts, _, lens = read_eval_history(run / "eval")
    assert ts == [0, 256, 512]
    write_eval_history(run / "eval", hist, ts, [[r] for r in returns], lens)
    for src, dst in (("ppo_512_steps.zip", "best_model.zip"),
                     ("ppo_vecnormalize_512_steps.pkl", "vecnormalize.pkl")):
        shutil.copy(run / "checkpoints" / src, run / "best" / dst)
    kill_after(run, 384)
    train(resume=run, n_timesteps=64, progress=False)  # one rollout, then the final evaluation
    err = capsys.readouterr().err
    assert "best/ was saved at step 512 by an evaluation after step 384" in err, err
    best = run / "best" / "best_model.zip"
    if kept_best is not None:
        assert f"re-derived it from checkpoints/ppo_{kept_best}_steps.zip" in err, err
        ck = run / "checkpoints"
        assert best.read_bytes() == (ck / f"ppo_{kept_best}_steps.zip").read_bytes()
        assert (run / "best" / "vecnormalize.pkl").read_bytes() == \
            (ck / f"ppo_vecnormalize_{kept_best}_steps.pkl").read_bytes()
    else:
        assert "removed it" in err, err
        assert zip_timesteps(best) == 512  # the next evaluation, the final one, wrote best/
    _, ts, _, _ = read_eval_history(run / "eval")
    assert max(ts) <= zip_timesteps(run / "model.zip")


def test_a_torn_checkpoint_is_skipped_and_said(tmp_path, capsys):
    run = train(tiny_config(tmp_path, 512, checkpoint_freq=128), tmp_path / "run",
                progress=False)
    newest = markers(run)[-1]
    # a kill between writing the model and its marker leaves a checkpoint without a marker;
    # one whose file was truncated afterwards is named and skipped
    zpath = run / "checkpoints" / f"ppo_{newest}_steps.zip"
    zpath.write_bytes(zpath.read_bytes()[:100])
    (run / "model.zip").unlink()
    state = latest_state(run, True)
    assert state[0] < newest and any("skipped damaged checkpoint" in n for n in state[3])
    train(resume=run, n_timesteps=128, progress=False)
    err = capsys.readouterr().err
    assert "skipped damaged checkpoint" in err and f"at {state[0]} env steps" in err
    assert "dropped" in err  # the evaluations after that state went with it, said so


@pytest.mark.parametrize("damage", ["vecnormalize.pkl", "eval/evaluations.npz",
                                    "eval/evaluations.json", "model.zip"])
def test_damaged_files_are_named(tmp_path, damage, capsys):
    run = train(tiny_config(tmp_path, 128, checkpoint_freq=128), tmp_path / "run",
                progress=False)
    path = run / damage
    path.write_bytes(path.read_bytes()[: max(1, path.stat().st_size // 3)])
    code = main(["evaluate", "--policy", str(run), "--scenarios", "nominal", "--out",
                 str(tmp_path / "ev")])
    err = capsys.readouterr().err
    assert code == 2 and str(path) in err and "damaged" in err, err
    assert not (tmp_path / "ev" / "report.json").exists()


def test_atomic_writes_leave_no_torn_artefacts(tmp_path):
    """Every file of a finished run loads; no temporary file is left behind."""
    run = train(tiny_config(tmp_path, 256, checkpoint_freq=128), tmp_path / "run",
                progress=False)
    assert not list(run.rglob(".*.tmp"))
    for marker in (run / "checkpoints").glob("ppo_*_steps.json"):
        meta = json.loads(marker.read_text())
        for name, size in meta["files"].items():
            assert (marker.parent / name).stat().st_size == size
    hist, ts, res, _ = read_eval_history(run / "eval")
    assert len(hist) == len(ts) == len(res) and np.all(np.isfinite(res))
    assert load_config(run / "config.yaml").n_timesteps == 256


@pytest.mark.parametrize("total", [4096, 256])  # the 2nd update: mid-run, or the last one
def test_nan_guard_on_the_command_line_exits_1_with_one_line(tmp_path, monkeypatch, capsys,
                                                             total):
    _poison_update(monkeypatch, 2)
    code = main(["train", "--config", str(tiny_config(tmp_path, total, checkpoint_freq=128)),
                 "--run-dir", str(tmp_path / "run"), "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and err.count("\n") == 1, err
    assert err.startswith("mpa-gym train: NaN guard:") and "kept the last finite state" in err


# ----------------------------------------------------------------------------- evaluation worker
def _state(path):
    return PPO.load(path, device="cpu").policy.state_dict()


def _same_run(a, b):
    """Two runs with the same evaluation history (bit for bit), best/ and final model."""
    ha, hb = (json.loads((r / "eval" / "evaluations.json").read_text()) for r in (a, b))
    assert ha == hb
    for name in ("best/best_model.zip", "model.zip"):
        sa, sb = _state(a / name), _state(b / name)
        assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa), name
    na, nb = (load_run(r, "best")[0].normalizer for r in (a, b))
    assert np.array_equal(na.obs_rms.mean, nb.obs_rms.mean)
    assert np.array_equal(na.obs_rms.var, nb.obs_rms.var)
    return ha


@pytest.fixture(scope="module")
def in_process_run(tmp_path_factory):
    """Evaluations at 0, 256, 512 and 768 steps, all in the training process."""
    tmp = tmp_path_factory.mktemp("in_process")
    return train(tiny_config(tmp, 768, eval_freq=256), tmp / "run", progress=False,
                 eval_worker=False)


def test_evaluations_in_the_worker_are_those_of_the_training_process(in_process_run, tmp_path):
    """The worker evaluates a pickled copy of the policy and normaliser at the evaluation's
    step, and best/ gets the model saved at that step: the run is the in-process one."""
    run = train(tiny_config(tmp_path, 768, eval_freq=256), tmp_path / "run", progress=False,
                eval_worker=True)
    hist = _same_run(run, in_process_run)
    assert [h["timesteps"] for h in hist] == [0, 256, 512, 768]


def test_a_killed_worker_hands_its_evaluations_back(in_process_run, tmp_path, monkeypatch,
                                                    capsys):
    """SIGKILL of the evaluation worker while its first evaluation is under way: training says
    so and evaluates that one and the rest itself; nothing is lost or changed."""
    from mpa_gym.agents.training import callbacks as tr

    evaluate = tr.EvalWorker.evaluate

    def evaluate_and_kill(self, snap):
        future = evaluate(self, snap)
        for pid in self.pids():  # the worker, a real process
            os.kill(pid, signal.SIGKILL)
        return future

    monkeypatch.setattr(tr.EvalWorker, "evaluate", evaluate_and_kill)
    run = train(tiny_config(tmp_path, 768, eval_freq=256), tmp_path / "run", progress=False,
                eval_worker=True)
    err = capsys.readouterr().err
    assert "the evaluation worker stopped" in err and "from the evaluation at step 0 on" in err
    _same_run(run, in_process_run)


def test_a_killed_training_process_takes_its_worker_with_it(tmp_path):
    """SIGKILL of training (nothing of it runs to close the worker): the worker, left holding
    its own end of the task queue, exits by itself, as does multiprocessing's tracker."""
    run = tmp_path / "run"
    proc = start(["--config", str(tiny_config(tmp_path, 10**6, checkpoint_freq=128)),
                  "--run-dir", str(run), "--eval-worker"])
    deadline = time.monotonic() + 120
    while not (run / "eval" / "evaluations.json").is_file():  # the worker has answered once
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    kids = children(proc.pid)
    assert kids and all(alive(k) for k in kids)
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    left = wait_gone(kids)
    assert not left, [open(f"/proc/{k}/cmdline").read() for k in left]


def test_the_worker_is_the_default_only_where_it_pays():
    from mpa_gym.agents.evaluation.seeds import cores
    from mpa_gym.agents.learned.config import DEFAULT_CONFIG
    from mpa_gym.agents.training.callbacks import eval_worker_pays

    cfg = load_config(DEFAULT_CONFIG)
    assert eval_worker_pays(cfg, cfg.n_timesteps, None) == (cores() >= 2)
    assert not eval_worker_pays(cfg, cfg.eval_freq, None)  # one interval: nothing to overlap
    assert not eval_worker_pays(cfg, cfg.n_timesteps, lambda entry: True)  # a pruner's caller
    short = load_config(DEFAULT_CONFIG)
    short.eval_freq = 1024  # over before the worker has started
    assert not eval_worker_pays(short, 10**6, None)


def test_a_run_shorter_than_eval_freq_ends_with_a_held_out_evaluation(tmp_path, capsys):
    """n_timesteps below eval_freq: the evaluation at step 0 is followed by one at the last
    step, in the history files, in TensorBoard and in `train --json`'s last_evaluation; its
    figures are those of the saved model.zip evaluated afresh (the report's own episode runner
    on the same scenario and seed), so it records the model training left."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from mpa_gym.agents.evaluation.evaluate import evaluate

    run = tmp_path / "run"
    code = main(["train", "--config", str(tiny_config(tmp_path, 256, eval_freq=10_000)),
                 "--run-dir", str(run), "--no-progress", "--no-eval-worker", "--json"])
    assert code == 0
    last = json.loads(capsys.readouterr().out)["last_evaluation"]
    steps = zip_timesteps(run / "model.zip")
    assert steps >= 256 and last["timesteps"] == steps
    hist, ts, _, _ = read_eval_history(run / "eval")
    assert ts == [0, steps] and [h["timesteps"] for h in hist] == ts and hist[-1] == last
    events = EventAccumulator(str(next((run / "tb").glob("PPO_*")))).Reload()
    logged = events.Scalars("eval/ev/position_rmse_mm")
    assert [e.step for e in logged][-1] == steps
    cfg = load_config(run / "config.yaml")
    again = evaluate([f"{run}:alone"], [EV], cfg.eval_seed)["results"]["ev"]["run (alone)"]
    for key in ("position_rmse_mm", "stiffness_rmse_pct", "return"):
        # float32 tensorboard scalars aside, the same episode: equal to rounding
        np.testing.assert_allclose(last["scenarios"]["ev"][key], again[key], rtol=1e-9)
    np.testing.assert_allclose(logged[-1].value, again["position_rmse_mm"], rtol=1e-6)


def test_the_final_evaluation_in_the_worker_is_the_training_processes(tmp_path):
    """With the evaluation worker, the final evaluation (as the one at step 0) runs there on a
    snapshot of the model as training left it: the same figures as in the training process."""
    runs = []
    for where in ("worker", "process"):
        (tmp_path / where).mkdir()
        runs.append(train(tiny_config(tmp_path / where, 256, eval_freq=10_000),
                          tmp_path / where / "run", progress=False,
                          eval_worker=where == "worker"))
    hw, hp = (read_eval_history(r / "eval")[0] for r in runs)
    assert [h["timesteps"] for h in hw] == [0, zip_timesteps(runs[0] / "model.zip")]
    assert hw == hp
