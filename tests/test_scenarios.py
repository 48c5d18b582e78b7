"""The scenario files minidem ships: every one is valid as shipped, and the example
scenes that no other test runs do what their comments promise.

The paper's sweeps, settle, hopper and column collapse run in test_paper.py,
test_multiparticle.py and test_walls_and_fills.py; here each file is at least read and
validated, so that a renamed key or law cannot leave a broken example behind.
"""

from __future__ import annotations

import numpy as np
import pytest

from conftest import REPO
from minidem import analysis, scenario, simulation, sweep

SCENARIOS = sorted((REPO / "scenarios").rglob("*.toml"))


def test_every_shipped_scenario_is_found():
    names = {p.name for p in SCENARIOS}
    assert {"oblique.toml", "settle.toml", "newtons_cradle.toml", "two_spheres_head_on.toml",
            "two_spheres_oblique.toml", "hopper.toml", "column_collapse.toml"} <= names
    assert len([p for p in SCENARIOS if p.parent.name == "paper"]) == 5


@pytest.mark.parametrize("path", SCENARIOS, ids=[str(p.relative_to(REPO / "scenarios")) for p in SCENARIOS])
def test_shipped_scenario_validates(path, tmp_path):
    data = scenario.read_toml(path)
    if sweep.has_sweep(data):
        if path.name == "figs02-04_ls_kappa.toml":
            # the paper's Table 1 varies the stiffness ratio through nu up to 0.83: accepted,
            # with a warning naming the file and key
            with pytest.warns(UserWarning, match=r"materials\.glass\.poisson_ratio = 0\.\d+ > 0\.5 is not physical"):
                plan = sweep.plan(data, str(path))
        else:
            plan = sweep.plan(data, str(path))  # validates every case's scenario too
        assert plan.cases
    else:
        scene = scenario.load_scene(path, output_directory=tmp_path)
        assert scene.n_particles >= 1


def test_newtons_cradle_passes_momentum_down_the_row():
    """Five touching equal steel balls, the first arriving at 1 m/s, frictionless elastic
    Hertz contacts, no gravity: momentum is conserved to round-off, kinetic energy to
    velocity Verlet's error once every contact has ended, the balls keep their order
    (no ball passes through another) and the last ball leaves first and fastest, in the
    direction of the impact (the cradle's point; a Hertz chain keeps a little motion in
    the other balls, so no exact share is asserted)."""
    scene = scenario.load_scene(REPO / "scenarios" / "newtons_cradle.toml", output_directory="-")
    result = simulation.Simulation(scene).run()
    mass = scene.mass
    momentum_in = (mass[:, None] * scene.velocity).sum(axis=0)
    momentum_out = (mass[:, None] * result.velocity).sum(axis=0)
    scale = float(mass[0] * np.linalg.norm(scene.velocity[0]))
    assert np.abs(momentum_out - momentum_in).max() <= 1e-13 * scale * result.steps ** 0.5  # round-off walk
    assert result.contacts == 0, "every contact should have ended by run.end_time"
    assert analysis.energy_ratio(result) == pytest.approx(1.0, abs=1e-6)  # elastic, no friction
    x = result.position[:, 0]
    assert np.all(np.diff(x) > 2 * scene.radius[:-1] * (1 - 1e-9))  # order kept, no overlap left
    speeds = result.velocity[:, 0]
    assert int(np.argmax(speeds)) == 4 and speeds[4] > 0.0
    assert speeds[4] > 0.5 * float(scene.velocity[0, 0])  # most momentum ends in the last ball
    assert np.abs(result.velocity[:, 1:]).max() == 0.0 and np.abs(result.angular_velocity).max() == 0.0
