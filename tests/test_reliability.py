"""Reliability suite: a table of bad inputs through the CLI and the env API.

Each case must give the documented exit code (2: bad input) or ``ValueError``, no traceback, and
a message that names the field and the value, before any work is done (no output files, no run
folder). Most CLI cases call ``mpa_gym.agents.cli.main`` in this process (an uncaught exception
fails the case, as a traceback would); a sample runs as real processes to check the exit code and
that stderr holds no traceback.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

import mpa_gym  # noqa: F401
from mpa_gym.agents.cli import main

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- fixtures
def _scenario(tmp: Path, name: str, body: object) -> str:
    path = tmp / f"{name}.yaml"
    path.write_text(body if isinstance(body, str) else yaml.safe_dump(body))
    return str(path)


def _config(tmp: Path, hp: dict | None = None, harness: dict | None = None) -> str:
    cfg = yaml.safe_load((ROOT / "configs" / "ppo_residual.yaml").read_text())
    cfg["MPALegResidual-v0"].update(n_envs=2, n_timesteps=64, n_steps=32, batch_size=32)
    cfg["MPALegResidual-v0"].update(hp or {})
    cfg["mpa_gym"].update(harness or {})
    path = tmp / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


@pytest.fixture
def files(tmp_path: Path) -> dict[str, str]:
    (tmp_path / "folder").mkdir()
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "binary.yaml").write_bytes(b"\x00\x01\xff\xfe\x80")
    (tmp_path / "broken.yaml").write_text("duration_s: [1, 2\n")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    (tmp_path / "run_no_config").mkdir()
    (tmp_path / "started").mkdir()
    (tmp_path / "started" / "config.yaml").write_text("{}")
    return {"tmp": str(tmp_path), "folder": str(tmp_path / "folder"),
            "file": str(tmp_path / "a_file"), "binary": str(tmp_path / "binary.yaml"),
            "broken": str(tmp_path / "broken.yaml"), "list": str(tmp_path / "list.yaml"),
            "run_no_config": str(tmp_path / "run_no_config"),
            "started": str(tmp_path / "started")}


# ----------------------------------------------------------------------------- CLI table
# (argv with {placeholders}, substrings the message must hold: the field and the value)
DESIGN = [
    (["design", "--x0", "-1"], ["--x0", "-1"]),
    (["design", "--x0", "nan"], ["--x0", "nan"]),
    (["design", "--x0", "5"], ["5"]),
    (["design", "--amp", "-0.01"], ["--amp", "-0.01"]),
    (["design", "--amp", "0.5"], ["x0_m + amp_m", "1.3"]),
    (["design", "--period", "0"], ["--period", "0"]),
    (["design", "--period", "inf"], ["--period", "inf"]),
    (["analyze", "--period", "1e6"], ["--period", "1e+06", "[0.1, 60]"]),
    (["analyze", "--period", "nan"], ["--period", "nan"]),
    (["analyze", "--period", "-3"], ["--period", "-3"]),
    (["design", "--pf-mean", "-1"], ["--pf-mean", "-1"]),
    (["design", "--pf-mean", "8"], ["--pf-mean", "8"]),
    (["design", "--pf-amp", "1"], ["--pf-amp", "1"]),
    (["design", "--p-max", "0"], ["--p-max", "0"]),
    (["design", "--p-max", "inf"], ["--p-max", "inf"]),
    (["design", "--samples", "1"], ["--samples", "1"]),
    (["design", "--samples", "1000000000"], ["--samples", "1000000000"]),
    (["analyze", "--pf-mean", "nan"], ["--pf-mean", "nan"]),
    # found by tools/probe.py: 1e308 bar overflowed to "p_max_bar=inf"
    (["design", "--p-max", "1e308"], ["--p-max", "1e+308", "(0, 100] bar"]),
]
SIMULATE = [
    (["simulate", "--scenario", "no_such_scenario"], ["no_such_scenario"]),
    (["simulate", "--scenario", "{folder}"], ["folder", "is a folder"]),
    (["simulate", "--scenario", "{binary}"], ["binary.yaml", "not UTF-8"]),
    (["simulate", "--scenario", "{broken}"], ["broken.yaml", "not valid YAML", "line 2"]),
    (["simulate", "--scenario", "{list}"], ["list.yaml", "mapping"]),
    (["simulate", "--scenario", "{tmp}/missing.yaml"], ["missing.yaml"]),
    (["simulate", "--scenario", "nominal", "--dt", "0"], ["dt", "0"]),
    (["simulate", "--scenario", "nominal", "--dt", "1"], ["dt", "1"]),
    (["simulate", "--scenario", "nominal", "--output-dt", "0"], ["--output-dt", "0"]),
    (["simulate", "--scenario", "nominal", "--dt", "nan"], ["dt", "nan"]),
]
# scenario bodies for `simulate --scenario FILE`
SCENARIOS = [
    ({"duration_s": "1e9"}, ["duration_s", "'1e9'", "as text"]),
    ({"duration_s": -1}, ["duration_s", "-1"]),
    ({"duration_s": float("nan")}, ["duration_s", "nan"]),
    ({"duration_s": 1e9}, ["duration_s", "1e+09"]),
    ({"durration_s": 3}, ["durration_s"]),
    ({"name": "x"}, ["duration_s", "missing"]),
    ({"duration_s": 3, "inputs": {"mode": [1]}}, ["inputs.mode", "[1]"]),
    ({"duration_s": 3, "inputs": {"mode": 7}}, ["inputs.mode", "7"]),
    ({"duration_s": 3, "inputs": {"mode": True}}, ["inputs.mode", "True"]),
    ({"duration_s": 3, "inputs": {"stiffness": "kmid"}}, ["inputs.stiffness", "kmid"]),
    ({"duration_s": 3, "inputs": {"stiffness": ["kmax"]}}, ["inputs.stiffness", "['kmax']"]),
    ({"duration_s": 3, "inputs": {"stiffness_const_N_per_m": -5}},
     ["infeasible", "P'_f", "k̂ = -5.0 N/m"]),
    ({"duration_s": 3, "inputs": {"p_max_bar": 0.1, "pf_mean_bar": 0.05}},
     ["infeasible", "P'_e", "[0, 0.1] bar"]),
    ({"duration_s": 3, "inputs": {"p_max_bar": 0.1}}, ["pf_mean_bar", "0.5", "[0, 0.1]"]),
    ({"duration_s": 3, "inputs": {"pf_amp_bar": 1}}, ["pf_amp_bar", "1"]),
    ({"duration_s": 3, "inputs": {"moed": 1}}, ["moed"]),
    ({"duration_s": 3, "inputs": {"mode": 1, "stiffness": "kmax"}}, ["mode", "stiffness"]),
    ({"duration_s": 3, "inputs": "fast"}, ["inputs", "fast"]),
    ({"duration_s": 3, "plant": {"mass_kg": -1}}, ["mass_kg", "-1"]),
    ({"duration_s": 3, "plant": {"mass_kg": "heavy"}}, ["mass_kg", "heavy"]),
    ({"duration_s": 3, "plant": {"gamma_Ns_per_m": float("nan")}}, ["gamma_Ns_per_m", "nan"]),
    ({"duration_s": 3, "plant": {"pressure_lag_s": 5}}, ["pressure_lag_s", "5"]),
    ({"duration_s": 3, "plant": {"masss": 1}}, ["masss"]),
    ({"duration_s": 3, "plant": {"extra_mass_kg": True}}, ["extra_mass_kg", "True"]),
    ({"duration_s": 3, "reference": {"period_s": 0}}, ["period_s", "0"]),
    ({"duration_s": 3, "reference": {"amp_m": 0.5}}, ["x0_m + amp_m", "1.3"]),
    ({"duration_s": 3, "reference": {"x0_m": -1}}, ["x0_m", "-1"]),
    ({"duration_s": 3, "initial_state": {"x_m": 0.8}}, ["initial_state", "v_mps"]),
    ({"duration_s": 3, "initial_state": {"x_m": 2, "v_mps": 0}}, ["x_m", "2"]),
    ({"duration_s": 3, "disturbances": {"type": "impulse"}}, ["disturbances"]),
    ({"duration_s": 3, "disturbances": [{"type": "kick", "t_s": 1, "force_N": 1}]},
     ["type", "kick"]),
    ({"duration_s": 3, "disturbances": [{"type": "impulse", "t_s": 99, "force_N": 1,
                                         "duration_s": 0.1}]}, ["t_s", "99"]),
    ({"duration_s": 3, "disturbances": [{"type": "impulse", "t_s": 1, "force_N": "big",
                                         "duration_s": 0.1}]}, ["force_N", "big"]),
    ({"duration_s": 3, "randomize": {"mass_kg": [4, 3]}}, ["mass_kg", "4", "3"]),
    ({"duration_s": 3, "randomize": {"mass_kg": 3}}, ["mass_kg", "3"]),
    ({"duration_s": 3, "randomize": {"C1_Pa": [1, "x"]}}, ["C1_Pa", "'x'"]),
    ({"duration_s": 3, "randomize": {"pressure_noise_bar": [0, 0.1]}}, ["pressure_noise_bar"]),
    # in range, but it throws the leg out of the model's domain (was a SimulationError traceback)
    ({"duration_s": 3, "disturbances": [{"type": "impulse", "t_s": 1, "force_N": -3000,
                                         "duration_s": 0.05}]},
     ["disturbances[0]", "force_N=-3000", "left the model's domain"]),
    ({"duration_s": 3, "plant": {"mass_kg": 50}}, ["plant.mass_kg=50", "left the model's domain"]),
]
# PPO / harness keys for `train --config FILE`: each refused before a run folder exists
CONFIGS = [
    ({"ent_coef": float("nan")}, ["ent_coef", "nan"]),
    ({"gae_lambda": 5.0}, ["gae_lambda", "5.0", "[0, 1]"]),
    ({"gamma": -1}, ["gamma", "-1", "[0, 1]"]),
    ({"max_grad_norm": -1}, ["max_grad_norm", "-1"]),
    ({"n_steps": "256"}, ["n_steps", "'256'"]),
    ({"batch_size": 0}, ["batch_size", "0"]),
    ({"policy_kwargs": "dict(net_arch=[-64, 64])"}, ["net_arch[0]", "-64"]),
    ({"n_epochs": -5}, ["n_epochs", "-5"]),
    ({"learning_rate": -1e-3}, ["learning_rate", "-0.001"]),
    ({"learning_rate": "lin_-1"}, ["learning_rate", "lin_-1"]),
    ({"learning_rate": "lin_abc"}, ["learning_rate", "lin_abc"]),
    ({"learning_rate": float("inf")}, ["learning_rate", "inf"]),
    ({"clip_range": 0}, ["clip_range", "0"]),
    ({"clip_range": -0.2}, ["clip_range", "-0.2"]),
    ({"vf_coef": -1}, ["vf_coef", "-1"]),
    ({"target_kl": 0}, ["target_kl", "0"]),
    ({"policy_kwargs": "dict(log_std_init=float('nan'))"}, ["policy_kwargs"]),
    ({"policy_kwargs": {"log_std_init": float("nan")}}, ["log_std_init", "nan"]),
    ({"policy_kwargs": {"log_std_init": 100}}, ["log_std_init", "100"]),
    ({"policy_kwargs": {"net_arch": "big"}}, ["net_arch", "big"]),
    ({"policy_kwargs": {"net_arch": {"pi": [64], "q": [64]}}}, ["net_arch", "'q'"]),
    ({"policy_kwargs": {"net_arch": [64, 1.5]}}, ["net_arch[1]", "1.5"]),
    ({"policy_kwargs": "dict(activation_fn=nn.Foo)"}, ["nn.Foo"]),
    ({"policy_kwargs": "dict(foo=1)"}, ["foo"]),
    ({"policy_kwargs": "dict(net_arch=[64, 64]"}, ["policy_kwargs", "not a valid expression"]),
    ({"n_envs": 0}, ["n_envs", "0"]),
    ({"n_envs": 1.5}, ["n_envs", "1.5"]),
    ({"n_timesteps": -1}, ["n_timesteps", "-1"]),
    ({"n_timesteps": float("nan")}, ["n_timesteps", "nan"]),
    ({"normalize": "{'norm_obs': 1}"}, ["norm_obs", "1"]),
    ({"normalize": "{'gamma': 2}"}, ["gamma", "2"]),
    ({"normalize": 3}, ["normalize", "3"]),
    ({"use_sde": "yes"}, ["use_sde", "yes"]),
    ({"normalize_advantage": 1}, ["normalize_advantage", "1"]),
    ({"sde_sample_freq": -2}, ["sde_sample_freq", "-2"]),
    ({"n_steps": 1, "n_envs": 1, "batch_size": 2}, ["n_steps * n_envs", "1"]),
    ({"batch_size": 10_000}, ["batch_size", "10000"]),
    ({"policy": "CnnPolicy"}, ["policy", "CnnPolicy"]),
    ({"env_kwargs": {"task": {"dt_s": "0.01"}}}, ["dt_s", "'0.01'"]),
    ({"env_kwargs": {"scenario": 5}}, ["scenario", "5"]),
    ({"env_kwargs": {"task": "fast"}}, ["task", "fast"]),
    ({"env_wrapper": [{"mpa_gym.agents.learned.wrappers.TrackingErrorObservation":
                       {"harmonics": -1}}]},
     ["harmonics", "-1"]),
]
HARNESS = [
    ({"seed": -1}, ["seed", "-1"]),
    ({"eval_freq": 0}, ["eval_freq", "0"]),
    ({"checkpoint_freq": "often"}, ["checkpoint_freq", "often"]),
    ({"eval_scenarios": ["no_such_scenario"]}, ["eval_scenarios[0]", "no_such_scenario"]),
    ({"eval_scenarios": "heldout_a"}, ["eval_scenarios", "heldout_a"]),
    ({"sed": 1}, ["sed"]),
]
OTHER = [
    (["train", "--config", "{tmp}/missing.yaml"], ["missing.yaml", "does not exist"]),
    (["train", "--config", "{folder}"], ["folder", "is a folder"]),
    (["train", "--config", "{binary}"], ["binary.yaml", "not UTF-8"]),
    (["train", "--config", "{list}"], ["list.yaml", "[1, 2]"]),
    (["train", "--n-timesteps", "0"], ["--n-timesteps", "0"]),
    (["train", "--seed", "-1"], ["--seed", "-1"]),
    (["train", "--resume", "{tmp}/nowhere"], ["nowhere", "config.yaml"]),
    (["train", "--resume", "{run_no_config}"], ["run_no_config", "config.yaml"]),
    (["train", "--config", "x.yaml", "--resume", "{folder}"], ["--config", "--resume"]),
    (["train", "--seed", "3", "--resume", "{folder}"], ["--seed", "--resume"]),
    (["train", "--config", "{good_config}", "--run-dir", "{file}"], ["--run-dir", "a_file"]),
    (["train", "--config", "{good_config}", "--run-dir", "{started}"], ["started", "--resume"]),
    (["evaluate", "--out", "{file}"], ["--out", "a_file", "is a file"]),
    (["evaluate", "--policy", "nonsense", "--out", "{tmp}/ev"], ["policy", "nonsense"]),
    (["evaluate", "--scenarios", "no_such", "--out", "{tmp}/ev"], ["no_such"]),
    (["evaluate", "--seed", "-1", "--out", "{tmp}/ev"], ["--seed", "-1"]),
    (["evaluate", "--random-rigs", "-1", "--out", "{tmp}/ev"], ["--random-rigs", "-1"]),
    (["evaluate", "--rigs-seed", "-5", "--out", "{tmp}/ev"], ["--rigs-seed", "-5"]),
    (["evaluate", "--policy", "{folder}", "--out", "{tmp}/ev"], ["folder", "config.yaml"]),
    (["evaluate", "--policy", "no_such_mod:Ctrl", "--out", "{tmp}/ev"],
     ["--policy", "no_such_mod:Ctrl", "no module named"]),
    (["evaluate", "--policy", "json:Nope", "--out", "{tmp}/ev"], ["--policy", "json:Nope"]),
    (["evaluate", "--policy", "json:JSONDecodeError", "--out", "{tmp}/ev"],
     ["json:JSONDecodeError", "not a controller class"]),
    (["evaluate", "--gains", "{tmp}/missing.yaml", "--out", "{tmp}/ev"],
     ["--gains", "missing.yaml", "does not exist"]),
    (["evaluate", "--gains", "{list}", "--out", "{tmp}/ev"], ["--gains", "list.yaml"]),
    # found by tools/probe.py: a binary gains file gave the raw "'utf-8' codec can't decode",
    # 1e20 random rigs ran until killed, and an empty path was read as "not given"
    (["evaluate", "--gains", "{binary}", "--out", "{tmp}/ev"],
     ["--gains", "binary.yaml", "not UTF-8"]),
    (["evaluate", "--random-rigs", "99999999999999999999", "--out", "{tmp}/ev"],
     ["--random-rigs", "99999999999999999999", "[0, 10000]"]),
    (["train", "--config", ""], ["--config", "empty"]),
    (["train", "--run-dir", ""], ["--run-dir", "empty"]),
    (["evaluate", "--policy", "ff", "", "--out", "{tmp}/ev"], ["--policy", "empty"]),
    (["tune-baselines", "--config", ""], ["--config", "empty"]),
    (["calibrate", ""], ["RUN_DIR", "empty"]),
    (["bench", "--loop", "no_such_mod:Ctrl", "--repeats", "1"], ["--loop", "no_such_mod:Ctrl"]),
    (["bench", "--gains", "{tmp}/g.yaml"], ["--gains", "--loop"]),
    (["tune-baselines", "--out", "{folder}"], ["--out", "folder", "is a folder"]),
    (["figures", "--out", "{file}"], ["--out", "a_file", "is a file"]),
    (["emulate", "--udp", "--host", "999.1.1.1"], ["--host", "999.1.1.1"]),
    (["emulate", "--udp", "--duration", "nan"], ["--duration", "nan"]),
    (["emulate", "--udp", "--duration", "-1"], ["--duration", "-1"]),
    (["emulate", "--udp", "--watchdog", "0"], ["--watchdog", "0"]),
    (["emulate", "--udp", "--port", "70000"], ["--port", "70000"]),
    (["emulate", "--udp", "--drop", "2"], ["--drop=2", "[0, 1]"]),
    (["emulate", "--udp", "--latency", "-1"], ["--latency=-1", "[0, 1] s"]),
    (["emulate", "--udp", "--scenario", "no_such"], ["no_such"]),
    (["rollout", "--policy", "ff", "--dry-run", "--episodes", "0"], ["--episodes", "0"]),
    (["rollout", "--policy", "ff", "--dry-run", "--episodes", "-3"], ["--episodes", "-3"]),
    (["rollout", "--policy", "ff", "--dry-run", "--control-hz", "0"], ["--control-hz", "0"]),
    (["rollout", "--policy", "ff", "--dry-run", "--control-hz", "nan"], ["--control-hz", "nan"]),
    (["rollout", "--policy", "ff", "--dry-run", "--control-hz", "1000"],
     ["--control-hz", "1000"]),
    (["rollout", "--policy", "ff", "--dry-run", "--episode-s", "-1"], ["--episode-s", "-1"]),
    (["rollout", "--policy", "ff", "--dry-run", "--log", "{folder}"], ["--log", "folder"]),
    (["rollout", "--policy", "ff", "--dry-run", "--log", "{file}/x.jsonl"], ["--log", "a_file"]),
    (["rollout", "--policy", "nonsense", "--dry-run", "--log", "{tmp}/r.jsonl"],
     ["policy", "nonsense"]),
    (["rollout", "--policy", "ff", "--dry-run", "--scenario", "no_such", "--log",
      "{tmp}/r.jsonl"], ["no_such"]),
    (["rollout", "--policy", "ff", "--log", "{tmp}/r.jsonl"], ["--device"]),
    (["rollout", "--policy", "ff", "--device", "ftp://x", "--log", "{tmp}/r.jsonl"],
     ["ftp://x"]),
    (["rollout", "--policy", "ff", "--device", "", "--log", "{tmp}/r.jsonl"],
     ["--device", "empty"]),
    (["rollout", "--policy", "ff", "--device", "serial:///nonexistent", "--log",
      "{tmp}/r.jsonl"], ["--device", "/nonexistent", "no serial device"]),
    (["bench", "--seconds", "0"], ["--seconds", "0"]),
    (["bench", "--sizes", "0"], ["--sizes", "0"]),
    # issue 34: refused before work, naming the flag (were tracebacks, silent or unclear)
    (["simulate", "--scenario", "nominal", "--dt", "100"], ["--dt=100", "[0.0001, 0.1]"]),
    (["simulate", "--scenario", "nominal", "--dt", "1e-9"], ["--dt=1e-09"]),
    (["analyze", "--stiffness-const", "1e12"], ["--stiffness-const", "1e+12"]),
    (["figures", "--out", ""], ["--out", "empty"]),
    (["bench", "--loop", "ff", "--rig", "no_such"], ["--rig", "no_such"]),
    (["bench", "--loop", "ff", "--rig", "{broken}"], ["--rig", "broken.yaml"]),
    (["bench", "--loop", "nonsense"], ["nonsense"]),
    (["bench", "--inference", "{folder}", "--loop", "ff"], ["--loop", "--inference"]),
    (["bench", "--inference", "{folder}", "--seconds", "0.1"], ["--seconds=0.1", "--inference"]),
    (["bench", "--seconds", "0.05", "--rig", "heldout_a"], ["--rig='heldout_a'"]),
    (["bench", "--loop", "ff", "--sizes", "4"], ["--sizes=[4]", "--loop"]),
    (["emulate", "--serial", "--port", "5000"], ["--port=5000", "--serial"]),
    (["emulate", "--serial", "--host", "10.0.0.1"], ["--host='10.0.0.1'", "--serial"]),
    (["rollout", "--policy", "ff", "--dry-run", "--device", "udp://127.0.0.1:9"],
     ["--device", "--dry-run"]),
    (["train", "--config", "{good_config}", "--jobs", "2"], ["--jobs=2", "--seeds"]),
    (["train", "--config", "{good_config}", "--run-dir", "{file}/run"], ["--run-dir", "a_file"]),
    (["train", "--config", "{good_config}", "--seeds", "0", "4294967296", "--run-dir",
      "{tmp}/run"], ["--seeds", "4294967296", "[0, 2147483647]"], "run-s0"),
    (["train", "--config", "{good_config}", "--seeds", "0", "1", "--jobs", "0", "--run-dir",
      "{tmp}/run"], ["--jobs=0", "[1, 256]"]),
    (["train", "--config", "{good_config}", "--seeds", "0", "1", "--jobs", "-1", "--run-dir",
      "{tmp}/run"], ["--jobs=-1"]),
    (["train", "--config", "{broken}", "--seeds", "0", "1", "--run-dir", "{tmp}/run"],
     ["broken.yaml", "not valid YAML"], "run-s0"),
    (["train", "--config", "{good_config}", "--seeds", "0", "1", "--run-dir", "{file}/run"],
     ["--run-dir", "a_file"]),
    (["evaluate", "--policy", "ff", "ff", "--out", "{tmp}/ev"], ["--policy", "'ff'", "once"]),
    (["evaluate", "--scenarios", "nominal", "nominal", "--out", "{tmp}/ev"],
     ["--scenarios", "'nominal'"]),
    (["tune", "--config", "{good_config}", "--heldout", "no_such", "--storage",
      "sqlite:///{tmp}/t.db", "--out-dir", "{tmp}/tune"], ["--heldout[0]", "no_such"], "tune"),
    (["tune", "--config", "{unsatisfiable}", "--storage", "sqlite:///{tmp}/t.db", "--out-dir",
      "{tmp}/tune"], ["mpa_gym.tune", "no point", "batch_size"], "tune"),
    (["tune", "--config", "{good_config}", "--storage", "sqlite:///{file}/t.db", "--out-dir",
      "{tmp}/tune"], ["--storage", "a_file"]),
    (["tune", "--config", "{good_config}", "--storage", "sqlite:///{tmp}/t.db", "--out-dir",
      "{file}"], ["--out-dir", "a_file"]),
    (["tune", "--config", "{broken}", "--storage", "sqlite:///{tmp}/t.db"],
     ["broken.yaml", "not valid YAML"]),
    # found by tools/probe.py: a coverage flag beside --log was ignored, the fault flags were
    # named by LinkFaults' fields, a binary --log raised the codec's error (and any file was
    # appended to), --inference named config.yaml rather than itself
    (["identify", "--log", "{tmp}/x.jsonl", "--episode-s", "nan"],
     ["--episode-s=nan", "--log", "ignore"]),
    (["identify", "--coverage", "2", "--out", "{tmp}/id.yaml"], ["--out=", "--coverage"]),
    (["emulate", "--udp", "--position-noise", "-1"], ["--position-noise=-1", "[0, 0.01]"]),
    (["rollout", "--policy", "ff", "--dry-run", "--log", "{binary}"],
     ["--log", "binary.yaml", "not a rollout log"]),
    (["rollout", "--policy", "ff", "--dry-run", "--log", "{file}"],
     ["--log", "a_file", "not a rollout log"]),
    (["bench", "--inference", "nonsense"], ["--inference", "'nonsense'", "run folder"]),
    # found by tools/probe.py: 1e20 trials or steps ran until killed
    (["tune", "--config", "{good_config}", "--storage", "sqlite:///{tmp}/t.db", "--out-dir",
      "{tmp}/tune", "--n-trials", "99999999999999999999"],
     ["--n-trials=99999999999999999999", "[1, 1000000]"], "tune"),
    (["tune", "--config", "{good_config}", "--storage", "sqlite:///{tmp}/t.db", "--out-dir",
      "{tmp}/tune", "--n-timesteps", "99999999999999999999"],
     ["--n-timesteps=99999999999999999999", "[1, 10000000000]"], "tune"),
    (["train", "--n-timesteps", "99999999999999999999"],
     ["--n-timesteps=99999999999999999999", "1e+10"]),
    (["tune", "--best", "s", "--storage", "sqlite:///{tmp}/t.db", "--out", "{folder}"],
     ["--out", "folder"]),
    (["tune-baselines", "--seed", "-1"], ["--seed=-1", "[0, 4294967295]"]),
    (["tune-baselines", "--n-trials", "0"], ["--n-trials=0"]),
    (["tune-baselines", "--n-plants", "-1"], ["--n-plants=-1"]),
    # found by tools/probe.py: an infinite episode overflowed (traceback), calibrate named its
    # Python arguments (n_plants=0) rather than its flags
    (["tune-baselines", "--episode-s", "inf"], ["--episode-s=inf", "[3, 600]"]),
    (["tune-baselines", "--episode-s", "nan"], ["--episode-s=nan", "[3, 600]"]),
    (["calibrate", "{started}", "--n-plants", "0"], ["--n-plants=0", "[1, 4096]"]),
    (["calibrate", "{started}", "--episode-s", "1e308"], ["--episode-s=1e+308", "[3, 600]"]),
]


def _cases() -> list[tuple[list[str], list[str], str]]:
    # a third element: a path under tmp that must not exist afterwards (nothing started)
    out = [(c[0], c[1], c[2] if len(c) > 2 else "") for c in DESIGN + SIMULATE + OTHER]
    out += [(["simulate", "--scenario", f"{{scenario:{i}}}"], want, "")
            for i, (_, want) in enumerate(SCENARIOS)]
    out += [(["train", "--config", f"{{config:{i}}}", "--run-dir", "{tmp}/run"], want, "run")
            for i, (_, want) in enumerate(CONFIGS)]
    out += [(["train", "--config", f"{{harness:{i}}}", "--run-dir", "{tmp}/run"], want, "run")
            for i, (_, want) in enumerate(HARNESS)]
    return out


CASES = _cases()


def _argv(argv: list[str], files: dict[str, str]) -> list[str]:
    tmp = Path(files["tmp"])
    out = []
    for a in argv:
        if a.startswith("{scenario:"):
            a = _scenario(tmp, "bad", SCENARIOS[int(a[10:-1])][0])
        elif a.startswith("{config:"):
            a = _config(tmp, hp=CONFIGS[int(a[8:-1])][0])
        elif a.startswith("{harness:"):
            a = _config(tmp, harness=HARNESS[int(a[9:-1])][0])
        elif a == "{good_config}":
            a = _config(tmp)
        elif a == "{unsatisfiable}":  # a search space whose every point PPO refuses
            a = _config(tmp, harness={"tune": {"batch_size": {"categorical": [100_000]}}})
        else:
            a = a.format(**files)
        out.append(a)
    return out


def test_the_table_has_at_least_100_cases():
    assert len(CASES) + len(ENV_CASES) >= 100
    assert len(PROCESS_SAMPLE) == 8


@pytest.mark.parametrize(("argv", "want", "absent"), CASES,
                         ids=[" ".join(c[0])[:60] for c in CASES])
def test_bad_cli_input_exits_2_naming_field_and_value(argv, want, absent, files, capsys):
    code = main(_argv(argv, files))
    out, err = capsys.readouterr()
    assert code == 2, (code, err)
    assert err.count("\n") == 1 and err.startswith(f"mpa-gym {argv[0]}: error: "), err
    assert out == ""
    for w in want:
        assert w in err, (w, err)
    if absent:  # refused before anything ran: no run folder made
        assert not (Path(files["tmp"]) / absent).exists()


def test_analyze_refuses_the_samples_it_would_ignore(capsys):
    """analyze integrates one period: it took --samples (any value, even 1e20) and ignored it."""
    with pytest.raises(SystemExit) as e:
        main(["analyze", "--samples", "99999999999999999999"])
    assert e.value.code == 2
    assert "unrecognized arguments: --samples" in capsys.readouterr().err


# a sample, run as real processes: the exit code and a stderr with one line and no traceback
PROCESS_SAMPLE = [i for i, (argv, _, _) in enumerate(CASES) if " ".join(argv) in {
    "design --x0 -1", "analyze --period 1e6", "simulate --scenario {binary}",
    "evaluate --out {file}", "emulate --udp --duration nan", "train --config {config:0} "
    "--run-dir {tmp}/run", "rollout --policy ff --dry-run --episodes 0",
    "rollout --policy ff --dry-run --log {folder}"}]


def test_bad_input_as_a_process_exits_2_without_traceback(files):
    """The sample's processes run side by side (each mostly waits on its imports)."""
    procs = []
    for i in PROCESS_SAMPLE:
        argv, want, _ = CASES[i]
        procs.append((argv, want, subprocess.Popen(
            [sys.executable, "-m", "mpa_gym.agents.cli", *_argv(argv, files)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)))
    for argv, want, proc in procs:
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 2, (argv, err)
        assert "Traceback" not in err and err.count("\n") == 1, (argv, err)
        assert all(w in err for w in want), (argv, err)


# ----------------------------------------------------------------------------- env API table
def _make(**kw):
    return gym.make("MPALegResidual-v0", **kw)


def _reset(options):
    env = _make()
    env.reset(seed=0, options=options)


def _step(action, env_id="MPALegResidual-v0"):
    env = gym.make(env_id)
    env.reset(seed=0)
    env.step(action)


def _vstep(actions):
    env = gym.make_vec("MPALegResidual-v0", num_envs=2, vectorization_mode="vector_entry_point")
    env.reset(seed=0)
    env.step(actions)


def _hardware(**kw):
    from mpa_gym.hardware.env import HardwareLegEnv

    HardwareLegEnv("udp://127.0.0.1:9", **kw)


def _hardware_device(device):
    from mpa_gym.hardware.env import HardwareLegEnv

    HardwareLegEnv(device)


ENV_CASES = [
    (lambda: _make(scenario=5), ["scenario", "5"]),
    (lambda: _make(scenario="no_such"), ["no_such"]),
    (lambda: _make(scenario=ROOT / "configs"), ["configs", "folder"]),
    (lambda: _make(scenario={"duration_s": "x"}), ["duration_s", "'x'"]),
    (lambda: _make(scenario={"duration_s": 3, "plant": {"mass_kg": 0}}), ["mass_kg", "0"]),
    (lambda: _make(task="fast"), ["task", "fast"]),
    (lambda: _make(task={"dt_s": "0.01"}), ["dt_s", "'0.01'"]),
    (lambda: _make(task={"dt_s": 0}), ["dt_s", "0"]),
    (lambda: _make(task={"dtt": 1}), ["dtt"]),
    (lambda: _make(task={"p_max_bar": float("nan")}), ["p_max_bar", "nan"]),
    (lambda: _make(task={"substeps": 1.5}), ["substeps", "1.5"]),
    (lambda: _make(task={"episode_s": -1}), ["episode_s", "-1"]),
    (lambda: _make(task={"x_min_m": True}), ["x_min_m", "True"]),
    (lambda: _reset("plant"), ["options", "plant"]),
    (lambda: _reset({"plant": "heavy"}), ["plant", "heavy"]),
    (lambda: _reset({"plant": {"mass_kg": -1}}), ["mass_kg", "-1"]),
    (lambda: _reset({"plant": {"mass": 1}}), ["mass"]),
    (lambda: _reset({"initial_state": {"x_m": 5, "v_mps": 0}}), ["x_m", "5"]),
    (lambda: _reset({"initial_state": "up"}), ["initial_state", "up"]),
    (lambda: _reset({"mass": 1}), ["mass"]),
    (lambda: _step("ab"), ["action", "'ab'"]),
    (lambda: _step(["a", "b"]), ["action", "'a'"]),
    (lambda: _step([1 + 1j, 0]), ["action", "1j"]),
    (lambda: _step([True, False]), ["action", "True"]),
    (lambda: _step(np.array([np.nan, 0.0])), ["action", "nan"]),
    (lambda: _step(np.zeros(3)), ["action", "(3,)"]),
    (lambda: _step(None), ["action", "None"]),
    (lambda: _step([1 + 1j, 0], "MPALeg-v0"), ["action", "1j"]),
    (lambda: _vstep(np.array([["a", "b"], ["c", "d"]])), ["action", "'a'"]),
    (lambda: _vstep(np.zeros((3, 2))), ["actions", "(3, 2)"]),
    (lambda: _vstep(np.ones((2, 2), dtype=bool)), ["action", "True"]),
    (lambda: _make(stiffness="bogus"), ["stiffness", "bogus"]),
    (lambda: _make(stiffness=[]), ["stiffness", "[]"]),
    (lambda: _make(render_mode="x"), ["render_mode", "'x'"]),
    (lambda: _make(scenario=None), ["scenario", "None"]),
    (lambda: _make(scenario=[1]), ["scenario", "[1]"]),
    (lambda: _make(scenario={"duration_s": 3, "plant": []}), ["plant", "[]"]),
    (lambda: _make(task={"w_stiffness": "x"}), ["w_stiffness", "'x'"]),
    (lambda: gym.make_vec("MPALegResidual-v0", num_envs=0,
                          vectorization_mode="vector_entry_point"), ["num_envs", "0"]),
    (lambda: gym.make_vec("MPALegResidual-v0", num_envs=2, vectorization_mode="vector_entry_point"
                          ).reset(options="plant"), ["options", "plant"]),
    (lambda: gym.make_vec("MPALegResidual-v0", num_envs=2, vectorization_mode="vector_entry_point"
                          ).reset(seed=[1, 2, 3]), ["seed", "3"]),
    (lambda: _hardware_device(5), ["URL", "5"]),
    (lambda: _hardware_device("udp://host"), ["URL", "udp://host", "port"]),
    (lambda: _hardware(control_hz=0), ["control_hz", "0"]),
    (lambda: _hardware(task={"dt_s": 0.01}), ["task.dt_s"]),
    (lambda: _hardware(stale_s="x"), ["stale_s", "'x'"]),
]


@pytest.mark.filterwarnings("ignore:.*render_mode='x'")  # gymnasium's own warning, then ours
@pytest.mark.parametrize(("call", "want"), ENV_CASES, ids=[str(i) for i in range(len(ENV_CASES))])
def test_bad_env_input_raises_value_error_naming_field_and_value(call, want):
    with pytest.raises(ValueError) as e:
        call()
    for w in want:
        assert w in str(e.value), (w, str(e.value))


@pytest.mark.parametrize(("flags", "inputs"), [
    (["--stiffness-const", "-5"], {"stiffness_const_N_per_m": -5}),
    (["--p-max", "0.1", "--pf-mean", "0.05"], {"p_max_bar": 0.1, "pf_mean_bar": 0.05}),
])
def test_simulate_refuses_what_design_marks_infeasible_with_the_same_report(flags, inputs,
                                                                            tmp_path, capsys):
    assert main(["design", "--json", *flags]) == 0
    design = json.loads(capsys.readouterr().out)
    assert not design["feasible"] and design["violations"]
    path = _scenario(tmp_path, "infeasible", {"duration_s": 6.0, "inputs": inputs})
    assert main(["simulate", "--scenario", path]) == 2
    err = capsys.readouterr().err
    for violation in design["violations"]:  # every violation design lists, word for word
        assert violation in err, (violation, err)


@pytest.mark.parametrize(("kwargs", "want"), [
    ({"n_timesteps": -1}, ["n_timesteps", "-1"]),
    ({"n_timesteps": 64, "ppo_kwargs": {"gamma": 2.0}}, ["gamma", "2.0"]),
    ({"n_timesteps": 64, "ppo_kwargs": {"n_stepz": 8}}, ["n_stepz"]),
    ({"n_timesteps": 64, "policy_kwargs": {"net_arch": [0]}}, ["net_arch[0]", "0"]),
    ({"n_timesteps": 64, "eval_freq": 0}, ["eval_freq", "0"]),
    ({"n_timesteps": 64, "env_kwargs": {"task": {"dt_s": -1}}}, ["dt_s", "-1"]),
])
def test_train_config_validates_itself(kwargs, want):
    """The dataclass checks itself: built in Python, without the YAML loader."""
    from mpa_gym.agents.learned.config import ConfigError, TrainConfig

    with pytest.raises(ConfigError) as e:
        TrainConfig(env_id="MPALegResidual-v0", **kwargs)
    for w in want:
        assert w in str(e.value), (w, str(e.value))
    assert TrainConfig(env_id="MPALegResidual-v0", n_timesteps=64).n_envs == 1


# ----------------------------------------------------------------------------- run folders
@pytest.fixture(scope="module")
def run_folders(tmp_path_factory) -> dict[str, str]:
    """A tiny trained run and copies of it whose config.yaml is broken YAML or names another
    observation wrapper than the model was trained with (harmonics 3: two more integral pairs
    and two more remodulated pairs, 39-wide observations against the model's 31)."""
    import shutil

    from conftest import tiny_config

    from mpa_gym.agents.training.train import train

    tmp = tmp_path_factory.mktemp("runs")
    run = train(tiny_config(tmp, n_envs=2, n_timesteps=64, n_steps=32, batch_size=64,
                            n_epochs=1), tmp / "r-s0", 0, progress=False)
    text = (run / "config.yaml").read_text()
    assert "harmonics: 1" in text
    out = {"run": str(run)}
    for name, body in (("broken-s0", text + "  oops: [\n"), ("broken-s1", text + "  oops: [\n"),
                       ("mismatch", text.replace("harmonics: 1", "harmonics: 3"))):
        shutil.copytree(run, tmp / name)
        (tmp / name / "config.yaml").write_text(body)
        out[name] = str(tmp / name)
    return out


@pytest.mark.parametrize(("policies", "want"), [
    (["{run}", "{run}"], ["--policy", "r-s0", "once"]),
    # the policies alone of two runs: grouped by their configs before anything read them
    (["{broken-s0}:alone", "{broken-s1}:alone"], ["broken-s0", "config.yaml", "not valid YAML"]),
    (["{mismatch}"], ["mismatch", "41-wide", "(33,)", "does not match its model"]),
])
def test_evaluate_refuses_a_run_it_cannot_report_naming_it(policies, want, run_folders,
                                                            tmp_path, capsys):
    argv = ["evaluate", "--policy", *(p.format(**run_folders) for p in policies),
            "--scenarios", "nominal", "--no-robustness", "--out", str(tmp_path / "ev")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("mpa-gym evaluate: error: "), err
    for w in want:
        assert w in err, (w, err)
    assert not (tmp_path / "ev" / "report.json").exists()


def test_bench_loop_on_a_rig_that_fails_its_pre_flight_stops_with_code_3(tmp_path):
    # a 1 s regulator dead time: the pre-flight's low-pressure test sees no pressure and the
    # loop stops as a rollout does (rig vented, code 3), naming --rig; was a HardwareFault
    # traceback. A real process and a real emulator process.
    rig = _scenario(tmp_path, "dead", {"duration_s": 3,
                                       "plant": {"pressure_dead_time_s": 1.0}})
    r = subprocess.run([sys.executable, "-m", "mpa_gym.agents.cli", "bench", "--loop", "ff",
                        "--rig", rig, "--loop-s", "1", "--repeats", "1"],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert "--rig" in r.stderr and "dead.yaml" in r.stderr and "pre-flight" in r.stderr


@pytest.mark.parametrize("argv", [["simulate", "--scenaro", "nominal"],
                                  ["rollout", "--no-such-flag"],
                                  ["emulate", "--udp", "--duraton", "1"]])
def test_an_unknown_flag_is_named_before_the_missing_required_ones(argv, capsys):
    # argparse checks the required flags first: 'the following arguments are required:
    # --scenario' was all that a typo of --scenario got
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert f"unrecognized arguments: {argv[-2] if argv[-1][0] != '-' else argv[-1]}" in err, err
