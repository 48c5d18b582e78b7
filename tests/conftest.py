"""Shared helpers: the paper's impact as a one-liner, and the CLI as a subprocess."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# The Ctrl-C tests send SIGINT to this process and to `minidem run` subprocesses. A shell
# without job control starts a background job (`.ci/run &` in a script) with SIGINT
# ignored, Python then installs no KeyboardInterrupt handler, the children inherit the
# ignored signal, and those tests fail though minidem is right. Python's own handler here:
# the children then start with the default disposition, as from a terminal.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

REPO = Path(__file__).resolve().parents[1]
OBLIQUE = REPO / "scenarios" / "oblique.toml"

# The seed problem (Thornton, Cummins & Cleary 2011, section 4; ../shared/paper/models.md):
# identical sphere and wall, E = 70 GPa, nu = 0.3, R = 25 mm, 2650 kg/m^3, Vi = 5 m/s, mu = 0.1.
PAPER = dict(youngs_modulus=70e9, poisson_ratio=0.3, radius=0.025, density=2650.0, speed=5.0, friction=0.1)


def paper_mass(radius=PAPER["radius"], density=PAPER["density"]) -> float:
    return 4.0 / 3.0 * math.pi * radius**3 * density


def paper_effective_modulus(youngs_modulus=PAPER["youngs_modulus"], poisson_ratio=PAPER["poisson_ratio"]) -> float:
    """E* of two identical bodies, E / (2 (1 - nu^2)) (paper eq 14)."""
    return youngs_modulus / (2.0 * (1.0 - poisson_ratio**2))


def _toml(value) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value)


def impact_summary(law: str = "hmd", angle_deg: float = 30.0, scenario: Path = OBLIQUE, **settings) -> dict:
    """Run the paper's impact in-process and return the summary dict (summary.json's content).

    ``settings`` are dotted scenario keys with '.' written as '__', e.g. contact__friction=0.
    """
    from minidem.results import analysis
    from minidem.scene import scenario as scenario_module
    from minidem.engine import simulation

    overrides = [f'contact.law="{law}"', f"impact.angle_deg={angle_deg!r}"]
    overrides += [f"{key.replace('__', '.')}={_toml(value)}" for key, value in settings.items()]
    scene = scenario_module.load_scene(scenario, overrides)
    return analysis.summary(simulation.Simulation(scene).run())


def minidem_command() -> list[str]:
    """The installed console script of the interpreter running the tests (the user's entry)."""
    script = Path(sys.executable).with_name("minidem")
    return [str(script)] if script.exists() else [sys.executable, "-m", "minidem.cli"]


def run_cli(*args, cwd=None, env=None, timeout=300) -> subprocess.CompletedProcess:
    merged = dict(os.environ)
    merged.update(env or {})
    return subprocess.run(minidem_command() + [str(a) for a in args], cwd=cwd or REPO, env=merged,
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def cli():
    return run_cli


def without_progress(err: str) -> str:
    """stderr without the progress notes a first run on empty caches prints while it
    compiles (after 2 s: 'minidem: compiling ...', minidem.engine.warmup and simulation):
    an error must be the first line after them."""
    return "".join(line for line in err.splitlines(keepends=True) if not line.startswith("minidem: compiling "))


def contact_count(state):
    """Contacts per particle (pairs and plane walls) in a :class:`minidem.engine.state.State`."""
    offsets, partners, _, overlap = state.pairs[:4]
    first = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    touching = overlap > 0
    n = len(offsets) - 1
    return (np.bincount(first[touching], minlength=n) + np.bincount(partners[touching], minlength=n)
            + np.bincount(state.plane_contacts()[0][state.planes[4] > 0], minlength=n))


def rk4_step(acceleration, x, v, dt):
    """One classical Runge-Kutta step of x'' = acceleration(x): the independent
    integrations the tests compare the engine with (its velocity Verlet shares nothing
    with it)."""
    k1x, k1v = v, acceleration(x)
    k2x, k2v = v + 0.5 * dt * k1v, acceleration(x + 0.5 * dt * k1x)
    k3x, k3v = v + 0.5 * dt * k2v, acceleration(x + 0.5 * dt * k2x)
    k4x, k4v = v + dt * k3v, acceleration(x + dt * k3x)
    return x + dt / 6.0 * (k1x + 2 * k2x + 2 * k3x + k4x), v + dt / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
