"""Several seeds of one config: training them side by side, and their results with intervals.

- :func:`train_seeds` (``mpa-gym train --seeds 0 1 2 3 4``) trains one process per seed, as many
  at once as the machine has cores (each on one torch thread), into sibling run folders
  ``<run-dir>-s<seed>``.
- :func:`aggregate` (used by ``mpa-gym evaluate`` when it is given several run folders of one
  config) gives, per scenario and metric, the interquartile mean over the runs and its 95 %
  stratified-bootstrap confidence interval, computed by the ``rliable`` library (Agarwal et al.,
  "Deep RL at the edge of the statistical precipice", 2021) as its authors recommend for a
  handful of runs; :func:`learning_curves` does the same for each held-out evaluation during
  training, and :func:`plot_curves` draws them.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from mpa_gym.agents.learned.config import DEFAULT_CONFIG, SEED_MAX, load_config, with_scenario
from mpa_gym.agents.learned.policies import ALONE_LABEL, run_of, spec_label
from mpa_gym.agents.learned.runs import read_run_config
from mpa_gym.files import check_out_dir

BOOTSTRAP_REPS = 5000  # rliable's default is 50 000; 5 000 puts 95 % bounds within ~1 % of it
CI = 0.95
MAX_JOBS = 256  # most training processes at once (--jobs)
METRICS = ("position_rmse_mm", "position_max_mm", "stiffness_rmse_pct", "saturation_pct",
           "return", "policy_share")


def cores() -> int:
    """Cores this process may use (the affinity mask, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def train_seeds(seeds: list[int], config: str | Path | None = None,
                run_dir: str | Path | None = None, n_timesteps: int | None = None,
                jobs: int | None = None, scenario: str | None = None,
                eval_worker: bool | None = None) -> list[dict[str, Any]]:
    """Train one run per seed in its own process (``jobs`` at once, default the cores); the
    runs go to ``<run_dir>-s<seed>`` (default ``runs/<config stem>-s<seed>``). Returns each
    process's ``mpa-gym train --json`` output; a failed seed raises after the others finish.

    ``eval_worker`` (``mpa-gym train --eval-worker``): None gives each run an evaluation worker
    only if there is a spare core for every run at once (else the workers would slow the other
    seeds' training as much as they speed up their own)."""
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds={seeds} must be distinct seeds, at least one")
    for s in seeds:  # every seed, the config and the folders checked before a child starts
        if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= SEED_MAX:
            raise ValueError(f"--seeds: seed {s!r} must be a whole number in [0, {SEED_MAX}]")
    if jobs is not None and (isinstance(jobs, bool) or not isinstance(jobs, int)
                             or not 1 <= jobs <= MAX_JOBS):
        raise ValueError(f"--jobs={jobs!r} must be a whole number of processes in "
                         f"[1, {MAX_JOBS}]")
    config = Path(config or DEFAULT_CONFIG)
    if scenario is None:
        load_config(config)
    else:
        with_scenario(config, scenario)
    base = Path(run_dir) if run_dir else Path("runs") / config.stem
    folders = [base.parent / f"{base.name}-s{s}" for s in seeds]
    for f in folders:
        if f.exists() and not f.is_dir():
            raise ValueError(f"--run-dir: run folder {str(f)!r} is a file")
        if (f / "model.zip").exists() or (f / "config.yaml").exists():
            raise ValueError(f"--run-dir: run folder {f} already holds a run; choose another "
                             "--run-dir")
    check_out_dir("--run-dir", str(base.parent))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    at_once = min(jobs or cores(), len(seeds))
    if eval_worker is None:
        eval_worker = None if cores() >= 2 * at_once else False

    def one(seed: int, folder: Path) -> dict[str, Any]:
        cmd = [sys.executable, "-m", "mpa_gym.agents.cli", "train", "--config", str(config),
               "--run-dir", str(folder), "--seed", str(seed), "--no-progress", "--json"]
        if n_timesteps is not None:
            cmd += ["--n-timesteps", str(n_timesteps)]
        if scenario is not None:
            cmd += ["--scenario", str(scenario)]
        if eval_worker is not None:
            cmd.append("--eval-worker" if eval_worker else "--no-eval-worker")
        r = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if r.returncode != 0:  # the child's last word: its one-line error or a traceback's end
            said = r.stderr.strip().splitlines() or [f"exit code {r.returncode}"]
            return {"run_dir": str(folder), "seed": seed, "error": said[-1]}
        return {**json.loads(r.stdout), "seed": seed}

    with ThreadPoolExecutor(max_workers=at_once) as pool:
        out = list(pool.map(one, seeds, folders))
    failed = [o for o in out if "error" in o]
    if failed:
        raise SeedsFailed([o for o in out if "error" not in o], "; ".join(
            f"seed {o['seed']} ({o['run_dir']}) failed: {o['error']}" for o in failed))
    return out


class SeedsFailed(RuntimeError):
    """Some seeds of :func:`train_seeds` failed (after the others finished); ``done`` holds the
    runs that finished, the message each failure's last line."""

    def __init__(self, done: list[dict[str, Any]], message: str) -> None:
        super().__init__(message)
        self.done = done


# ------------------------------------------------------------------ grouping and statistics

def config_key(run: str | Path) -> str:
    """A run's config without its seed: runs of one config share it."""
    data = copy.deepcopy(read_run_config(run).raw)  # either layout (learned.runs)
    (data.get("mpa_gym") or {}).pop("seed", None)
    return json.dumps(data, sort_keys=True, default=str)


def group_runs(policies: list[str]) -> list[list[str]]:
    """The run folders among ``policies`` grouped by config (:func:`config_key`) and by how
    they run: supervised (as given) and ``RUN_DIR:alone`` (the policy alone,
    ``mpa_gym.agents.learned.policies.ALONE``) are separate groups, so each has its own
    interval. Groups of two or more runs only (a lone run of its config has no interval)."""
    by_cfg: dict[tuple[str, bool], list[str]] = {}
    for spec in policies:
        run, supervised = run_of(spec)
        if run is not None:
            by_cfg.setdefault((config_key(run), supervised), []).append(spec)
    return [runs for runs in by_cfg.values() if len(runs) > 1]


def require_stats() -> None:
    """Raise a clear error, before any work, when ``rliable`` (the ``stats`` extra) is absent."""
    try:
        import rliable  # noqa: F401
    except ImportError:
        raise ValueError("--policy: several runs of one config are aggregated with intervals "
                         "by the rliable library, which is not installed (the stats extra): "
                         "pip install -c constraints.txt -e \".[stats]\"") from None


def group_label(runs: list[str]) -> str:
    """``name`` for runs ``name-s0``, ``name-s1``, … (else the first folder's name + ``…``);
    ``name (alone)`` for a group of ``RUN_DIR:alone``."""
    folders = [run_of(r) for r in runs]
    names = [f.name if f is not None else r for (f, _), r in zip(folders, runs, strict=True)]
    stems = {n.rsplit("-s", 1)[0] if n.rsplit("-s", 1)[-1].isdigit() else n for n in names}
    alone = "" if folders[0][1] else ALONE_LABEL
    return (stems.pop() if len(stems) == 1 else f"{names[0]}…") + alone


def iqm_ci(scores: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Per task (column): IQM over the runs (rows) and its 95 % stratified-bootstrap CI.

    ``scores`` (n_runs, n_tasks); returns (iqm (n_tasks,), ci (2, n_tasks))."""
    from rliable import library
    from scipy.stats import trim_mean

    scores = np.asarray(scores, dtype=float)
    # rliable's aggregate_iqm of each column (trim_mean(column, 0.25)), all columns in one call:
    # the same numbers, one scipy call per bootstrap sample instead of one per task
    per_task = lambda x: trim_mean(x, 0.25, axis=0)  # noqa: E731
    with warnings.catch_warnings():  # rliable hands arch a RandomState, which arch deprecates
        warnings.simplefilter("ignore", FutureWarning)
        point, ci = library.get_interval_estimates(
            {"m": scores}, per_task, reps=BOOTSTRAP_REPS, confidence_interval_size=CI,
            random_state=np.random.RandomState(seed))
    return point["m"], ci["m"]


def aggregate(results: dict[str, dict[str, Any]], runs: list[str]) -> dict[str, dict[str, Any]]:
    """Per scenario, for the group of ``runs`` (their labels in ``results``): each metric's
    IQM over the runs and ``<metric>_ci`` [low, high] (``policy_share`` among them: the share of
    steps the learned policy drove), plus ``n_runs``, ``terminated`` (how many runs
    terminated), ``fallback_runs`` and ``last_resort_runs`` (in how many a supervisor's
    fallback, and its last resort, drove) and ``chosen_runs`` (in how many of those it drove
    from the start, chosen on the model: ``who_drove``'s ``chosen``)."""
    labels = [spec_label(r) for r in runs]
    scen = list(results)
    out: dict[str, dict[str, Any]] = {sc: {"n_runs": len(runs)} for sc in scen}
    cols = [(key, sc) for key in METRICS for sc in scen]  # one bootstrap for every column
    point, ci = iqm_ci(np.array([[results[sc][lab][key] for key, sc in cols] for lab in labels]))
    for j, (key, sc) in enumerate(cols):
        out[sc][key] = float(point[j])
        out[sc][f"{key}_ci"] = [float(ci[0, j]), float(ci[1, j])]
    for sc in scen:
        out[sc]["terminated"] = sum(bool(results[sc][lab]["terminated"]) for lab in labels)
        rec = [results[sc][lab]["recovery_s"] for lab in labels]
        out[sc]["recovery_s"] = None if any(r is None for r in rec) else float(np.median(rec))
        for key in ("fallback", "last_resort"):
            out[sc][f"{key}_runs"] = sum(results[sc][lab].get(f"{key}_s") is not None
                                         for lab in labels)
        out[sc]["chosen_runs"] = sum(results[sc][lab].get("chosen") is not None
                                     for lab in labels)
    return out


def learning_curves(runs: list[str], key: str = "position_rmse_mm") -> dict[str, Any]:
    """IQM and 95 % CI of ``key`` over the runs at each held-out evaluation of training, per
    scenario (the evaluations the runs share: same steps, same scenarios)."""
    hists = [json.loads((Path(r) / "eval" / "evaluations.json").read_text()) for r in runs
             if (Path(r) / "eval" / "evaluations.json").is_file()]
    if len(hists) != len(runs) or not hists:
        return {}
    n = min(len(h) for h in hists)
    steps = [h["timesteps"] for h in hists[0][:n]]
    scen = [s for s in hists[0][0]["scenarios"] if all(s in e["scenarios"] for h in hists
                                                       for e in h[:n])]
    out: dict[str, Any] = {"timesteps": steps, "metric": key, "scenarios": {}}
    for sc in scen:
        scores = np.array([[h[i]["scenarios"][sc][key] for i in range(n)] for h in hists])
        point, ci = iqm_ci(scores)
        out["scenarios"][sc] = {"iqm": point.tolist(), "ci_low": ci[0].tolist(),
                                "ci_high": ci[1].tolist()}
    return out


def plot_curves(curves: dict[str, dict[str, Any]], path: Path) -> Path:
    """Aggregate learning curves (IQM with the 95 % CI as a band), one panel per scenario."""
    from matplotlib.figure import Figure

    scen = sorted({s for c in curves.values() for s in c.get("scenarios", {})})
    fig = Figure(figsize=(4 * max(1, len(scen)), 3.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, max(1, len(scen)), sharey=True))
    for ax, sc in zip(axes, scen, strict=False):
        for i, (label, c) in enumerate(curves.items()):
            if sc not in c.get("scenarios", {}):
                continue
            t = np.array(c["timesteps"]) / 1e6
            d = c["scenarios"][sc]
            ax.plot(t, d["iqm"], color=f"C{i}", label=f"{label} (IQM)")
            ax.fill_between(t, d["ci_low"], d["ci_high"], color=f"C{i}", alpha=0.25,
                            label="95 % CI")
        ax.set(title=sc, xlabel="env steps [M]", yscale="log")
    axes[0].set_ylabel("held-out position RMSE [mm]")
    axes[0].legend(fontsize=7)
    fig.savefig(path, dpi=90)
    return path
