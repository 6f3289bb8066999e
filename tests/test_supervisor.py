"""Run-time assurance (mpa_gym.agents.controllers.supervisor): the fallback rescues a residual that
destabilises the plant, never drives a healthy loop, and the config names what is wrong with a bad
spec."""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml
from conftest import REALTIME, serving, tiny_config

import mpa_gym  # noqa: F401
from mpa_gym.agents.cli import show_rollout
from mpa_gym.agents.controllers import baselines
from mpa_gym.agents.controllers.baselines import BAR, BASELINES, Policy, make_baseline
from mpa_gym.agents.controllers.supervisor import (
    ARM_PERIODS,
    FALLBACK,
    GRACE_PERIODS,
    Divergence,
    LimitCycle,
    Persistent,
    Selection,
    Stage,
    Supervised,
    SupervisorSpec,
    took_over,
)
from mpa_gym.agents.evaluation.episodes import Job, run_episodes
from mpa_gym.agents.evaluation.evaluate import evaluate
from mpa_gym.agents.evaluation.robustness import _cell as robustness_cell
from mpa_gym.agents.evaluation.robustness import _scenario, cell_metrics, run_batches
from mpa_gym.agents.learned.config import ConfigError, parse_config
from mpa_gym.agents.learned.policies import supervise
from mpa_gym.agents.rig.rollout import read_log, rollout
from mpa_gym.agents.training.train import train
from mpa_gym.analysis.scenario import load_scenario
from mpa_gym.design.feedforward import affine_in_pressures
from mpa_gym.model.params import check_range
from mpa_gym.task.contract import (
    OBS_COS,
    OBS_KREF,
    OBS_KREF_SCALE,
    OBS_SIN,
    OBS_V,
    OBS_VREF,
    OBS_X,
    OBS_XREF,
    obs_names,
)

DT, T = 0.01, 3.0
N_OBS = len(obs_names(residual=True))


def flat(**keys) -> SupervisorSpec:
    """The spec of a flat ``supervisor`` section (the form run folders hold; its omitted keys
    mean what they always did: no clip, no persistent monitor, no last resort)."""
    return SupervisorSpec.from_config(keys)


class Constant:
    """A controller that always outputs ``value`` (to see which one drives)."""

    def __init__(self, value: float) -> None:
        self.value = value

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        obs = np.atleast_2d(observation)
        a = np.full((obs.shape[0], 2), self.value, dtype=np.float32)
        return (a[0] if np.ndim(observation) == 1 else a), state


def _drive(sup: Supervised, errors: np.ndarray) -> np.ndarray:
    """Feed observations with X̂ − X = errors[k, row]; the action's value per step and row."""
    state, out = None, []
    for k, e in enumerate(errors):
        obs = np.zeros((errors.shape[1], N_OBS))
        obs[:, OBS_XREF] = 0.8 + e
        obs[:, OBS_X] = 0.8
        a, state = sup.predict(obs, state, np.full(errors.shape[1], k == 0))
        out.append(a[:, 0])
    return np.array(out)


def test_monitor_trips_on_an_aperiodic_oscillation_and_not_on_a_periodic_error():
    # Row 0: a 10 mm-amplitude error with the reference's period (a sag and lag that repeat):
    # its change over one period is zero and its RMS (7.1 mm) is under error_mm, so the
    # policy keeps driving. Row 1: the same plus an oscillation of 3 mm RMS at 7.17 Hz, 21.5
    # cycles per period: e_t − e_{t−T} is twice the oscillation (RMS 6 mm > aperiodic_mm 3 mm),
    # and the fallback takes over once the monitor is armed (third period) and its running
    # mean of the squared change (3 s time constant) has passed (3 mm)²:
    # 1 − exp(−t / 3 s) > (3/6)², t > 3 s · ln(4/3) = 0.86 s (± the ripple at 2 × 7.17 Hz).
    # Row 2: a 20 mm step (a divergence) trips the error monitor within its 0.5 s window:
    # 1 − exp(−t / 0.5 s) > (15/20)², t > 0.5 s · ln 16/7 = 0.41 s.
    t = DT * np.arange(round(5 * T / DT))
    periodic = 0.010 * np.sin(2 * np.pi * t / T)
    osc = 0.003 * np.sqrt(2) * np.sin(2 * np.pi * (21.5 / T) * t)
    errors = np.stack([periodic, periodic + osc, np.where(t >= 1.0, 0.02, 0.0)], axis=1)
    sup = Supervised(Constant(0.0), Constant(1.0), DT, T, flat())
    drove = _drive(sup, errors) > 0.5
    first = [np.flatnonzero(drove[:, r])[0] * DT if drove[:, r].any() else None
             for r in range(3)]
    assert first[0] is None
    assert ARM_PERIODS * T + 0.75 < first[1] < ARM_PERIODS * T + 1.0
    assert 1.0 + 0.38 < first[2] < 1.0 + 0.45
    assert np.all(drove[round(first[1] / DT):, 1])  # the latch never hands back


def test_clipped_limit_cycle_monitor_lets_a_kick_pass_and_still_catches_oscillations():
    # aperiodic_mm 2 mm, each sample of e_t − e_{t−T} clipped to ±3 mm. Row 0: a kick at 7 s
    # (armed from 6 s), an error of 20 mm decaying with 0.1 s: ∫e² dt = 20 mm² s, so the
    # unclipped running mean (3 s) jumps to ~6.7 mm² > (2 mm)² and trips; clipped, the pulse
    # adds at most 9 mm² × 0.19 s (while it is above 3 mm) + 0.45 mm² s of its tail, ~0.7 mm²
    # and ~1 mm² once the change sees it again a period later: < 4 mm², no trip. Row 1: an
    # oscillation whose change has RMS 2.1 mm and peaks at 2.97 mm < 3 mm: the clip changes no
    # sample, so both trip at the same step. Row 2: the 6 mm-RMS change of the first test
    # (peaks 8.5 mm): clipped it still averages ~7.5 mm² > 4 mm², and trips.
    t = DT * np.arange(round(5 * T / DT))
    after = np.clip(t - 7.0, 0.0, None)
    kick = np.where(t >= 7.0, 0.020 * np.exp(-after / 0.1), 0.0)
    f = 21.5 / T  # cycles per period: e_t − e_{t−T} = 2 × the oscillation
    small = 0.00297 / 2 * np.sin(2 * np.pi * f * t)
    big = 0.003 * np.sqrt(2) * np.sin(2 * np.pi * f * t)
    errors = np.stack([kick, small, big], axis=1)
    drove = {clip: _drive(Supervised(Constant(0.0), Constant(1.0), DT, T,
                                     flat(aperiodic_mm=2.0, aperiodic_clip_mm=clip)),
                          errors) > 0.5 for clip in (None, 3.0)}
    first = {clip: [np.flatnonzero(d[:, r])[0] if d[:, r].any() else None for r in range(3)]
             for clip, d in drove.items()}
    assert first[None][0] is not None and first[3.0][0] is None
    assert first[3.0][1] is not None and first[3.0][1] == first[None][1]
    assert first[3.0][2] is not None and first[3.0][2] >= first[None][2]
    with pytest.raises(ValueError, match=r"aperiodic_clip_mm=1.5 mm is outside the allowed "
                                         r"range \(2, 100\] mm"):
        flat(aperiodic_mm=2.0, aperiodic_clip_mm=1.5)


def test_persistent_error_monitor_catches_a_periodic_error_and_lets_a_kick_pass():
    # persistent_mm 2 mm, each sample of e clipped to ±3 mm. Row 0: a 4 mm-amplitude error
    # with the reference's period (2.83 mm RMS), which the limit-cycle monitor cannot see (its
    # change over a period is zero) and the divergence level (15 mm) does not reach. Armed at
    # 6 s, the running mean (3 s) rises as m (1 − exp(−(t − 6 s)/3 s)), m the clipped signal's
    # mean square (5.9 mm²), so it passes (2 mm)² at 6 s + 3 s · ln(m / (m − 4 mm²)) = 9.4 s,
    # give or take the ripple at twice the reference frequency: the mean's ripple is at most
    # max|e² − m| / (2ωτ) = 5.9 / 12.6 = 0.47 mm², its slope there m/τ · (1 − 4/m) = 0.63 mm²/s,
    # so ± 0.75 s: 0.8 s. Row 1: a 1 mm periodic error and a kick at 7 s
    # (20 mm, decaying with 0.1 s): clipped, the kick adds ~1 mm² (9 mm² for its 0.19 s above
    # 3 mm and its tail) to 0.5 mm², no trip; unclipped it adds ~6.7 mm² and trips.
    t = DT * np.arange(round(5 * T / DT))
    wave = np.sin(2 * np.pi * t / T)
    kick = np.where(t >= 7.0, 0.020 * np.exp(-np.clip(t - 7.0, 0.0, None) / 0.1), 0.0)
    errors = np.stack([0.004 * wave, 0.001 * wave + kick], axis=1)

    def first(**keys):  # the limit-cycle monitor set out of the way (it sees the kick again)
        spec = flat(**keys, aperiodic_mm=100.0)
        drove = _drive(Supervised(Constant(0.0), Constant(1.0), DT, T, spec), errors) > 0.5
        return [np.flatnonzero(drove[:, r])[0] * DT if drove[:, r].any() else None
                for r in range(2)]

    m = np.mean(np.clip(0.004 * wave, -0.003, 0.003) ** 2)
    expected = ARM_PERIODS * T + 3.0 * np.log(m / (m - 0.002 ** 2))
    clipped = first(persistent_mm=2.0, persistent_clip_mm=3.0)
    assert clipped[0] == pytest.approx(expected, abs=0.8) and clipped[1] is None
    assert first(persistent_mm=2.0)[1] is not None  # the clip is what passes it
    assert first() == [None, None]  # not watched unless set
    # the fallback's own loop is not judged on it: with a last resort, the fallback keeps
    # driving under the same periodic error for six periods after the monitor re-arms (two
    # periods into the fallback's stage), where the policy's stage tripped 3.4 s after arming
    t8 = DT * np.arange(round(clipped[0] / DT) + round((ARM_PERIODS + 6) * T / DT))
    sup = Supervised(Constant(0.0), Constant(1.0), DT, T,
                     flat(aperiodic_mm=100.0, persistent_mm=2.0, persistent_clip_mm=3.0,
                          last_resort="ff"), make_baseline("ff"))
    out = _drive(sup, 0.004 * np.sin(2 * np.pi * t8 / T)[:, None])
    assert np.all(out[round(clipped[0] / DT) + 1:] == 1.0)
    with pytest.raises(ValueError, match=r"persistent_clip_mm=1.5 mm is outside the allowed "
                                         r"range \(2, 100\] mm"):
        flat(persistent_mm=2.0, persistent_clip_mm=1.5)
    with pytest.raises(ValueError,
                       match=r"persistent_clip_mm=3\.0 needs supervisor\.persistent_mm"):
        flat(persistent_clip_mm=3.0)


def test_last_resort_takes_over_when_the_fallback_loop_trips_too():
    # A 20 mm step at 1 s that the fallback does not remove (a fallback that cannot hold this
    # plant): the error monitor trips at 1.41 s (previous test) and hands over to the
    # fallback; with a last resort the error monitor restarts from zero there and judges the
    # fallback's loop after GRACE_PERIODS periods (its running mean has long passed the level
    # by then), and the feedforward alone (a zero residual) drives from then on. Without one
    # the fallback keeps driving. Row 1, a healthy periodic error, is never touched.
    t = DT * np.arange(round(3 * T / DT))
    errors = np.stack([np.where(t >= 1.0, 0.02, 0.0), 0.010 * np.sin(2 * np.pi * t / T)],
                      axis=1)
    chained = _drive(Supervised(Constant(0.5), Constant(1.0), DT, T,
                                flat(last_resort="ff"), make_baseline("ff")), errors)
    plain = _drive(Supervised(Constant(0.5), Constant(1.0), DT, T, flat()), errors)
    to_fallback = np.flatnonzero(chained[:, 0] == 1.0)[0] * DT
    to_ff = np.flatnonzero(chained[:, 0] == 0.0)[0] * DT
    assert 1.38 < to_fallback < 1.45
    assert GRACE_PERIODS * T <= to_ff - to_fallback < GRACE_PERIODS * T + 2 * DT
    assert np.all(chained[round(to_ff / DT):, 0] == 0.0)  # and stays there
    assert np.array_equal(plain[:round(to_ff / DT), 0], chained[:round(to_ff / DT), 0])
    assert np.all(plain[round(to_fallback / DT):, 0] == 1.0)
    assert np.all(chained[:, 1] == 0.5) and np.all(plain[:, 1] == 0.5)


def test_a_last_resort_with_state_starts_from_rest_on_each_row_it_takes_over():
    # The adaptive feedforward integrates the error, so its state matters. Two rows whose
    # fallback fails on a 20 mm step (at 1 s and at 2.5 s): each row's last resort takes over
    # one grace period after its fallback did, at a different step, and from there outputs
    # exactly what a fresh afc started at that step outputs (the other row's errors, which it
    # saw meanwhile, leave it untouched). Without one, the spec is refused by name.
    t = DT * np.arange(round(3 * T / DT))
    errors = np.stack([np.where(t >= 1.0, 0.02, 0.0), np.where(t >= 2.5, 0.02, 0.0)], axis=1)
    sup = Supervised(Constant(0.5), Constant(1.0), DT, T, flat(last_resort="afc"),
                     make_baseline("afc"))
    state, got, want = None, [[], []], [[], []]
    fresh = [None, None]
    for k, e in enumerate(errors):
        obs = np.zeros((2, N_OBS))
        obs[:, OBS_XREF], obs[:, OBS_X], obs[:, OBS_KREF] = 0.8 + e, 0.8, 545.0 / OBS_KREF_SCALE
        phase = 2 * np.pi * t[k] / T
        obs[:, OBS_SIN], obs[:, OBS_COS] = np.sin(phase), np.cos(phase)
        stage_before = np.zeros(2) if state is None else Supervised.stage(state)
        a, state = sup.predict(obs, state, np.full(2, k == 0))
        for r in range(2):
            if Supervised.stage(state)[r] >= 2:
                start = np.array([stage_before[r] < 2.0])
                b, fresh[r] = make_baseline("afc").predict(obs[r:r + 1], fresh[r], start)
                got[r].append(a[r])
                want[r].append(b[0])
    assert abs(len(got[0]) - len(got[1]) - round(1.5 / DT)) <= 1  # the steps 1.5 s apart
    assert len(got[1]) > 100 and np.any(np.abs(np.array(got[1])) > 0.001)
    for r in range(2):
        np.testing.assert_array_equal(np.array(got[r]), np.array(want[r]))
    with pytest.raises(ValueError, match=r"last_resort='afc' needs its controller"):
        Supervised(Constant(0.5), Constant(1.0), DT, T, flat(last_resort="afc"))


def test_last_resort_keeps_the_feedforward_where_the_fallback_is_unstable_too():
    # 40 ms of dead time (beyond what the default trains on) on the nominal leg: the tuned pid
    # is itself unstable there, so a supervisor that hands a failing residual (the stiff PID
    # of the next test) to it still loses the loop; with the feedforward as the last resort the
    # loop ends within the no-harm floor (0.05 mm) of the feedforward alone, which Theorem 1
    # keeps stable whatever the regulator's delay (it has no feedback to delay), and with afc
    # below it. The cell's metrics and its Markdown say when each stage took over.
    sc = _sc(30.0)
    plants = [{"pressure_dead_time_s": 0.04, "pressure_lag_s": 0.03}]
    pid = make_baseline("pid", sc)
    stiff = dataclasses.replace(pid, kp_bar_per_m=80.0, ki_bar_per_m_s=3000.0,
                                kd_bar_s_per_m=12.0, tf_s=0.0)
    plain = Supervised(stiff, make_baseline("pid", sc), DT, T, flat())
    chained, adaptive = (Supervised(stiff, make_baseline("pid", sc), DT, T,
                                    flat(last_resort=name), make_baseline(name, sc))
                         for name in ("ff", "afc"))
    ff = make_baseline("ff", sc)
    m_pid, m_plain, m_chained, m_adaptive, m_ff = (
        cell_metrics(r, T, DT)[0]
        for r in run_batches([pid, plain, chained, adaptive, ff], sc, plants, 3))
    assert m_pid["unstable"] and m_plain["unstable"] and not m_ff["unstable"]
    for m in (m_chained, m_adaptive):
        assert not m["unstable"] and not m["terminated"]
    assert m_chained["position_rmse_mm"] <= m_ff["position_rmse_mm"] + 0.05
    # the adaptive feedforward learns the periodic command the delay costs the feedforward
    # (its error is the delay's phase at ω₀, 2 mm here): the loop ends at less than half
    # of it, so no transient left in the window can put it above (the no-harm bound, strict)
    assert m_adaptive["position_rmse_mm"] < 0.5 * m_ff["position_rmse_mm"]
    assert m_adaptive["fallback_s"] < T < m_adaptive["last_resort_s"]  # diverged in period 1
    assert m_adaptive["last_resort_s"] - m_adaptive["fallback_s"] >= GRACE_PERIODS * T
    assert m_plain["last_resort_s"] is None and m_pid["fallback_s"] is None
    assert f"‡{m_adaptive['fallback_s']:.1f} s §{m_adaptive['last_resort_s']:.1f} s" in \
        robustness_cell(m_adaptive)


def _sc(duration_s: float) -> object:
    return _scenario(load_scenario({"name": "rig", "duration_s": duration_s}), "rig",
                     {"pressure_quantum_bar": 0.02})


def test_fallback_rescues_a_residual_that_destabilises_a_slow_regulator():
    # A stiff PID (Kp 80 bar/m, Ki 3000 bar/(m s), Kd 12 bar s/m) as "the residual" on the
    # slow-regulator plant (20 ms dead time, 30 ms lag, 0.02 bar quantum, +0.5 kg) and on a
    # 40 ms regulator: alone it oscillates or leaves the bounds; supervised (tuned pid as the
    # fallback) the loop is stable on both and within 1.5× (the no-harm ratio) of the tuned
    # pid alone. The plants and the stiff gains are none the monitor's defaults were set on.
    # The 20 ms loop's limit cycle is caught once the limit-cycle monitor is armed (after two
    # periods); the 40 ms one diverges within the first period (the error monitor).
    sc = _sc(21.0)
    plants = [{"pressure_dead_time_s": 0.02, "pressure_lag_s": 0.03, "extra_mass_kg": 0.5},
              {"pressure_dead_time_s": 0.04, "pressure_lag_s": 0.03, "extra_mass_kg": 1.0}]
    pid = make_baseline("pid", sc)
    stiff = dataclasses.replace(pid, kp_bar_per_m=80.0, ki_bar_per_m_s=3000.0,
                                kd_bar_s_per_m=12.0, tf_s=0.0)
    sup = Supervised(stiff, make_baseline("pid", sc), DT, T, flat())
    alone, supervised, reference = (cell_metrics(r, T, DT) for r in
                                    run_batches([stiff, sup, pid], sc, plants, 7))
    assert all(m["unstable"] for m in alone)
    for s, ref in zip(supervised, reference, strict=True):
        assert not s["unstable"] and not s["terminated"]
        assert s["position_rmse_mm"] <= 1.5 * ref["position_rmse_mm"]
        # in time for the metric window (the last three periods, from 21 − 9 = 12 s)
        assert s["fallback_s"] is not None and s["fallback_s"] < 21.0 - 3 * T
        assert ref["fallback_s"] is None  # an unsupervised controller reports none
    assert ARM_PERIODS * T < supervised[0]["fallback_s"] and supervised[1]["fallback_s"] < T


@pytest.mark.parametrize("name", ["pid", "rc", "mbfb"])
def test_a_baseline_commands_the_same_pressures_in_an_env_of_any_residual_scale(name,
                                                                                 monkeypatch):
    # A supervisor's fallback acts in the learned policy's env (the default config's residual
    # scale is 2 bar); the report's column for the same baseline in the default env (1 bar).
    # Its authority is its own (baselines.AUTHORITY_BAR), so on a plant where it saturates
    # an env of any scale sees the same pressure commands, to the float32 rounding of the
    # action u / scale (exact at 2; 6e-8 bar measured at 1.5 and 3; 1e-6 bar lets the loop
    # carry it over 12 s). With the env's scale as its clip they differed by up to 1 bar (on
    # random rig 22, rc 1.36 mm against 2.62).
    sc = _sc(12.0)
    # random rig 22 rounded: a heavy leg (4.2 + 2.1 kg) behind a slow, slew-limited regulator
    plant = {"mass_kg": 4.2, "extra_mass_kg": 2.1, "pressure_dead_time_s": 0.043,
             "pressure_slew_bar_per_s": 10.0, "braid_friction_ratio": 0.025,
             "slider_friction_N": 1.4}

    def commands(scale):
        task = {"residual_scale_bar": scale}
        job = Job(sc, make_baseline(name, sc, task=task), "MPALegResidual-v0", task,
                  plant=plant, seed=3)
        return run_episodes([job], 3)[0].pressure_cmd_bar

    one = commands(1.0)
    for scale in (1.5, 2.0, 3.0):
        assert np.max(np.abs(commands(scale) - one)) < 1e-6, scale
    # the authority binds on this plant (the check can fail): given 2 bar, the baseline
    # commands other pressures
    monkeypatch.setattr(baselines, "AUTHORITY_BAR", 2.0)
    assert np.max(np.abs(commands(2.0) - one)) > 0.1


def test_supervisor_never_drives_a_healthy_loop_and_changes_nothing_there():
    # The tuned pid under a supervisor (whose fallback would output the full residual) on
    # scenarios a healthy loop meets: a 5 mm initial error, a 30 N impulse, a mass mismatch, a
    # 1.6 kg load with the level kick and the friction grid's corner. The fallback never takes
    # over and every figure is the pid's own, bit for bit.
    scen = ["initial_error", "impulse", "mass_mismatch", "heldout_bladder"]
    pid = make_baseline("pid", "nominal")
    sup = Supervised(pid, Constant(1.0), DT, T, flat())
    rep = evaluate(["pid"], scen)["results"]
    from mpa_gym.agents.evaluation.episodes import Job, metrics, run_episodes

    jobs = [Job(load_scenario(s), sup, "MPALegResidual-v0", {}) for s in scen]
    for s, tr in zip(scen, run_episodes(jobs, 1_000_000), strict=True):
        assert tr.fallback is not None and not tr.fallback.any()
        m = metrics(tr, T, None)
        assert m["fallback_s"] is None
        assert m["position_rmse_mm"] == rep[s]["pid"]["position_rmse_mm"]
    sc = _sc(15.0)
    runs = run_batches([sup], sc, [{"extra_mass_kg": 1.6}, {"braid_friction_ratio": 0.05,
                                                           "slider_friction_N": 3.0,
                                                           "pressure_lag_s": 0.02}], 3)
    assert not runs[0]["fallback"].any()


class Held:
    """A controller that outputs ``held`` (2,) and hides its fallback's ``take_over`` (a cold
    start: the supervisor's behaviour for a fallback without a bumpless transfer)."""

    def __init__(self, inner) -> None:
        self.inner = inner

    def predict(self, *args, **kwargs):
        return self.inner.predict(*args, **kwargs)


@pytest.mark.parametrize("name", ["pid", "mbfb", "rc"])
def test_take_over_continues_the_held_command(name):
    # At exact tracking (e = ė = 0) the P and D terms are zero, so the fallback's first output
    # is what its integrator holds. pid: the antagonistic part of the held residual, exactly
    # (up to float32); rc: the same (its delay line starts empty: no correction yet); mbfb:
    # pressures with the held pressures' ground force (the stiffness is its own, k̂), on the
    # nominal model at the measured state: to 1e-6 N of a ~40 N force.
    env = gym.make("MPALegResidual-v0")
    obs, _ = env.reset(seed=3)
    obs = np.repeat(obs[None], 2, axis=0)
    obs[:, OBS_X] = obs[:, OBS_XREF]
    obs[:, OBS_V], obs[:, OBS_VREF] = 0.0, 0.0  # no error rate
    fb = make_baseline(name, "nominal")
    held = np.array([[0.30, -0.10], [-0.2, 0.05]])
    state = fb.take_over(obs, held, None, np.array([True, True]))
    a, _ = fb.predict(obs, state)
    if name in ("pid", "rc"):
        u = 0.5 * (held[:, 0] - held[:, 1])
        np.testing.assert_allclose(a, np.stack([u, -u], axis=-1), atol=1e-7)
    else:
        scale = fb.cfg.residual_scale_bar * BAR
        c = affine_in_pressures(obs[:, OBS_X], obs[:, OBS_V], fb.params)
        force = [c.F0 + np.einsum("...j,...j->...", c.J[..., 0, :], fb._feedforward(obs)
                                  + r * scale) for r in (held, a)]
        np.testing.assert_allclose(force[1], force[0], atol=1e-6)
        assert not np.allclose(a, held)  # its stiffness is k̂, not the held command's


@pytest.mark.parametrize("name", ["pid", "rc", "afc"])
def test_take_over_in_a_wider_env_starts_at_the_fallbacks_own_authority(name):
    # In a 2-bar env (a learned run's) the policy may hold ±1.8 bar; the fallback may command
    # ±1 bar (AUTHORITY_BAR). It continues the part it can make: its integrator holds 1 bar,
    # not 1.8, so one step of error of the other sign moves its output off the clip at once
    # (a wound-up integrator would hold it there for 0.8 bar / Ki of ∫e). At exact tracking
    # the first output is the clip, ±0.5 in the env's units.
    task = {"residual_scale_bar": 2.0}
    env = gym.make("MPALegResidual-v0", task=task)
    obs, _ = env.reset(seed=3)
    obs = obs[None].copy()
    obs[:, OBS_X] = obs[:, OBS_XREF]
    obs[:, OBS_V], obs[:, OBS_VREF] = 0.0, 0.0
    fb = make_baseline(name, "nominal", task=task)
    held = np.array([[0.9, -0.9]])
    history = np.repeat(held[:, :, None], 300, axis=-1) if name == "afc" else None
    state = fb.take_over(obs, held, None, np.array([True]), history=history)
    if name == "afc":  # no proportional path (its output moves over periods): θ₀ is 1 bar
        assert np.asarray(state)[0, 0] == pytest.approx(1.0)
    a, state = fb.predict(obs, state)
    np.testing.assert_allclose(a, [[0.5, -0.5]], atol=1e-7)
    if name != "afc":
        obs[:, OBS_X] = obs[:, OBS_XREF] + 1e-3  # 1 mm above the reference
        a, _ = fb.predict(obs, state)
        assert a[0, 0] < 0.5 - 1e-3


def test_bumpless_transfer_keeps_carrying_the_load():
    # pid carrying 1.6 kg (its integrator holds the load) hands over to a second pid when a
    # hair-trigger limit-cycle level (0.01 mm) trips at the monitor's arming (quantised
    # pressures make every loop a little aperiodic). Started from the period mean of the
    # command the first one held, the second one continues the loop: its largest |e| after
    # the switch is within 1 mm (the recovery band, docs/design.md#targets) of pid's alone.
    # From zero state it drops the load: over 5 mm, on a plain regulator and on 20 ms of dead
    # time + 30 ms lag.
    sc = _sc(15.0)
    pid = make_baseline("pid", sc)
    spec = flat(aperiodic_mm=0.01)
    plants = [{"extra_mass_kg": 1.6},
              {"extra_mass_kg": 1.6, "pressure_dead_time_s": 0.02, "pressure_lag_s": 0.03}]
    alone, bumpless, cold = run_batches(
        [pid, Supervised(pid, pid, DT, T, spec), Supervised(pid, Held(pid), DT, T, spec)],
        sc, plants, 3)
    switch = np.argmax(bumpless["fallback"], axis=0)  # per plant, the first fallback step
    np.testing.assert_array_equal(np.argmax(cold["fallback"], axis=0), switch)
    assert np.all((switch >= ARM_PERIODS * T / DT) & (switch < (ARM_PERIODS * T + 1.5) / DT))
    for j, k in enumerate(switch):
        worst = [np.abs(r["x_ref"] - r["x"])[k:, j].max() for r in (alone, bumpless, cold)]
        assert worst[1] <= worst[0] + 1e-3, (j, worst)
        assert worst[2] > 5e-3, (j, worst)


def test_afc_take_over_continues_the_policys_periodic_command():
    # The policy's antagonistic command over the last period is a mean and a first harmonic
    # u = c0 + cs sin(phase) + cc cos(phase), plus a common part that afc has no place for. At
    # exact tracking (e = 0: no adaptation this step) afc's first output after the take-over is
    # that command continued at this step's phase, to float32; a row younger than a period
    # (NaN in its history) starts from the mean alone.
    env = gym.make("MPALegResidual-v0")
    obs, _ = env.reset(seed=5)
    for _ in range(37):  # somewhere inside a period
        obs, *_ = env.step(np.zeros(2, dtype=np.float32))
    obs = np.repeat(obs[None], 2, axis=0)
    obs[:, OBS_X], obs[:, OBS_V] = obs[:, OBS_XREF], obs[:, OBS_VREF]
    afc = make_baseline("afc", "nominal")
    scale, n = afc.cfg.residual_scale_bar, round(T / DT)
    now = np.arctan2(obs[0, OBS_SIN], obs[0, OBS_COS])
    phase = now - 2 * np.pi * np.arange(n - 1, -1, -1) / n  # the oldest first
    c0, cs, cc = 0.21, -0.13, 0.08  # [bar]
    u = c0 + cs * np.sin(phase) + cc * np.cos(phase)
    common = 0.05 * np.cos(3 * phase)
    one = np.stack([(u + common) / scale, (-u + common) / scale])  # (2, N)
    history = np.stack([one, one])
    history[1, :, :10] = np.nan  # row 1: the episode is younger than a period
    held = np.nanmean(history, axis=-1)
    state = afc.take_over(obs, held, None, np.array([True, True]), history=history)
    a, _ = afc.predict(obs, state)
    want = c0 + cs * np.sin(now) + cc * np.cos(now)
    np.testing.assert_allclose(a[0], [want / scale, -want / scale], atol=1e-7)
    mean = 0.5 * (held[1, 0] - held[1, 1])
    np.testing.assert_allclose(a[1], [mean, -mean], atol=1e-7)


def test_afc_takes_over_a_load_bumplessly():
    # rc carrying 1.6 kg (with and without 20 ms dead time + 30 ms lag) hands over to afc when
    # a hair-trigger limit-cycle level (0.01 mm) trips at its arming. Started from the mean
    # and first harmonic of rc's command over the last period, afc continues the loop: its
    # largest |e| after the switch is within 1 mm (the recovery band) of rc's alone over the
    # same span. From rest (afc alone adapts from zero over two periods) it drops the load:
    # over 20 mm.
    sc = _sc(12.0)
    rc, afc = make_baseline("rc", sc), make_baseline("afc", sc)
    spec = SupervisorSpec.from_config({
        "monitors": {"limit_cycle": {"level_mm": 0.01, "window_s": 3.0, "clip_mm": None,
                                     "arm_periods": ARM_PERIODS}},
        "stages": [{"controller": "policy", "monitors": ["limit_cycle"]},
                   {"controller": "afc"}]})
    plants = [{"extra_mass_kg": 1.6},
              {"extra_mass_kg": 1.6, "pressure_dead_time_s": 0.02, "pressure_lag_s": 0.03}]
    alone, warm, cold = run_batches(
        [rc, Supervised(rc, afc, DT, T, spec), Supervised(rc, Held(afc), DT, T, spec)],
        sc, plants, 3)
    switch = np.argmax(warm["fallback"], axis=0)
    np.testing.assert_array_equal(np.argmax(cold["fallback"], axis=0), switch)
    assert np.all((switch >= ARM_PERIODS * T / DT) & (switch < (ARM_PERIODS * T + 1.5) / DT))
    for j, k in enumerate(switch):
        worst = [np.abs(r["x_ref"] - r["x"])[k:, j].max() for r in (alone, warm, cold)]
        assert worst[1] <= worst[0] + 1e-3, (j, worst)
        assert worst[2] > 20e-3, (j, worst)


def test_took_over_is_none_for_an_unsupervised_controller():
    assert took_over(make_baseline("pid", "nominal"), None) is None
    sup = Supervised(Constant(0.0), Constant(1.0), DT, T, flat())
    a, state = sup.predict(np.zeros(N_OBS))  # one observation in, one action out
    assert a.shape == (2,) and not took_over(sup, state)[0]


def _config(tmp_path, supervisor):
    cfg = yaml.safe_load(open("configs/ppo_residual.yaml"))
    cfg["mpa_gym"]["supervisor"] = supervisor
    return parse_config(cfg, "cfg.yaml")


@pytest.mark.parametrize("bad, match", [
    ({"fallback": "ff"},
     r"mpa_gym\.supervisor\.fallback='ff': allowed \['pid', 'mbfb', 'rc'\]"),
    ({"trip": 3.0}, r"mpa_gym\.supervisor: unknown key\(s\) \['trip'\]; allowed keys"),
    ({"last_resort": "pid"},
     r"mpa_gym\.supervisor\.last_resort='pid': allowed null or \['ff', 'afc'\]"),
    ({"aperiodic_mm": -1.0},
     r"mpa_gym\.supervisor\.aperiodic_mm=-1 mm is outside the allowed range \(0, 100\] mm"),
    ({"error_window_s": "1s"}, r"mpa_gym\.supervisor\.error_window_s='1s' is not a number"),
    ("pid", r"mpa_gym\.supervisor='pid' must be a mapping"),
])
def test_config_names_the_bad_supervisor_field(tmp_path, bad, match):
    with pytest.raises(ConfigError, match=match):
        _config(tmp_path, bad)


def test_config_supervisor_defaults_and_round_trip(tmp_path):
    cfg = _config(tmp_path, {"fallback": "mbfb", "aperiodic_mm": 2.5})
    # a flat section: the policy judged on divergence and limit cycle, the fallback to the end,
    # the policy always starting (runs written in that form were evaluated so)
    assert cfg.supervisor == SupervisorSpec(
        (Divergence(15.0, 0.5, None, 0), LimitCycle(2.5, 3.0, None, ARM_PERIODS)),
        (Stage("policy", ("divergence", "limit_cycle")), Stage("mbfb")), select=None)
    assert cfg.supervisor.last_resort is None  # off unless asked for
    assert "ff alone" in _config(tmp_path, {"last_resort": "ff"}).supervisor.describe()
    assert "adaptive feedforward" in _config(tmp_path, {"last_resort": "afc"}).supervisor.describe()
    assert "mbfb takes over" in cfg.supervisor.describe()
    assert _config(tmp_path, None).supervisor is None


DEFAULT_STAGES_CFG = [{"controller": "policy", "monitors": ["divergence", "limit_cycle"]},
                      {"controller": "pid", "monitors": ["divergence"], "grace_periods": 1},
                      {"controller": "afc"}]


@pytest.mark.parametrize("bad, match", [
    ({"monitors": {"divergence": {"level_mm": 0}}},
     r"supervisor\.monitors\.divergence\.level_mm=0 mm is outside the allowed range "
     r"\(0, 100\] mm"),
    ({"monitors": {"persistent": {"window_s": 45}}},
     r"supervisor\.monitors\.persistent\.window_s=45 s is outside the allowed range "
     r"\(0, 30\] s"),
    ({"monitors": {"limit_cycle": {"clip_mm": 0.3}}},  # at or under its level: never trips
     r"supervisor\.monitors\.limit_cycle\.clip_mm=0\.3 mm is outside the allowed range "
     rf"\({re.escape(f'{LimitCycle().level_mm:g}')}, 100\] mm"),  # the default level
    ({"monitors": {"limit_cycle": {"arm_periods": 1.5}}},
     r"supervisor\.monitors\.limit_cycle\.arm_periods=1\.5 must be a whole number of "
     r"reference periods in \[0, 100\]"),
    ({"monitors": {"wobble": {}}},
     r"supervisor\.monitors: unknown key\(s\) \['wobble'\]; allowed keys are "
     r"\['divergence', 'limit_cycle', 'persistent'\]"),
    ({"monitors": {"divergence": {"level": 3}}},
     r"supervisor\.monitors\.divergence: unknown key\(s\) \['level'\]; allowed keys are "
     r"\['arm_periods', 'clip_mm', 'level_mm', 'window_s'\]"),
    ({"stages": [{"controller": "pid", "monitors": ["divergence"]}, {"controller": "ff"}]},
     r"supervisor\.stages\[0\]\.controller='pid': allowed \['policy'\]"),
    # a later stage names any baseline (mpa-gym calibrate orders them by measurement)
    ({"stages": [DEFAULT_STAGES_CFG[0], {"controller": "policy"}]},
     r"supervisor\.stages\[1\]\.controller='policy': allowed \['ff', 'pid', 'mbfb', 'afc', "
     r"'rc'\]"),
    ({"stages": [*DEFAULT_STAGES_CFG[:2], {"controller": "nosuch"}]},
     r"supervisor\.stages\[2\]\.controller='nosuch': allowed \['ff', 'pid', 'mbfb', 'afc', "
     r"'rc'\]"),
    ({"stages": [{"controller": "policy", "monitors": ["drift"]}, {"controller": "pid"}]},
     r"supervisor\.stages\[0\]\.monitors=\['drift'\]: allowed distinct names of "
     r"supervisor\.monitors \['divergence', 'limit_cycle', 'persistent'\]"),
    ({"stages": [{"controller": "policy"}, {"controller": "pid"}]},
     r"supervisor\.stages\[0\]\.monitors=\[\]: every stage but the last needs a monitor"),
    ({"stages": [DEFAULT_STAGES_CFG[0], {"controller": "pid", "monitors": ["divergence"]}]},
     r"supervisor\.stages\[1\]\.monitors=\['divergence'\]: the last stage drives to the end"),
    ({"stages": [*DEFAULT_STAGES_CFG[:1],
                 {"controller": "pid", "monitors": ["divergence"], "grace_periods": -1},
                 DEFAULT_STAGES_CFG[2]]},
     r"supervisor\.stages\[1\]\.grace_periods=-1 is outside the allowed range \[0, 100\]"),
    ({"stages": [DEFAULT_STAGES_CFG[0]]},
     r"supervisor\.stages has 1 stage\(s\): allowed 2 \(the policy, a fallback\) or 3"),
    ({"stages": DEFAULT_STAGES_CFG, "fallback": "pid"},
     r"supervisor: unknown key\(s\) \['fallback'\]; allowed keys are "
     r"\['gains', 'monitors', 'select', 'stages'\]"),
    ({"stages": DEFAULT_STAGES_CFG, "select": {"ratio": 0.5}},
     r"supervisor\.select\.ratio=0\.5 is outside the allowed range \[1, 10\]"),
    ({"stages": DEFAULT_STAGES_CFG, "select": {"stiffness_ratio": 0.5}},
     r"supervisor\.select\.stiffness_ratio=0\.5 is outside the allowed range \[1, 10\]"),
    ({"stages": DEFAULT_STAGES_CFG, "select": {"margin": 1.5}},
     r"supervisor\.select: unknown key\(s\) \['margin'\]; allowed keys are \['ratio', "
     r"'stiffness_ratio'\]"),
    ({"stages": DEFAULT_STAGES_CFG, "select": 1.5},
     r"supervisor\.select=1\.5 must be null or a mapping with keys among "
     r"\['ratio', 'stiffness_ratio'\]"),
])
def test_config_names_the_bad_field_of_a_declared_supervisor(tmp_path, bad, match):
    with pytest.raises(ConfigError, match=r"mpa_gym\." + match):
        _config(tmp_path, bad)


def test_config_declared_supervisor_states_only_what_differs(tmp_path):
    # A monitor's omitted fields, the omitted monitors and the omitted stages are the
    # defaults (SupervisorSpec's, the default config's); the spec keeps the monitors its
    # stages name. Its describe() says who takes over on what.
    cfg = _config(tmp_path, {"monitors": {"limit_cycle": {"level_mm": 0.6, "clip_mm": 0.8}},
                             "stages": DEFAULT_STAGES_CFG})
    assert cfg.supervisor == SupervisorSpec(
        (Divergence(), LimitCycle(level_mm=0.6, clip_mm=0.8)),
        (Stage("policy", ("divergence", "limit_cycle")), Stage("pid", ("divergence",), 1),
         Stage("afc")))
    assert cfg.supervisor.fallback == "pid" and cfg.supervisor.last_resort == "afc"
    text = cfg.supervisor.describe()
    assert text.startswith("pid takes over once the error's RMS over 0.5 s exceeds "
                           f"{Divergence().level_mm:g} mm or ")
    assert "exceeds 0.6 mm after the stage's first 2 periods" in text
    assert "in pid's loop (given 1 period(s) to settle)" in text
    assert text.endswith("; the loop starts at the stage predicted best on the model (each "
                         "stage's controller alone), the policy unless another is predicted "
                         "over 1.1x better (position figures below 0.05 mm alike)")
    two = _config(tmp_path, {"stages": [DEFAULT_STAGES_CFG[0], {"controller": "mbfb"}]})
    assert two.supervisor.last_resort is None and two.supervisor.fallback == "mbfb"
    # the start chosen on the model: the default's ratio, another, or never (null)
    # (on position alone: stiffness_ratio's default is null)
    assert two.supervisor.select == Selection(1.1, None)
    assert _config(tmp_path, {"stages": DEFAULT_STAGES_CFG, "select": {"ratio": 1.5}}
                   ).supervisor.select == Selection(1.5, None)
    alone = _config(tmp_path, {"stages": DEFAULT_STAGES_CFG,
                               "select": {"stiffness_ratio": None}}).supervisor.select
    assert alone == Selection(1.1, None) and "stiffness" not in alone.describe()
    both = _config(tmp_path, {"stages": DEFAULT_STAGES_CFG,
                              "select": {"stiffness_ratio": 1.1}}).supervisor.select
    assert both == Selection(1.1, 1.1) and "no more than 1.1x worse on stiffness" in \
        both.describe()
    off = _config(tmp_path, {"stages": DEFAULT_STAGES_CFG, "select": None}).supervisor
    assert off.select is None and "predicted" not in off.describe()


@REALTIME
def test_a_supervised_run_on_the_rig_logs_when_its_fallback_takes_over(tmp_path):
    # A run whose config asks for a supervisor with a hair trigger (0.05 mm of error RMS) and
    # afc as the last resort, rolled out on the device emulator (its own thread, real time)
    # playing a rig the run was not trained on: 20 ms regulator dead time, 30 ms lag and an
    # unmodelled 0.5 kg load (its sag is ~10 mm under the feedforward; pid holds it to
    # ~0.4 mm, over the trigger). The deployed policy comes supervised; the log has one
    # "fallback" event naming the supervisor and, one grace period later, one "last_resort"
    # event; each step's stage says who drove it, and the episode's metrics say when.
    def hair_trigger(cfg):
        cfg["mpa_gym"]["supervisor"] = {"fallback": "pid", "error_mm": 0.05,
                                        "last_resort": "afc"}

    path = tiny_config(tmp_path, hair_trigger, n_envs=2, n_timesteps=64, n_steps=32,
                       batch_size=64, n_epochs=1)
    run = train(path, tmp_path / "run", progress=False)
    rig = {"name": "slow_rig", "duration_s": 4.5, "plant": {
        "pressure_dead_time_s": 0.02, "pressure_lag_s": 0.03, "extra_mass_kg": 0.5}}
    log = tmp_path / "r.jsonl"
    with serving(scenario=rig) as (url, _):
        out = rollout(str(run), url, log, episode_s=4.5)
    records = read_log(log)
    events = [r for r in records if r.get("event") in ("fallback", "last_resort")]
    steps = [r for r in records if "reward" in r]  # the steps (not the events)
    assert [e["event"] for e in events] == ["fallback", "last_resort"]
    assert events[0]["supervisor"].startswith("pid takes over")
    stage = np.array([r["fallback"] for r in steps])
    first, last = int(np.argmax(stage >= 1)), int(np.argmax(stage >= 2))
    assert first < last and np.all(stage[:first] == 0)  # (a hair trigger may trip at once)
    assert np.all(stage[first:last] == 1) and np.all(stage[last:] == 2)  # the latches hold
    assert last - first >= round(GRACE_PERIODS * T / DT)  # pid's loop judged after its grace
    assert [e["t_s"] for e in events] == [steps[first]["t_s"], steps[last]["t_s"]]
    assert out["episodes"][0]["fallback_s"] == steps[first]["t_s"]
    assert out["episodes"][0]["last_resort_s"] == steps[last]["t_s"]
    # the summary says who drove: the policy its first steps only
    assert out["stages"] == ["policy", "pid", "afc"]
    assert out["episodes"][0]["policy_share"] == pytest.approx(first / len(steps), abs=1e-12)
    said = (f"pid from {steps[first]['t_s']:.1f} s, afc from {steps[last]['t_s']:.1f} s; "
            f"policy {100 * first / len(steps):.0f} % of steps")
    assert out["episodes"][0]["hand_overs"] == said
    assert f"hand-over: {said}" in show_rollout(out)


# --- today's flat sections keep their numbers ---------------------------------------------

class Wobbly:
    """A stateless stand-in for a learned residual whose action depends on the observation (so
    that the command the fallback takes over, the mean of the policy's last period, matters)."""

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        obs = np.atleast_2d(observation)
        e = obs[:, OBS_XREF] - obs[:, OBS_X]
        a = np.stack([0.3 * np.tanh(e / 0.004), -0.2 * np.tanh(e / 0.009) + 0.05 * obs[:, OBS_SIN]],
                     axis=-1).astype(np.float32)
        return (a[0] if np.ndim(observation) == 1 else a), state


def _stream(seed: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(observations (steps, 5, N_OBS), episode starts (steps, 5)): five rows of a synthetic loop
    on the default reference: a growing oscillation at 1.7 Hz, a 25 mm kick at 7 s decaying with
    0.15 s on a 1 mm periodic error, a sag of 2.6 mm with noise, a ramp that diverges from 4 s,
    and a 2.5 mm periodic error whose row starts a new episode at 6 s and 11 s."""
    rng = np.random.default_rng(seed)
    t = DT * np.arange(n_steps)
    wave = np.sin(2 * np.pi * t / T)
    kick = np.where(t >= 7.0, 0.025 * np.exp(-np.clip(t - 7.0, 0.0, None) / 0.15), 0.0)
    e = np.stack([1e-4 * np.exp(t / 2.0).clip(max=300.0) * np.sin(2 * np.pi * 1.7 * t),
                  0.001 * wave + kick,
                  0.0026 + 0.0004 * rng.standard_normal(n_steps),
                  np.where(t >= 4.0, 0.01 * (t - 4.0) ** 2, 0.0) + 0.0002 * wave,
                  0.0025 * wave + 0.0003 * rng.standard_normal(n_steps)], axis=1)
    obs = np.zeros((n_steps, e.shape[1], N_OBS))
    phase = 2 * np.pi * (t / T)[:, None]
    obs[..., OBS_XREF] = 0.8 + 0.02 * np.sin(phase)
    obs[..., OBS_X] = obs[..., OBS_XREF] - e
    obs[..., OBS_VREF] = 0.02 * 2 * np.pi / T * np.cos(phase)
    obs[..., OBS_V] = obs[..., OBS_VREF] - np.gradient(e, DT, axis=0)
    obs[..., OBS_SIN], obs[..., OBS_COS] = np.sin(phase), np.cos(phase)
    obs[..., OBS_KREF] = 545.0 / OBS_KREF_SCALE
    start = np.zeros((n_steps, e.shape[1]), dtype=bool)
    start[0] = True
    start[[600, 1100], 4] = True
    return obs, start


# the default config's section before the cascade was declared (configs/ppo_residual.yaml at
# d227f9f), which the run folders trained on it hold
DEFAULT_FLAT = {"fallback": "pid", "aperiodic_mm": 0.4, "aperiodic_clip_mm": 0.5,
                "persistent_mm": 2.0, "persistent_clip_mm": 3.0, "last_resort": "afc"}
FLAT_SECTIONS = [
    DEFAULT_FLAT,
    {},
    {"fallback": "mbfb", "aperiodic_mm": 2.5},
    {"fallback": "pid", "error_mm": 0.05, "last_resort": "afc"},
    {"error_mm": 8.0, "error_window_s": 0.3, "aperiodic_mm": 1.0, "aperiodic_window_s": 2.0,
     "aperiodic_clip_mm": 1.5, "persistent_mm": 2.0, "last_resort": "ff"},
    {"fallback": "mbfb", "persistent_mm": 2.2, "persistent_clip_mm": 2.5, "last_resort": "afc"},
]


@pytest.mark.parametrize("section", FLAT_SECTIONS, ids=range(len(FLAT_SECTIONS)))
def test_a_flat_section_drives_exactly_as_before(section):
    # A run folder written before the cascade was declared holds its supervisor as flat keys
    # (config.yaml keeps the file's content). Read by SupervisorSpec.from_config and run by
    # Supervised on a fixed observation stream the code did not produce (_stream), it gives
    # the stages and actions of the supervisor of that time (RefSupervised below, a verbatim
    # copy), bit for bit: same float64 running means, same comparisons, same controllers
    # called with the same states. Batched rows (with mid-stream episode starts) and a single
    # observation at a time (the rig's path).
    obs, start = _stream(7, round(5 * T / DT))
    flat = dict(section)
    old_spec = RefSupervisorSpec(**flat)
    new_spec = SupervisorSpec.from_config(flat)
    assert new_spec.fallback == old_spec.fallback
    assert new_spec.last_resort == old_spec.last_resort

    def build(cls, spec):
        last = None if spec.last_resort is None else make_baseline(spec.last_resort)
        return cls(Wobbly(), make_baseline(spec.fallback), DT, T, spec, last)

    old, new = build(RefSupervised, old_spec), build(Supervised, new_spec)
    reached = set()
    for rows in (slice(None), 3):  # the batch, then row 3 alone, one observation at a time
        s_old = s_new = None
        for k in range(obs.shape[0]):
            o, st = obs[k, rows], start[k, rows]
            a_old, s_old = old.predict(o, s_old, np.atleast_1d(st))
            a_new, s_new = new.predict(o, s_new, np.atleast_1d(st))
            assert a_new.dtype == a_old.dtype and a_new.shape == a_old.shape, k
            np.testing.assert_array_equal(a_new, a_old, err_msg=f"step {k}")
            np.testing.assert_array_equal(took_over(new, s_new), RefSupervised.stage(s_old),
                                          err_msg=f"step {k}")
            reached |= set(RefSupervised.stage(s_old).tolist())
    # the stream exercises the cascade as far as the section goes
    assert reached == ({0, 1, 2} if old_spec.last_resort else {0, 1})


def test_the_default_config_declares_the_dataclass_defaults():
    # Each default written once: the declared section of configs/ppo_residual.yaml is
    # SupervisorSpec() (a change to either fails here). The former flat section is a cascade of
    # its own (the levels chosen on the sweep, pid first), whose numbers are pinned to the old
    # code by test_a_flat_section_drives_exactly_as_before.
    section = yaml.safe_load(open("configs/ppo_residual.yaml"))["mpa_gym"]["supervisor"]
    assert set(section) == {"monitors", "stages", "select"}
    assert SupervisorSpec.from_config(section) == SupervisorSpec()
    assert SupervisorSpec.from_config({"stages": section["stages"]}) == SupervisorSpec()
    assert SupervisorSpec.from_config(DEFAULT_FLAT).fallback == "pid"


# --- each monitor, and the cascade, against trip times derived by hand ----------------------
#
# A monitor's running mean z_j = z_{j-1} + α (s² − z_{j-1}), α = dt / (window + dt), from z = 0
# under a constant |s| = S is S² (1 − (1 − α)^j) after its j-th armed step: it first exceeds
# level L at the j* = ⌊x⌋ + 1-th, x = ln(1 − L²/S²) / ln(1 − α). The tests assert that step
# exactly: the signals are exact in floating point (a constant, a square wave, a sequence
# repeated every N steps) and x is kept 5 % of a step or more from a whole number, far beyond
# the ~1e-13 relative error the recursion accumulates over a few hundred steps.


def _stages(spec, errors, last=None):
    """(steps, rows) the stage of each row at each step, under stand-in controllers, for
    observations with X̂ − X = errors[k, row]."""
    sup = Supervised(Constant(0.0), Constant(1.0), DT, T, spec, last)
    state, out = None, []
    for k, e in enumerate(errors):
        obs = np.zeros((errors.shape[1], N_OBS))
        obs[:, OBS_XREF], obs[:, OBS_X] = 0.8 + e, 0.8
        _, state = sup.predict(obs, state, np.full(errors.shape[1], k == 0))
        out.append(took_over(sup, state))
    return np.array(out)


def _first(stages, stage=1):
    """Per row, the first step at ``stage`` or beyond (None: never)."""
    return [int(np.argmax(c >= stage)) if (c >= stage).any() else None for c in stages.T]


def _trip_step(first_armed, level_mm, s_mm, window_s):
    """The step at which a monitor armed at ``first_armed`` with z = 0 and |s| = s_mm trips."""
    x = np.log(1 - (level_mm / s_mm) ** 2) / np.log(1 - DT / (window_s + DT))
    assert 0.05 < x % 1 < 0.95, x  # clear of a rounding tie
    return first_armed + int(np.floor(x))


def _policy_judged_by(*monitors):
    return SupervisorSpec(monitors, (Stage("policy", tuple(m.name for m in monitors)),
                                     Stage("pid")))


N_PER = round(T / DT)  # steps per reference period


def test_divergence_monitor_trips_at_the_derived_step_from_the_start():
    # Divergence(8 mm, 0.4 s): a 10 mm step at step 100 (1 s, before any arming: the
    # divergence monitor is armed from the start); the same step with each sample clipped to
    # ±9 mm (a later trip, at S = 9 mm); a 7.9 mm step, under the level, which never trips
    # (z stays a convex combination of 0 and (7.9 mm)²).
    steps = 400
    k = np.arange(steps)[:, None]
    errors = np.where(k >= 100, np.array([0.010, 0.0079]), 0.0)
    got = _first(_stages(_policy_judged_by(Divergence(8.0, 0.4)), errors))
    assert got == [_trip_step(100, 8.0, 10.0, 0.4), None]
    clipped = _first(_stages(_policy_judged_by(Divergence(8.0, 0.4, clip_mm=9.0)), errors))
    assert clipped == [_trip_step(100, 8.0, 9.0, 0.4), None]
    assert got[0] < clipped[0] < 2 * N_PER


def test_limit_cycle_monitor_trips_on_a_non_reference_oscillation_from_its_arming():
    # LimitCycle(1.5 mm, 2 s, armed after 2 periods). Row 0: a ±1 mm square wave with a 1 s
    # half-period, 1.5 cycles per reference period, so e_t − e_{t−T} = 2 e_t: |s| = 2 mm
    # exactly from the second period on; the monitor accumulates from step 2N (its arming),
    # so it trips at the derived step. Row 1: a 10 mm error that repeats every N steps
    # exactly (a sag and a lag): its change over a period is zero and it never trips, though
    # its RMS is five times the level. With each sample clipped to ±1.8 mm row 0 trips later,
    # at S = 1.8 mm.
    steps = 3 * N_PER + 300
    k = np.arange(steps)
    square = 0.001 * np.where((k // 100) % 2 == 0, 1.0, -1.0)
    periodic = 0.010 * np.sin(2 * np.pi * (k % N_PER) / N_PER)
    errors = np.stack([square, periodic], axis=1)
    armed = ARM_PERIODS * N_PER
    got = _first(_stages(_policy_judged_by(LimitCycle(1.5, 2.0, None)), errors))
    assert got == [_trip_step(armed, 1.5, 2.0, 2.0), None]
    clipped = _first(_stages(_policy_judged_by(LimitCycle(1.5, 2.0, 1.8)), errors))
    assert clipped == [_trip_step(armed, 1.5, 1.8, 2.0), None]


def test_persistent_monitor_trips_on_a_sag_with_its_own_window():
    # Persistent(2 mm, 5 s, clip 3 mm, armed after 2 periods) beside a LimitCycle(1.5 mm, 2 s):
    # each on its own window. Row 0: a 2.5 mm sag (a constant error: its change over a period
    # is zero, so the limit cycle never sees it), tripping the persistent monitor at the step
    # derived with 5 s. Row 1: a 4 mm sag, clipped to 3 mm: earlier, at S = 3 mm. Row 2: a
    # 1.9 mm sag, under the level: never. Row 3: the ±1 mm square wave of the limit-cycle test
    # (|e| = 1 mm, under the persistent level): the limit cycle trips it at its own 2 s step.
    steps = 4 * N_PER
    k = np.arange(steps)
    square = 0.001 * np.where((k // 100) % 2 == 0, 1.0, -1.0)
    errors = np.stack([np.full(steps, 0.0025), np.full(steps, 0.004), np.full(steps, 0.0019),
                       square], axis=1)
    armed = ARM_PERIODS * N_PER
    spec = _policy_judged_by(Persistent(2.0, 5.0, 3.0), LimitCycle(1.5, 2.0, None))
    assert _first(_stages(spec, errors)) == [_trip_step(armed, 2.0, 2.5, 5.0),
                                             _trip_step(armed, 2.0, 3.0, 5.0), None,
                                             _trip_step(armed, 1.5, 2.0, 2.0)]


def test_cascade_hands_to_the_fallback_then_the_last_resort_after_its_grace():
    # Policy judged by Divergence(8 mm, 0.4 s); pid by Persistent(2 mm, 5 s, armed at once)
    # after one period of grace; then ff. Every row: a 10 mm step at step 100, so divergence
    # hands all rows to pid at step i1 (derived). There the monitors restart from zero and
    # the error becomes, row 0, 10 mm: the persistent monitor passes 2 mm within 21 steps, but
    # pid's loop is judged only from i1 + 1 + N (its grace), where it trips; row 1, 2.5 mm:
    # from zero the mean takes 512 steps to pass (2 mm)² (after the grace), the step derived;
    # without the restart the ~8 mm² the 10 mm step had put into the mean would trip it at the
    # end of the grace; row 2, 1 mm: pid holds, no last resort. The latches hold; the output
    # is each stage's controller's (policy 0.0, pid 1.0, ff's zero residual).
    steps = 3 * N_PER
    k = np.arange(steps)[:, None]
    i1 = _trip_step(100, 8.0, 10.0, 0.4)
    after = np.array([0.010, 0.0025, 0.001])
    errors = np.where(k > i1, after, np.where(k >= 100, 0.010, 0.0))
    spec = SupervisorSpec((Divergence(8.0, 0.4), Persistent(2.0, 5.0, None, 0)),
                          (Stage("policy", ("divergence",)),
                           Stage("pid", ("persistent",), grace_periods=1), Stage("ff")))
    stages = _stages(spec, errors, make_baseline("ff"))
    assert _first(stages, 1) == [i1] * 3
    since = i1 + 1  # the fallback's first step, from which its monitors and grace count
    assert _first(stages, 2) == [since + N_PER, _trip_step(since, 2.0, 2.5, 5.0), None]
    for c in stages.T:
        assert np.all(np.diff(c) >= 0)  # a latch: never back
    sup = Supervised(Constant(0.5), Constant(1.0), DT, T, spec, make_baseline("ff"))
    state = None
    for j, e in enumerate(errors):
        obs = np.zeros((3, N_OBS))
        obs[:, OBS_XREF], obs[:, OBS_X] = 0.8 + e, 0.8
        a, state = sup.predict(obs, state, np.full(3, j == 0))
        np.testing.assert_array_equal(a[:, 0], np.array([0.5, 1.0, 0.0])[stages[j]])


# --- the reference: agents/controllers/supervisor.py as of d227f9f, before the cascade was
# declared ---
# Copied verbatim (its names prefixed Ref / REF_, the contract columns aliased) so that the
# equivalence test needs nothing outside this repository. Do not edit: it is the yardstick.
OX, OXR = OBS_X, OBS_XREF

REF_FALLBACKS = ("pid", "mbfb")
# the last resorts (mpa_gym.agents.controllers.baselines names) and what ``describe`` calls them
REF_LAST_RESORTS = {"ff": "ff alone",
                "afc": "afc (the feedforward with adaptive feedforward cancellation)"}
REF_ARM_PERIODS = 2  # periods left out of the limit-cycle monitor (module docstring)
REF_GRACE_PERIODS = 1  # periods the fallback's loop has to settle before it is judged
REF_POLICY, REF_FALLBACK, REF_LAST_RESORT = 0, 1, 2  # the stages: who drives
# the monitor's columns per row (``RefSupervised``): the two running means, the stage, the steps
# taken, the step the stage began; then the ring buffers
REF_M_ERR, REF_M_AP, REF_M_STAGE, REF_M_STEP, REF_M_SINCE, REF_M_PER = range(6)
REF_M_RING = 6


@dataclass(frozen=True)
class RefSupervisorSpec:
    """A run config's ``mpa_gym.supervisor`` (its keys; module docstring)."""

    fallback: str = "pid"  # the baseline that takes over
    error_mm: float = 15.0  # [mm] running RMS of X̂ − X above which it takes over
    error_window_s: float = 0.5  # [s] time constant of that running mean
    aperiodic_mm: float = 3.0  # [mm] running RMS of e_t − e_{t−T} above which it takes over
    aperiodic_window_s: float = 3.0  # [s] time constant of that running mean
    aperiodic_clip_mm: float | None = None  # [mm] e_t − e_{t−T} clipped to ± this (None: not)
    # [mm] running RMS (over aperiodic_window_s, from the third period on) of e itself, each
    # sample clipped to ±persistent_clip_mm, above which it takes over (None: not watched)
    persistent_mm: float | None = None
    persistent_clip_mm: float | None = None  # [mm] (None: not clipped)
    # once the fallback trips too: "ff", the feedforward alone; "afc", with adaptive
    # feedforward cancellation (mpa_gym.agents.controllers.baselines.AdaptiveFeedforward)
    last_resort: str | None = None

    def __post_init__(self) -> None:
        if self.fallback not in REF_FALLBACKS:
            raise ValueError(f"supervisor.fallback={self.fallback!r}: "
                             f"allowed {list(REF_FALLBACKS)}")
        if self.last_resort is not None and self.last_resort not in REF_LAST_RESORTS:
            raise ValueError(f"supervisor.last_resort={self.last_resort!r}: allowed null or "
                             f"{list(REF_LAST_RESORTS)}")
        for key, hi, unit in (("error_mm", 100.0, "mm"), ("error_window_s", 30.0, "s"),
                              ("aperiodic_mm", 100.0, "mm"), ("aperiodic_window_s", 30.0, "s")):
            check_range(f"supervisor.{key}", getattr(self, key), 0.0, hi, low_open=True,
                        unit=unit)
        if self.aperiodic_clip_mm is not None:  # below the level, the monitor could never trip
            check_range("supervisor.aperiodic_clip_mm", self.aperiodic_clip_mm,
                        self.aperiodic_mm, 100.0, low_open=True, unit="mm")
        if self.persistent_mm is not None:
            check_range("supervisor.persistent_mm", self.persistent_mm, 0.0, 100.0,
                        low_open=True, unit="mm")
        if self.persistent_clip_mm is not None:
            if self.persistent_mm is None:
                raise ValueError(f"supervisor.persistent_clip_mm={self.persistent_clip_mm!r} "
                                 "needs supervisor.persistent_mm")
            check_range("supervisor.persistent_clip_mm", self.persistent_clip_mm,
                        self.persistent_mm, 100.0, low_open=True, unit="mm")

    @classmethod
    def from_config(cls, value: Any) -> RefSupervisorSpec:
        """The spec of a config's ``supervisor`` mapping (unknown keys refused by name)."""
        if isinstance(value, cls):
            return value
        keys = [f.name for f in dataclasses.fields(cls)]
        if not isinstance(value, dict):
            raise ValueError(f"supervisor={value!r} must be a mapping with keys {keys}")
        unknown = sorted(set(value) - set(keys), key=str)
        if unknown:
            raise ValueError(f"supervisor: unknown key(s) {unknown}; allowed keys are {keys}")
        return cls(**value)

    def describe(self) -> str:
        out = (f"{self.fallback} takes over once the error's RMS over {self.error_window_s:g} s "
               f"exceeds {self.error_mm:g} mm or, after {REF_ARM_PERIODS} periods, the RMS of its "
               f"change over one period (over {self.aperiodic_window_s:g} s"
               + (f", each sample clipped to ±{self.aperiodic_clip_mm:g} mm"
                  if self.aperiodic_clip_mm is not None else "")
               + f") exceeds {self.aperiodic_mm:g} mm")
        if self.persistent_mm is not None:
            out += (f" or, after {REF_ARM_PERIODS} periods, the error's own RMS over "
                    f"{self.aperiodic_window_s:g} s"
                    + (f" (each sample clipped to ±{self.persistent_clip_mm:g} mm)"
                       if self.persistent_clip_mm is not None else "")
                    + f" exceeds {self.persistent_mm:g} mm")
        if self.last_resort:
            out += (f"; {REF_LAST_RESORTS[self.last_resort]} once {self.fallback}'s loop, given "
                    f"{REF_GRACE_PERIODS} period(s) to settle, passes {self.error_mm:g} mm too")
        return out


class RefSupervised:
    """``policy`` until the monitor trips, then ``fallback`` for the rest of the episode
    (module docstring); ``period_s`` is the reference's period T, ``dt`` the control period.
    With ``spec.last_resort``, the error monitor restarts when the fallback takes over and, if
    the fallback's loop diverges too (after ``REF_GRACE_PERIODS`` to settle), ``last`` (the
    controller ``spec.last_resort`` names) drives the rest of the episode from its rest state.

    State: (policy's, fallback's, monitor, last resort's) with the monitor an (n, 6 + 3N) array
    per row: the ``M_*`` columns (running mean of e², running mean of (e_t − e_{t−T})², the
    stage, the steps taken, the step the stage began, running mean of the clipped e²), then ring
    buffers of the last N = T / dt errors and of the policy's last N actions (extensor's, then
    flexor's)."""

    def __init__(self, policy: Policy, fallback: Policy, dt: float, period_s: float,
                 spec: RefSupervisorSpec = RefSupervisorSpec(), last: Policy | None = None) -> None:
        if spec.last_resort is not None and (
                last is None or type(last).__name__ != BASELINES[spec.last_resort]):
            raise ValueError(f"supervisor.last_resort={spec.last_resort!r} needs its controller "
                             f"{BASELINES[spec.last_resort]}, got {type(last).__name__} "
                             "(mpa_gym.agents.learned.policies.supervise builds it)")
        self.policy, self.fallback, self.last, self.spec = policy, fallback, last, spec
        self.n_period = max(1, round(period_s / dt))
        self.a_err = dt / (spec.error_window_s + dt)
        self.a_ap = dt / (spec.aperiodic_window_s + dt)
        self.clip = np.inf if spec.aperiodic_clip_mm is None else spec.aperiodic_clip_mm * 1e-3
        self.persistent = np.inf if spec.persistent_mm is None else spec.persistent_mm * 1e-3
        self.per_clip = (np.inf if spec.persistent_clip_mm is None
                         else spec.persistent_clip_mm * 1e-3)

    def predict(self, observation: np.ndarray, state: Any = None,
                episode_start: np.ndarray | None = None, deterministic: bool = True
                ) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation, dtype=np.float64)
        single = obs.ndim == 1
        rows = obs.reshape(1, -1) if single else obs
        n, N = rows.shape[0], self.n_period
        inner, fb, mon, lr = (None, None, None, None) if state is None else state
        mon = np.zeros((n, REF_M_RING + 3 * N)) if mon is None else np.array(mon, dtype=float)
        if episode_start is not None:
            mon[np.asarray(episode_start, dtype=bool).reshape(-1)] = 0.0
        stage_before = mon[:, REF_M_STAGE].copy()
        e = rows[:, OXR] - rows[:, OX]
        k = mon[:, REF_M_STEP].astype(np.int64)
        slot = REF_M_RING + k % N
        past = mon[np.arange(n), slot]  # e one period ago (once k >= N)
        mon[:, REF_M_ERR] += self.a_err * (e**2 - mon[:, REF_M_ERR])
        armed = k - mon[:, REF_M_SINCE] >= REF_ARM_PERIODS * N  # two periods into the stage
        change = np.clip(e - past, -self.clip, self.clip)
        mon[:, REF_M_AP] += np.where(armed, self.a_ap * (change**2 - mon[:, REF_M_AP]), 0.0)
        held_e = np.clip(e, -self.per_clip, self.per_clip)
        mon[:, REF_M_PER] += np.where(armed, self.a_ap * (held_e**2 - mon[:, REF_M_PER]), 0.0)
        mon[np.arange(n), slot] = e
        # the fallback's loop is judged on divergence alone: after a hand-over it settles from
        # the policy's oscillation, slowly where it is near its own margin (module docstring)
        grace = (stage_before > 0.0) & (k - mon[:, REF_M_SINCE] < REF_GRACE_PERIODS * N)
        trip = (((np.sqrt(mon[:, REF_M_ERR]) > self.spec.error_mm * 1e-3) & ~grace)
                | (((np.sqrt(mon[:, REF_M_AP]) > self.spec.aperiodic_mm * 1e-3)
                    | (np.sqrt(mon[:, REF_M_PER]) > self.persistent))
                   & (stage_before == 0.0)))
        last = REF_LAST_RESORT if self.spec.last_resort else REF_FALLBACK
        mon[:, REF_M_STAGE] = np.where(trip, np.minimum(stage_before + 1.0, last), stage_before)
        if self.spec.last_resort:  # each stage is judged on its own loop: the monitor restarts
            moved = (mon[:, REF_M_STAGE] > stage_before) & (mon[:, REF_M_STAGE] < last)
            mon[moved, REF_M_ERR] = mon[moved, REF_M_AP] = mon[moved, REF_M_PER] = 0.0
            mon[moved, REF_M_SINCE] = k[moved] + 1
        driving = mon[:, REF_M_STAGE] > 0.0
        a, inner = self.policy.predict(observation, inner, episode_start, deterministic)
        a2 = np.atleast_2d(a)
        mon[np.arange(n), slot + N] = a2[:, 0]
        mon[np.arange(n), slot + 2 * N] = a2[:, 1]
        mon[:, REF_M_STEP] += 1
        if not driving.any():  # the fallback runs only once it drives
            return a, (inner, None, mon, None)
        new = driving & ~(stage_before > 0.0) if fb is not None else driving
        take_over = getattr(self.fallback, "take_over", None)
        if take_over is None:  # no bumpless transfer: from zero state
            b, fb = self.fallback.predict(observation, fb, new[0] if single else new,
                                          deterministic)
        else:
            fb = take_over(rows, self.held(mon), fb, new) if new.any() else fb
            b, fb = self.fallback.predict(observation, fb, None, deterministic)
        out = np.where(driving[:, None], np.atleast_2d(b), a2)
        resort = mon[:, REF_M_STAGE] >= REF_LAST_RESORT
        if resort.any():  # the last resort, from its rest state on the rows it takes over
            fresh = resort & (stage_before < REF_LAST_RESORT)
            c, lr = self.last.predict(observation, lr, fresh[0] if single else fresh,
                                      deterministic)
            out[resort] = np.atleast_2d(c)[resort]
        out = out.astype(np.float32)
        return (out[0] if single else out), (inner, fb, mon, lr)

    def held(self, mon: np.ndarray) -> np.ndarray:
        """(n, 2) per row, the mean of the policy's actions over the last reference period (or
        over the steps so far, within the first): the command the fallback takes over."""
        N, r = self.n_period, REF_M_RING
        filled = np.minimum(mon[:, REF_M_STEP], N)[:, None]
        return np.stack([mon[:, r + N:r + 2 * N].sum(axis=1),
                         mon[:, r + 2 * N:].sum(axis=1)], axis=-1) / np.maximum(filled, 1.0)

    @staticmethod
    def stage(state: Any) -> np.ndarray | None:
        """Per row, who drives: ``REF_POLICY``, ``REF_FALLBACK`` or ``REF_LAST_RESORT`` (None
        before the first step)."""
        return None if state is None else np.asarray(state[2])[:, REF_M_STAGE].astype(np.int8)


def test_rc_is_a_stage_controller_with_its_gains(tmp_path):
    # A declared cascade policy → rc → afc, with rc's gains inline: the fallback is rc built with
    # them, and a policy that sags the leg (a constant antagonistic residual of −0.1 bar: ~7 mm
    # on the nominal model's 68 mm/bar) trips a 2 mm divergence level and is handed to rc,
    # which brings the loaded leg back to the reference (its error over the last 3 of 6
    # periods under 1 mm, the recovery band) without the last resort.
    cfg = _config(tmp_path, {"monitors": {"divergence": {"level_mm": 2.0}}, "stages": [
        {"controller": "policy", "monitors": ["divergence"]},
        {"controller": "rc", "monitors": ["divergence"], "grace_periods": 1},
        {"controller": "afc"}], "gains": {"rc": {"learn": 0.2}}})
    sc = _sc(18.0)
    sup = supervise(Constant(-0.1), cfg, {"scenario": sc})
    assert type(sup.controllers[0]).__name__ == "RepetitiveControl"
    assert sup.controllers[0].learn == 0.2
    (run,) = run_batches([sup], sc, [{"extra_mass_kg": 0.5}], 3)
    assert run["fallback"][:, 0].max() == FALLBACK
    e = (run["x"] - run["x_ref"])[-900:, 0]
    assert np.sqrt(np.mean(e**2)) < 1e-3
