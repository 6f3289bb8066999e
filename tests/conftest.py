"""Shared fixtures."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from mpa_gym.configs import DEFAULT_TRAIN_CONFIG
from mpa_gym.model.params import DEFAULT_PARAMS, Params

# Tests that run a device loop in another process in real time (the emulator over a link). The
# shared machines that run the suite pause processes now and then, for up to hundreds of
# milliseconds (a 340 ms pause of the telemetry was seen in CI), longer than any rig's limits
# should absorb. Such a test runs again, up to twice, on a fresh device and a fresh log; no
# limit or tolerance is loosened. pytest reports each rerun (R), so a real regression, which
# fails every time, still fails.
REALTIME = pytest.mark.flaky(reruns=2, reruns_delay=1)


@pytest.fixture
def params() -> Params:
    return DEFAULT_PARAMS


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def central_diff(f, x, h):
    """Fourth-order (five-point) central difference: truncation O(h⁴ f⁽⁵⁾), round-off
    O(eps |f| / h); with the steps used in the tests both are below 1e-8 relative."""
    return (f(x - 2 * h) - 8 * f(x - h) + 8 * f(x + h) - f(x + 2 * h)) / (12.0 * h)


def children(pid: int) -> set[int]:
    """The pids of a process's children (every thread's), from /proc."""
    out = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            out |= {int(c) for c in open(f"/proc/{pid}/task/{task}/children").read().split()}
        except OSError:  # the thread ended between the listing and the read: no children
            continue
    return out


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie has exited)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def wait_gone(pids: Iterable[int], timeout: float = 30.0) -> list[int]:
    """Wait up to ``timeout`` seconds for processes to exit; those still running."""
    deadline = time.monotonic() + timeout
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    return [p for p in pids if alive(p)]


def default_sigint() -> None:
    """``preexec_fn`` for a child process a test interrupts: a job a non-interactive shell
    starts in the background inherits SIGINT ignored, and Python then never raises
    KeyboardInterrupt; the child gets the default back, as a terminal's process has it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@contextlib.contextmanager
def serving(kind: str = "udp", scenario: Any = "nominal", **kw: Any
            ) -> Iterator[tuple[str, Any]]:
    """(device URL, emulator): the device emulator serving in a thread on a UDP loopback port
    or a pseudo-terminal, stopped and its link closed on the way out."""
    from mpa_gym.hardware.emulator import Emulator
    from mpa_gym.hardware.transport import PtyPair, UDPServer

    link = UDPServer("127.0.0.1", 0) if kind == "udp" else PtyPair()
    url = (f"udp://127.0.0.1:{link.address[1]}" if kind == "udp"
           else f"serial://{link.slave_path}")
    try:
        emu = Emulator(link, scenario, **kw)
    except BaseException:
        link.close()
        raise
    thread = emu.start_thread()
    try:
        yield url, emu
    finally:
        emu.stop()
        thread.join(timeout=2.0)
        link.close()


def tiny_config(folder: Path, edit: Callable[[dict[str, Any]], None] | None = None,
                **ppo: Any) -> Path:
    """The default training config cut down to a tiny run, written to ``folder/cfg.yaml``:
    half-second episodes, no held-out evaluation or checkpoint during it, ``ppo`` (n_envs,
    n_timesteps, n_steps, batch_size, n_epochs) over the defaults below, then ``edit`` applied to
    the whole config. The weights and statistics it trains are real; their quality does not
    matter to the tests that use it."""
    cfg = yaml.safe_load(DEFAULT_TRAIN_CONFIG.read_text())
    hp = cfg["MPALegResidual-v0"]
    hp.update({"n_envs": 4, "n_timesteps": 512, "n_steps": 64, "batch_size": 128,
               "n_epochs": 2, **ppo})
    hp["env_kwargs"]["task"]["episode_s"] = 0.5
    cfg["mpa_gym"].update(eval_scenarios=[], eval_freq=10_000, checkpoint_freq=10_000)
    if edit is not None:
        edit(cfg)
    path = Path(folder) / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path
