"""The `mpa-gym` command line against its contract (docs/design.md#cli)."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

import mpa_gym.agents.cli as cli
from mpa_gym.agents.cli import main
from mpa_gym.design import FeedforwardDesign, Reference, mode_pattern
from mpa_gym.model.params import BAR


def run_json(capsys, *args):
    assert main([*args, "--json"]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1  # one JSON object on one line
    return json.loads(out)


def test_design_json_keys_and_values(capsys):
    o = run_json(capsys, "design", "--mode", "1", "--samples", "31")
    assert {"t", "x_ref", "v_ref", "pe_bar", "pf_bar", "k", "feasible"} <= set(o)
    assert len(o["t"]) == 31 and o["feasible"] is True
    d = FeedforwardDesign(Reference(), flexor=mode_pattern(1))
    s = d.sample(np.array(o["t"]))
    np.testing.assert_allclose(o["pe_bar"], s.pe / BAR, rtol=1e-12)
    np.testing.assert_allclose(o["pf_bar"], 1.0 + np.sin(2 * np.pi * np.array(o["t"]) / 3),
                               rtol=1e-12)


def test_design_flags_reach_the_reference(capsys):
    o = run_json(capsys, "design", "--x0", "0.78", "--amp", "0.01", "--period", "2", "--pf-mean",
                 "0.8", "--pf-amp", "0.3", "--samples", "5")
    np.testing.assert_allclose(o["x_ref"], 0.78 + 0.01 * np.sin(np.pi * np.array(o["t"])),
                               atol=1e-15)
    assert o["t"][-1] == 2.0


def test_stiffness_design_reports_infeasible_k(capsys):
    o = run_json(capsys, "design", "--stiffness-const", "2000")
    assert o["feasible"] is False and o["violations"]
    np.testing.assert_allclose(o["k"], 2000.0, rtol=1e-9)  # Eq. 25 round trip through the CLI
    assert all(lo <= 2000.0 for lo in o["k_feasible_min"])
    assert any(hi < 2000.0 for hi in o["k_feasible_max"])


def test_analyze_json(capsys):
    o = run_json(capsys, "analyze")
    assert o["int_a1"] < 0 and o["stable"] is True
    mults = [complex(re, im) for re, im in o["floquet_multipliers"]]
    assert len(mults) == 2
    np.testing.assert_allclose(np.prod(mults).real, np.exp(o["int_a1"]), rtol=1e-8)


def test_simulate_json(capsys):
    o = run_json(capsys, "simulate", "--scenario", "mass_mismatch")
    assert {"rmse_m", "max_abs_err_m", "t", "x", "x_ref"} <= set(o)
    assert len(o["t"]) == len(o["x"]) == len(o["x_ref"]) == 3001
    assert o["rmse_m"] > 5e-3


def test_human_output_is_a_table(capsys):
    assert main(["design"]) == 0
    out = capsys.readouterr().out
    assert "P'_e [bar]" in out and "design is feasible" in out


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["design", "--pf-amp", "1"], "--pf-amp=1 bar is outside the allowed range [-0.5, 0.5]"),
        (["design", "--amp", "nan"], "--amp=nan must be finite"),
        (["design", "--samples", "1"], "--samples=1 is outside the allowed range [2, 100000]"),
        (["simulate", "--scenario", "nope"], "neither a file nor one of the named scenarios"),
    ],
)
def test_bad_input_exits_2_with_a_message(capsys, args, match):
    assert main(args) == 2
    err = capsys.readouterr().err
    assert match in err


@pytest.mark.parametrize("how", ["console_script", "module"])
def test_command_runs_as_a_process(how):
    exe = shutil.which("mpa-gym")
    assert exe is not None, "pip install -e . installs the mpa-gym console script"
    cmd = [exe] if how == "console_script" else [sys.executable, "-m", "mpa_gym.agents.cli"]
    r = subprocess.run([*cmd, "analyze", "--json"], capture_output=True, text=True, check=True)
    assert json.loads(r.stdout)["stable"] is True


def test_emulate_stops_on_sigterm_with_the_documented_exit_code():
    """Ctrl-C is how an emulator is meant to stop (exit 0); SIGTERM exits 128 + 15 like every
    other command, after printing what it served."""
    import re
    import signal

    proc = subprocess.Popen([sys.executable, "-m", "mpa_gym.agents.cli", "emulate", "--udp",
                             "--port", "0", "--duration", "60", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert re.search(r"udp://\S+", proc.stderr.readline())
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 143, err
    assert "interrupted by SIGTERM" in err and "Traceback" not in err
    assert "commands" in json.loads(out)


def test_a_missing_optional_package_names_its_extra(monkeypatch, capsys):
    # stable-baselines3 is installed here: a missing submodule of it is a genuine fault (the
    # traceback shows); the package itself missing is answered with the extra that brings it
    def needs(name):
        def run(a):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return run

    monkeypatch.setattr(cli, "cmd_figures", needs("stable_baselines3.nosuch"))
    with pytest.raises(ModuleNotFoundError):
        main(["figures", "--out", "unused"])
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda n, *a: None if n == "stable_baselines3" else real(n, *a))
    assert main(["figures", "--out", "unused"]) == 2
    err = capsys.readouterr().err
    assert "needs stable_baselines3" in err and "pip install 'mpa-gym[train]'" in err
