"""Hostile-input probes of the ``mpa-gym`` command line, each a real process (issue 34).

    python tools/probe.py [--out DIR] [--jobs N] [--timeout S] [--only CMD ...]

Three kinds of probe:

- **options**: every option of every subcommand, read from the parser itself, given the values a
  user types by mistake (``nan``, ``inf``, ``-1``, ``0``, text for a number, an empty string, a
  folder, a binary, broken or list-shaped YAML, a missing file, a path under a file, a name that
  does not exist), one at a time on a cheap valid invocation of that subcommand;
- **registry**: the CLI table of ``tests/test_reliability.py`` (each a bad input with the words
  its message must hold), as processes rather than in-process calls;
- **signals**: SIGINT and SIGTERM a few seconds into each long-running command: the documented
  code (130 / 143; the emulator exits 0 on Ctrl-C), one line, and what was reached kept (a
  training run's ``model.zip``, a rollout's log, a tune trial queued again).

Each probe ends as one of:

``refused``    exit 2 with one line ``mpa-gym CMD: error: ...`` naming the flag (or field) and
               the value;
``accepted``   exit 0 for a value that may be valid (``0``, ``-1``, a folder...): listed for a
               person to judge;
``ok``         a signal probe that held;
``silent``     exit 0 for a value no command can honour (``nan``, text for a number, an empty
               string, broken YAML...) or a registry case that exited 0;
``unclear``    refused, but the line names neither the flag nor the value, or spans several
               lines, or an undocumented exit code, or a signal probe that lost its work;
``traceback``  "Traceback" on stderr;
``hang``       no exit within ``--timeout`` seconds.

It writes ``probes.jsonl`` (one record per probe: argv, exit code, seconds, outcome, stderr's
last lines) and prints the counts and every probe that is not refused / ok. The exit code is 1
when any probe is silent, unclear, a traceback or a hang.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

FLOATS = ["nan", "inf", "-inf", "-1", "0", "1e308", "abc", ""]
INTS = ["-1", "0", "1.5", "abc", "", "99999999999999999999"]
PATHS = ["", "{folder}", "{binary}", "{broken}", "{list}", "{w}/missing.yaml", "{file}/x",
         "nonsense"]
# values no option can honour: a probe that exits 0 with one of them is silent
NEVER = {"nan", "inf", "-inf", "1e308", "abc", "", "1.5", "99999999999999999999", "bogus",
         "{binary}", "{broken}", "{list}", "{w}/missing.yaml", "{file}/x"}
# options that name a file or folder to write: an existing file there may be overwritten
OUTPUTS = {("figures", "--out"), ("train", "--run-dir"), ("evaluate", "--out"),
           ("tune-baselines", "--out"), ("tune", "--out-dir"), ("tune", "--out"),
           ("rollout", "--log"), ("identify", "--out"), ("identify", "--plot"),
           ("identify", "--coverage-dir")}
NEVER_OUT = {"", "{file}/x"}
# free-form names (any text is a valid Optuna study name): only the empty one is never valid
NAMES = {("tune", "--study-name")}

# cheap valid invocations: {flag: value | [values] | None (a switch)}; a probe sets one flag
BASES: dict[str, list[dict]] = {
    "design": [{}],
    "analyze": [{}],
    "simulate": [{"--scenario": "nominal"}],
    "figures": [{"--out": "{w}/figs"}],
    "train": [{"--config": "{tiny}", "--run-dir": "{w}/run", "--no-progress": None},
              {"--no-progress": None}],
    "evaluate": [{"--policy": ["ff"], "--scenarios": ["nominal"], "--no-robustness": None,
                  "--out": "{w}/ev"}],
    "tune-baselines": [{"--policy": ["pid"], "--n-trials": "1", "--n-plants": "1",
                        "--episode-s": "3", "--out": "{w}/g.yaml"}],
    "calibrate": [{"": "{run}", "--n-plants": "2", "--episode-s": "3"}],
    "tune": [{"--config": "{tiny_tune}", "--storage": "sqlite:///{w}/t.db", "--n-trials": "1",
              "--out-dir": "{w}/tune", "--heldout": ["{short}"]},
             {"--best": "probe", "--storage": "sqlite:///{study}", "--out": "{w}/best.yaml"}],
    "emulate": [{"--udp": None, "--duration": "1"}],
    "rollout": [{"--policy": "ff", "--dry-run": None, "--episodes": "1", "--episode-s": "1",
                 "--log": "{w}/r.jsonl"}],
    "identify": [{"--log": "{excite}", "--out": "{w}/id.yaml", "--plot": "{w}/id.png"},
                 {"--coverage": "1", "--episode-s": "12", "--coverage-dir": "{w}/cov"}],
    "bench": [{"--seconds": "0.05", "--sizes": ["1"]},
              {"--inference": "{run}", "--actions": "100", "--no-emulator": None},
              {"--loop": "ff", "--loop-s": "1", "--repeats": "1"}],
}
# an option that belongs to a mode: the base it is probed on (default: the command's first)
MODE = {("train", "--resume"): 1,
        ("tune", "--best"): 1, ("tune", "--trial"): 1, ("tune", "--out"): 1,
        ("identify", "--coverage"): 1, ("identify", "--seed"): 1, ("identify", "--jobs"): 1,
        ("identify", "--episode-s"): 1,
        ("identify", "--coverage-dir"): 1, ("bench", "--inference"): 1,
        ("bench", "--actions"): 1, ("bench", "--no-emulator"): 1, ("bench", "--loop"): 2,
        ("bench", "--control-hz"): 2, ("bench", "--loop-s"): 2, ("bench", "--repeats"): 2,
        ("bench", "--rig"): 2, ("bench", "--gains"): 2}
# long-running invocations for the signal probes, and what each must keep
LONG: dict[str, tuple[list[str], float, str | None]] = {
    "train": (["train", "--config", "{tiny_long}", "--run-dir", "{w}/run", "--no-progress"],
              25.0, "{w}/run/model.zip"),
    "evaluate": (["evaluate", "--policy", "ff", "pid", "--out", "{w}/ev", "--random-rigs", "50"],
                 12.0, None),
    "tune": (["tune", "--config", "{tiny_tune}", "--storage", "sqlite:///{w}/t.db",
              "--n-trials", "1", "--n-timesteps", "1000000", "--out-dir", "{w}/tune",
              "--heldout", "{short}"], 25.0, "{w}/tune/trial0000-s0/model.zip"),
    "rollout": (["rollout", "--policy", "ff", "--dry-run", "--episodes", "3", "--episode-s",
                 "20", "--log", "{w}/r.jsonl"], 10.0, "{w}/r.jsonl"),
    "emulate": (["emulate", "--udp"], 5.0, None),
    "tune-baselines": (["tune-baselines", "--n-trials", "50", "--out", "{w}/g.yaml"], 10.0,
                       None),
    "identify": (["identify", "--coverage", "2", "--coverage-dir", "{w}/cov"], 20.0, None),
    "bench": (["bench", "--loop", "ff", "--loop-s", "30", "--repeats", "1"], 10.0, None),
}


@dataclass
class Probe:
    kind: str                 # options | registry | signals
    argv: list[str]
    command: str
    flag: str = ""
    value: str = ""
    want: list[str] = field(default_factory=list)   # registry: the words the message holds
    expect: str = "either"    # options: "refuse" (NEVER values) or "either"
    signal: str = ""          # signals: SIGINT / SIGTERM
    after_s: float = 0.0
    keeps: str | None = None  # signals: a path that must exist afterwards


def _argv(base: dict, flag: str | None = None, value: str | None = None) -> list[str]:
    d = dict(base)
    if flag is not None:
        d[flag] = value
    out = []
    for k, v in d.items():
        if k == "":
            out.append(v)
            continue
        if isinstance(v, str) and v.startswith("-") and not _is_number(v):
            out.append(f"{k}={v}")  # argparse reads "-inf" after a flag as another flag
            continue
        out.append(k)
        if isinstance(v, list):
            out += v
        elif v is not None:
            out.append(v)
    return out


def _is_number(v: str) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return v.lstrip("-")[:1].isdigit()


def option_probes() -> list[Probe]:
    from mpa_gym.agents.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    probes = []
    for cmd, p in sub.choices.items():
        for act in p._actions:
            if not act.option_strings or act.option_strings[0] in ("-h", "--json"):
                continue
            flag = act.option_strings[-1]
            if act.nargs == 0:
                continue  # a switch has no value to get wrong; the registry pairs them
            if act.choices is not None:
                values = ["bogus", ""]
            elif act.type in (float,):
                values = FLOATS
            elif act.type in (int,):
                values = INTS
            else:
                values = PATHS
            base = BASES[cmd][MODE.get((cmd, flag), 0)]
            never = (NEVER_OUT if (cmd, flag) in OUTPUTS else {""} if (cmd, flag) in NAMES
                     else NEVER)
            for v in values:
                val = [v] if act.nargs in ("+", "*") else v
                probes.append(Probe("options", [cmd, *_argv(base, flag, val)[0:]], cmd, flag,
                                    v, expect="refuse" if v in never else "either"))
    return probes


def registry_probes(files: dict[str, str]) -> list[Probe]:
    import test_reliability as reg

    probes = []
    for i, (argv, want, _) in enumerate(reg.CASES):
        own = Path(files["tmp"]) / f"registry{i:03d}"  # each case writes its files here
        own.mkdir()
        probes.append(Probe("registry", reg._argv(argv, {**files, "tmp": str(own)}), argv[0],
                            want=want))
    return probes


def signal_probes() -> list[Probe]:
    return [Probe("signals", argv, cmd, signal=sig, after_s=after, keeps=keeps)
            for cmd, (argv, after, keeps) in LONG.items() for sig in ("SIGINT", "SIGTERM")]


# ----------------------------------------------------------------------------- fixtures
def fixtures(root: Path) -> dict[str, str]:
    """Files every probe may name, a tiny trained run, a rollout log to identify and a study."""
    small = small_files(root)
    cfg = yaml.safe_load((ROOT / "configs" / "ppo_residual.yaml").read_text())
    env_id = next(k for k in cfg if k != "mpa_gym")
    cfg[env_id].update(n_envs=2, n_timesteps=64, n_steps=32, batch_size=32)
    cfg["mpa_gym"].update(eval_freq=10**6, checkpoint_freq=10**6,
                          eval_scenarios=[{"name": "ev", "duration_s": 1.0}])
    (root / "tiny.yaml").write_text(yaml.safe_dump(cfg))
    cfg[env_id]["n_timesteps"] = 10**7
    (root / "tiny_long.yaml").write_text(yaml.safe_dump(cfg))
    cfg[env_id].update(n_envs=4, n_timesteps=128, batch_size=64, n_epochs=1)
    cfg[env_id]["env_kwargs"]["task"]["episode_s"] = 0.5
    cfg["mpa_gym"].update(eval_freq=128, tune={"learning_rate": {"float": [1e-4, 1e-3],
                                                                 "log": True}})
    (root / "tiny_tune.yaml").write_text(yaml.safe_dump(cfg))
    (root / "short.yaml").write_text(yaml.safe_dump({
        "name": "short", "duration_s": 1.5,
        "reference": {"x0_m": 0.8, "amp_m": 0.02, "period_s": 0.5}}))
    files = {**small, "tmp": str(root), "tiny": str(root / "tiny.yaml"),
             "tiny_long": str(root / "tiny_long.yaml"), "tiny_tune": str(root / "tiny_tune.yaml"),
             "short": str(root / "short.yaml"), "run": str(root / "run"),
             "excite": str(root / "excite.jsonl"), "study": str(root / "study.db")}
    made = [
        ["train", "--config", files["tiny"], "--run-dir", files["run"], "--no-progress"],
        ["rollout", "--policy", "excite", "--dry-run", "--episodes", "1", "--episode-s", "12",
         "--log", files["excite"]],
        ["tune", "--config", files["tiny_tune"], "--storage", f"sqlite:///{files['study']}",
         "--study-name", "probe", "--n-trials", "1", "--out-dir", str(root / "study_runs"),
         "--heldout", files["short"]],
    ]
    for argv in made:
        r = subprocess.run([sys.executable, "-m", "mpa_gym.agents.cli", *argv],
                           capture_output=True, text=True, env=_env())
        if r.returncode != 0:
            raise SystemExit(f"fixture {' '.join(argv)} failed ({r.returncode}): {r.stderr}")
    return files


def small_files(root: Path) -> dict[str, str]:
    """The hostile files (an empty folder, a plain file, binary / broken / list-shaped YAML, a
    run folder without config and a started one) in ``root``. Every probe gets its own: an
    output probe that writes into ``{folder}`` must not turn it into a run folder for the next."""
    (root / "folder").mkdir()
    (root / "a_file").write_text("x")
    (root / "binary.yaml").write_bytes(b"\x00\x01\xff\xfe\x80")
    (root / "broken.yaml").write_text("duration_s: [1, 2\n")
    (root / "list.yaml").write_text("- 1\n- 2\n")
    (root / "run_no_config").mkdir()
    (root / "started").mkdir()
    (root / "started" / "config.yaml").write_text("{}")
    names = {"folder": "folder", "file": "a_file", "binary": "binary.yaml",
             "broken": "broken.yaml", "list": "list.yaml", "run_no_config": "run_no_config",
             "started": "started"}
    return {k: str(root / v) for k, v in names.items()}


def _env() -> dict[str, str]:
    return {**os.environ, "MPLBACKEND": "Agg", "PYTHONWARNINGS": "ignore"}


# ----------------------------------------------------------------------------- running
def run(probe: Probe, files: dict[str, str], work: Path, timeout: float) -> dict:
    w = Path(tempfile.mkdtemp(dir=work))
    subst = {**files, **small_files(w), "w": str(w)}
    argv = [a.format(**subst) for a in probe.argv]
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "mpa_gym.agents.cli", *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=w, env=_env(), start_new_session=True,
                            # a terminal's Ctrl-C: SIGINT handled, even when this harness runs
                            # in the background (where a shell starts it with SIGINT ignored)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    if probe.signal:
        try:
            proc.wait(timeout=probe.after_s)
        except subprocess.TimeoutExpired:
            proc.send_signal(getattr(signal, probe.signal))
    try:
        _, err = proc.communicate(timeout=timeout)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        code = None
    rec = {**asdict(probe), "argv": argv, "code": code,
           "seconds": round(time.monotonic() - t0, 2),
           "stderr": err.strip().splitlines()[-3:]}
    keeps = probe.keeps.format(**subst) if probe.keeps else None
    rec["outcome"] = judge(probe, code, err, keeps)
    return rec


def _lines(err: str) -> list[str]:
    """stderr less Optuna's and the emulator's informational log lines and argparse's usage
    (which it prints above its own errors, as every argparse program does)."""
    out, usage = [], False
    for ln in err.strip().splitlines():
        usage = ln.startswith("usage:") or (usage and ln.startswith(" "))
        if ln and not usage and not ln.startswith(("[I ", "[W ", "emulating the rig")):
            out.append(ln)
    return out


def judge(probe: Probe, code: int | None, err: str, keeps: str | None) -> str:
    if code is None:
        return "hang"
    if "Traceback" in err:
        return "traceback"
    lines = _lines(err)
    if probe.kind == "signals":
        want = 0 if (probe.command == "emulate" and probe.signal == "SIGINT") else (
            128 + getattr(signal, probe.signal))
        if code != want or len(lines) > 2 or (keeps and not Path(keeps).exists()):
            return "unclear"
        return "ok"
    if code == 0:
        if probe.kind == "registry" or probe.expect == "refuse":
            return "silent"
        return "accepted"
    if code != 2 or len(lines) != 1 or not lines[0].startswith(f"mpa-gym {probe.command}"):
        return "unclear"
    msg = lines[0]
    if probe.kind == "registry":
        return "refused" if all(w in msg for w in probe.want) else "unclear"
    value = probe.value.format(folder="folder", binary="binary.yaml", broken="broken.yaml",
                               list="list.yaml", w="", file="a_file")
    named_flag = probe.flag in msg or probe.flag.lstrip("-") in msg
    named_file = probe.value.startswith("{") and Path(value).name in msg
    named_value = (value == "" and ("empty" in msg or "''" in msg or "expected one" in msg)) or (
        value != "" and (value in msg or Path(value).stem in msg or _same_number(value, msg)))
    # a hostile file is named by its path (the user's own words) as well as by the flag
    return "refused" if (named_flag or named_file) and named_value else "unclear"


def _same_number(value: str, msg: str) -> bool:
    try:
        x = float(value)
    except ValueError:
        return False
    whole = math.isfinite(x) and x == int(x) and abs(x) < 1e300
    return any(s in msg for s in (repr(x), str(x), f"{x:g}", str(int(x)) if whole else "\0"))


def _key(rec: dict) -> tuple:
    """What identifies a probe across runs (its paths differ)."""
    return (rec["kind"], rec["command"], rec["flag"], rec["value"], rec["signal"],
            tuple(rec["want"]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/probes", help="folder of probes.jsonl")
    ap.add_argument("--jobs", type=int, default=2, help="probes at once")
    ap.add_argument("--timeout", type=float, default=180.0, help="seconds before a hang")
    ap.add_argument("--only", nargs="+", metavar="CMD", help="these subcommands only")
    ap.add_argument("--kinds", nargs="+", default=["options", "registry", "signals"],
                    choices=["options", "registry", "signals"])
    ap.add_argument("--again", metavar="PROBES_JSONL",
                    help="only the probes that a previous run's records did not pass")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="probes-"))
    print(f"fixtures in {work} ...", flush=True)
    files = fixtures(work)
    probes = []
    if "options" in a.kinds:
        probes += option_probes()
    if "registry" in a.kinds:
        probes += registry_probes(files)
    if "signals" in a.kinds:
        probes += signal_probes()
    if a.only:
        probes = [p for p in probes if p.command in a.only]
    if a.again:
        failed = {_key(r) for r in map(json.loads, Path(a.again).read_text().splitlines())
                  if r["outcome"] not in ("refused", "ok", "accepted")}
        probes = [p for p in probes if _key(asdict(p)) in failed]
    print(f"{len(probes)} probes, {a.jobs} at a time", flush=True)
    records = []
    with open(out / "probes.jsonl", "w") as f, ThreadPoolExecutor(a.jobs) as pool:
        for rec in pool.map(lambda p: run(p, files, work, a.timeout), probes):
            f.write(json.dumps(rec) + "\n")
            f.flush()
            records.append(rec)
    counts: dict[str, int] = {}
    for r in records:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
    print(f"{len(records)} probes: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    for r in records:
        if r["outcome"] not in ("refused", "ok"):
            print(f"  {r['outcome']:<9} rc={r['code']} {' '.join(r['argv'])[:110]}\n"
                  f"            {(r['stderr'] or [''])[-1][:160]}")
    bad = {"silent", "unclear", "traceback", "hang"}
    return 1 if any(r["outcome"] in bad for r in records) else 0


if __name__ == "__main__":
    sys.exit(main())
