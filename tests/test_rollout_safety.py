"""Rollouts that say why they stopped: safety stops, Ctrl-C and SIGTERM (real processes, real
signals, the emulator in its own process), each logged with its reason, the rig vented from the
PC side, a non-zero exit."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
import time

import pytest
from conftest import REALTIME, default_sigint, serving, tiny_config

from mpa_gym.agents.cli import main
from mpa_gym.agents.learned.policies import load_policy
from mpa_gym.agents.rig.rollout import read_log, rollout
from mpa_gym.agents.training.train import train
from mpa_gym.hardware.env import HardwareLegEnv

pytestmark = REALTIME  # a device loop in another process: conftest.REALTIME


def _wait_for_steps(log, n, timeout=60.0, proc=None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if log.exists() and sum("t_s" in r for r in read_log(log)) >= n:
            return
        if proc is not None:
            assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    raise AssertionError(f"fewer than {n} logged steps within {timeout} s")


# stale_s is relaxed to 0.2 s (as in test_hardware.py): these tests are about stops the test
# makes, and a scheduling hiccup of the shared 2-core test machine must not stop the episode first
RELAXED = ("import functools, sys, mpa_gym.agents.rig.rollout as r; "
           "r.HardwareLegEnv = functools.partial(r.HardwareLegEnv, stale_s=0.2); "
           "from mpa_gym.agents.cli import main; sys.exit(main(sys.argv[1:]))")


def test_a_safety_stop_is_logged_printed_and_exits_3(tmp_path, capsys, monkeypatch):
    """The leg is knocked below its position bound mid-episode: the episode ends, the rest of
    the session is not run, the log and stderr say why, the exit code is 3."""
    import functools

    import mpa_gym.agents.rig.rollout

    monkeypatch.setattr(mpa_gym.agents.rig.rollout, "HardwareLegEnv",
                        functools.partial(mpa_gym.agents.rig.rollout.HardwareLegEnv, stale_s=0.2))
    log = tmp_path / "r.jsonl"
    # the device's watchdog relaxed: the env stops, not the device
    with serving(watchdog_s=0.5) as (url, emu):
        def knock() -> None:  # a fall: the plant's hip drops to 0.65 m (x_min_m is 0.70 m)
            _wait_for_steps(log, 30)
            with emu.lock:
                emu.state[0], emu.state[1] = 0.65, 0.0

        threading.Thread(target=knock, daemon=True).start()
        code = main(["rollout", "--policy", "ff", "--device", url, "--episodes", "2",
                     "--episode-s", "3", "--log", str(log), "--json"])
    out, err = capsys.readouterr()
    assert code == 3
    assert re.search(r"STOPPED, rig vented: episode 0: position bound: X = 0\.6\d+ m", err), err
    report = json.loads(out)  # the metrics of what ran are still printed
    assert len(report["episodes"]) == 1 and "position bound" in report["stopped"]
    records = read_log(log)
    stop = [r for r in records if r.get("event") == "stopped"]
    assert len(stop) == 1 and "position bound" in stop[0]["fault"]
    assert "position bound" in [r for r in records if "t_s" in r][-1]["fault"]
    assert emu.vented


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_and_sigterm_print_one_line_vent_and_log_the_reason(tmp_path, sig):
    # the device's watchdog is relaxed to 1 s so that a scheduling hiccup of the shared test
    # machine does not fire it; after the signal it would fire within 1 s unless the PC vented
    emu = subprocess.Popen([sys.executable, "-m", "mpa_gym.agents.cli", "emulate", "--udp",
                            "--json", "--watchdog", "1.0"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           preexec_fn=default_sigint)
    url = re.search(r"udp://\S+", emu.stderr.readline()).group(0)
    log = tmp_path / "r.jsonl"
    proc = subprocess.Popen([sys.executable, "-c", RELAXED, "rollout", "--policy", "pid",
                             "--device", url, "--episode-s", "20", "--log", str(log)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=default_sigint)
    try:
        _wait_for_steps(log, 50, proc=proc)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=30)
        time.sleep(1.5)  # beyond the watchdog's 1 s
    finally:
        emu.send_signal(signal.SIGINT)
        emu_out, _ = emu.communicate(timeout=30)
        if proc.poll() is None:
            proc.kill()
    name = signal.Signals(sig).name
    assert proc.returncode == 128 + sig
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert f"interrupted by {name}; rig vented" in err
    stop = [r for r in read_log(log) if r.get("event") == "stopped"]
    assert len(stop) == 1 and name in stop[0]["fault"]
    # the PC vented the rig: the device's watchdog never had to
    assert json.loads(emu_out)["watchdog_vents"] == 0, emu_out


def test_episodes_0_is_refused_before_the_rig_is_pressurised(tmp_path, capsys):
    with serving() as (url, emu):
        code = main(["rollout", "--policy", "ff", "--device", url, "--episodes", "0",
                     "--log", str(tmp_path / "r.jsonl")])
    assert code == 2 and "--episodes=0" in capsys.readouterr().err
    assert emu.stats.commands == 0  # not even the pre-flight's low-pressure test
    assert not (tmp_path / "r.jsonl").exists()


def test_a_run_at_another_control_rate_is_refused_before_the_rig_is_touched(tmp_path, capsys):
    """A PPO run trained at dt_s = 0.01 s sums its tracking-error integrals per 10 ms period and
    learned its actions for it: rolled out at 500 Hz it would act silently wrong."""
    def at_100_hz(cfg):
        cfg["MPALegResidual-v0"]["env_kwargs"]["task"]["dt_s"] = 0.01

    path = tiny_config(tmp_path, at_100_hz, n_envs=2, n_timesteps=64, n_steps=32,
                       batch_size=64, n_epochs=1)
    run = train(path, tmp_path / "run", progress=False)
    with serving() as (url, emu):
        code = main(["rollout", "--policy", str(run), "--device", url, "--control-hz", "500",
                     "--log", str(tmp_path / "r.jsonl")])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    assert "--control-hz 500 (period 0.002 s) vs the run's dt_s 0.01 s = 100 Hz" in err, err
    assert emu.stats.commands == 0  # not even the pre-flight's low-pressure test
    assert not (tmp_path / "r.jsonl").exists()
    # at its own rate the run loads
    _, env_id, run_cfg = load_policy(str(run), {"task": {"dt_s": 0.01}})
    assert env_id == "MPALegResidual-v0" and run_cfg.n_timesteps == 64


def test_the_stop_reason_is_logged_when_venting_fails(tmp_path, monkeypatch):
    """Ctrl-C mid-episode, then the vent raises (the link died; not an OSError, which vent
    itself absorbs): the log still says what stopped the rollout, and that venting failed."""
    import mpa_gym.agents.rig.rollout

    class DyingLink(HardwareLegEnv):
        steps, dead = 0, False

        def __init__(self, *a, **kw):
            super().__init__(*a, **{**kw, "stale_s": 0.2})  # as RELAXED above

        def step(self, action):
            self.steps += 1
            if self.steps == 20:
                self.dead = True
                raise KeyboardInterrupt  # Ctrl-C between two steps
            return super().step(action)

        def vent(self):
            if self.dead:
                raise ValueError("link gone")
            super().vent()

    monkeypatch.setattr(mpa_gym.agents.rig.rollout, "HardwareLegEnv", DyingLink)
    log = tmp_path / "r.jsonl"
    # the device's watchdog relaxed: the env decides, not the device
    with serving(watchdog_s=0.5) as (url, _), pytest.raises(ValueError, match="link gone"):
        rollout("ff", url, log, episode_s=3.0)
    records = read_log(log)
    assert sum("t_s" in r for r in records) == 19
    stop = [r for r in records if r.get("event") == "stopped"]
    assert stop == [{"event": "stopped", "fault": "interrupted by SIGINT; venting FAILED",
                     "vent_fault": "ValueError: link gone"}], stop


def test_a_log_is_appended_to_only_if_it_is_one(tmp_path):
    """``open_log`` appends to a rollout log, also one whose first record a kill or a full disk
    tore (``read_log`` skips that line), and refuses any other file rather than corrupt it (a
    config given as --log by mistake)."""
    from mpa_gym.agents.rig.rollout import open_log

    torn = tmp_path / "torn.jsonl"
    torn.write_bytes(b'{"event": "sess')
    with open_log(torn) as f:
        f.write(json.dumps({"event": "session"}) + "\n")
    assert torn.read_text().splitlines()[1] == '{"event": "session"}'
    recs = read_log(torn)
    assert [r["event"] for r in recs] == ["session"] and recs.skipped == 1
    with open_log(torn) as f:  # torn first line, then a record: still a log
        pass
    for name, content in (("config.yaml", b"duration_s: 3\n"), ("b.bin", b"\x00\xff\x80"),
                          ("list.jsonl", b"[1, 2]\n")):
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=f"--log .*{re.escape(name)}.* not a rollout log"):
            open_log(tmp_path / name)
        assert (tmp_path / name).read_bytes() == content  # untouched
