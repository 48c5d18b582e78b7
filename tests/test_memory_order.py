"""Particles stored in space order (minidem.geometry.order): a scene given in a scattered
order is stored sorted by cells, runs the same physics, and every result a user sees
(Result arrays, VTK frames, fault messages) comes back in the scenario's order; the
state files say where each stored row came from (particle_id) and resume bit for bit."""

import signal

import numpy as np
import pytest

import minidem
from minidem.engine import checkpoint, kernel, simulation
from minidem.geometry.order import SCATTERED_RATIO, mean_step, scattered, spatial_order

# the settle scene (shared/bench/settle.md) at 6,000 spheres: three layers, above
# REORDER_MIN_PARTICLES; 1,500 steps of 2e-5 s land the lowest layers on the floor and on
# each other (thousands of touching contacts at the end, with tangential history)
N, STEPS = 6000, 1500


def lattice_positions():
    return minidem.load("scenarios/bench/settle.toml", {"fill.0.count": N}).scene().position


def settle(position, end_steps=STEPS):
    return (minidem.Scenario()
            .material("beads", youngs_modulus=5e6, poisson_ratio=0.3, density=2500.0)
            .contact("hm", friction=0.5, restitution=0.5)
            .wall("box", lower=[0, 0, 0], upper=[0.1, 0.1, 1.0], open_top=True, material="beads")
            .particles(position=position, radius=1e-3, material="beads")
            .run_settings(dt=2e-5, stop="time", end_time=end_steps * 2e-5, gravity=[0, 0, -9.81], skin=0.5e-3,
                          threads=1)
            .output(vtk=False))


@pytest.fixture(scope="module")
def shuffle():
    return np.random.default_rng(7).permutation(N)


def test_spatial_order_sorts_a_shuffled_lattice_back_into_layers(shuffle):
    position = lattice_positions()
    shuffled = position[shuffle]
    cell = 1.25e-3  # half the list cutoff 2 R + skin, as the engine sorts
    order = spatial_order(shuffled, cell)
    assert np.array_equal(np.sort(order), np.arange(N))  # a permutation
    stored = shuffled[order]
    # non-decreasing cells of z, then y, then x
    index = np.floor((stored - stored.min(axis=0)) / cell).astype(np.int64)
    key = (index[:, 2] * 1000 + index[:, 1]) * 1000 + index[:, 0]
    assert np.all(np.diff(key) >= 0)
    # sites 2.2 mm apart lie one to a cell, layers in cells of their own: the shuffled lattice
    # sorts back to its fill's layers (a jittered row may straddle two cells of y)
    layer = np.floor(stored[:, 2] / 2.2e-3).astype(np.int64)
    assert np.all(np.diff(layer) >= 0)
    assert np.mean(shuffle[order] == np.arange(N)) > 0.8
    # consecutive spheres are neighbours again: the lattice's own order is ~1.07x the sorted
    # one's mean step (its rows' ends jump across the box), a random order ~24x
    assert mean_step(stored) < 1.2 * mean_step(position)
    assert scattered(shuffled, order)
    assert not scattered(position, spatial_order(position, cell))
    assert mean_step(shuffled) > 2 * SCATTERED_RATIO * mean_step(stored)
    # stable: ties (the same cell) keep their given order, so a scene always sorts the same way
    assert np.array_equal(order, spatial_order(shuffled, cell))


def test_a_scattered_scene_runs_the_same_physics_in_space_order(shuffle):
    position = lattice_positions()
    ordered = simulation.Simulation(settle(position).scene())
    stored = simulation.Simulation(settle(position[shuffle]).scene())
    # the fill's own order is spatial and is kept (its results keep their bits); the
    # shuffled one is stored sorted
    assert ordered.scene.particle_id is None
    assert stored.scene.particle_id is not None and stored.input_scene.particle_id is None
    assert np.array_equal(stored.scene.position, stored.input_scene.position[stored.scene.particle_id])
    reference, run = ordered.run(), stored.run()
    # results in the scenario's order: row k is the k-th particle given
    assert run.scene is stored.input_scene
    assert reference.contacts > 1000 and run.contacts == reference.contacts
    # the same contacts evaluated with i and j exchanged and summed in another order: the
    # same trajectories to round-off (measured 2e-16 m and 2e-13 m/s after 1,500 steps;
    # the bound is 1e4 times float64's resolution of the 2 cm positions and 0.04 m/s speeds)
    for name, bound in (("position", 1e-12), ("velocity", 1e-11), ("angular_velocity", 1e-7)):
        assert np.abs(getattr(run, name) - getattr(reference, name)[shuffle]).max() < bound, name
    # momentum the walls did not take is gravity's: the same total either way
    assert np.allclose(run.velocity.sum(axis=0), reference.velocity.sum(axis=0), rtol=0, atol=1e-9)


def test_files_of_a_stored_order_name_each_row_and_frames_are_in_the_scenario_order(tmp_path, shuffle):
    scenario = settle(lattice_positions()[shuffle]).output(vtk=True, interval=0.01)
    result = minidem.run(scenario, out=tmp_path / "out")
    output = minidem.open_results(tmp_path / "out")
    state = output.final_state
    ids = state["particle_id"]
    assert np.array_equal(np.sort(ids), np.arange(N))
    # the state file holds the stored rows (its Verlet list indexes them); particle_id names them
    assert np.array_equal(state["position"], result.position[ids])
    assert np.array_equal(state["velocity"], result.velocity[ids])
    # every frame in the scenario's order, as the Result
    times = output.series.times
    last = output.series[len(times) - 1]
    assert np.array_equal(np.asarray(last.points), result.position)
    assert np.array_equal(last.point_data["velocity"], result.velocity)
    assert np.array_equal(last.point_data["particle_id"], np.arange(N))
    first = output.series[0]
    assert np.array_equal(np.asarray(first.points), lattice_positions()[shuffle])


def test_a_stored_order_resumes_bit_for_bit(tmp_path, monkeypatch, shuffle):
    scene = lambda: settle(lattice_positions()[shuffle], end_steps=600).scene()  # noqa: E731
    reference = simulation.Simulation(scene()).run()
    original, copies = simulation.State.capture, []

    def capture(self, into=None):  # Ctrl-C after the third copy of the state
        out = original(self, into)
        copies.append(1)
        if len(copies) == 3:
            signal.raise_signal(signal.SIGINT)
        return out

    monkeypatch.setattr(simulation.State, "capture", capture)
    with pytest.raises(KeyboardInterrupt):
        simulation.Simulation(scene()).run(checkpoints=checkpoint.Policy(tmp_path, interval=2e-3), chunk_steps=100)
    monkeypatch.setattr(simulation.State, "capture", original)
    arrays, meta = checkpoint.read(tmp_path / checkpoint.CHECKPOINT)
    assert 0 < meta["step"] < 600 and "particle_id" in arrays
    sim = simulation.Simulation(scene())
    resumed = sim.run(resume_from=checkpoint.load_for_resume(sim, tmp_path))
    assert resumed.steps == reference.steps
    for name in ("position", "velocity", "angular_velocity", "force"):
        assert np.array_equal(getattr(resumed, name), getattr(reference, name)), name


def test_a_fault_names_the_particle_as_the_scenario_numbers_it(shuffle):
    sim = simulation.Simulation(settle(lattice_positions()[shuffle]).scene(), compile=False)
    stored = 17
    given = int(sim.scene.particle_id[stored])
    assert given != stored
    message = sim._fault_message(np.array([kernel.TUNNELLED, stored, 0, kernel.PLANE]), 10)
    assert f"particle {given} passed through" in message
