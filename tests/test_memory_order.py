"""Particles stored in space order (minidem.geometry.order): a scene given in a scattered
order is stored sorted by cells, runs the same physics, and every result a user sees
(Result arrays, VTK frames, fault messages) comes back in the scenario's order; the
state files say where each stored row came from (particle_id) and resume bit for bit."""

import dataclasses
import signal

import numba
import numpy as np
import pytest

import minidem
from minidem.contact import laws
from minidem.engine import checkpoint, kernel, simulation, warmup
from minidem.engine.run_loop import LoopThreads
from minidem.engine.state import State
from minidem.geometry.order import SCATTERED_RATIO, exchange_pairs, mean_step, permute_rows, scattered, spatial_order
from minidem.studies import verify

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
    # consecutive spheres are neighbours again: at 6,000 the lattice's own order is 0.91x the
    # sorted one's mean step (its rows' ends jump across the box), a random order 10.9x
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
    scenario = settle(lattice_positions()[shuffle]).output(vtk=True, interval=0.01, contacts=True)
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
    # the contact network's lines join the scenario's particles that touch (centres closer
    # than the 2 mm diameter): its stored pairs renamed as the scenario numbers them
    network = output.contacts[len(output.contacts.times) - 1]
    pairs = network.cells_dict[3]  # VTK_LINE
    assert pairs.shape[0] > 1000
    distance = np.linalg.norm(result.position[pairs[:, 0]] - result.position[pairs[:, 1]], axis=1)
    assert distance.max() < 2e-3


def interrupted_then_resumed(tmp_path, monkeypatch, scene, copies: int, interval: float, chunk_steps: int):
    """Ctrl-C (SIGINT, held until the copy is whole) after ``copies`` copies of the last
    good state, with checkpoints every ``interval`` s; then --resume. Returns (the run left
    alone, the resumed run, the checkpoint's arrays, the state's sorts at the last copy)."""
    reference = simulation.Simulation(scene()).run()
    original, sorts = State.capture_items, []

    def capture_items(self):
        yield from original(self)
        sorts.append(self.sorts)
        if len(sorts) == copies:
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(State, "capture_items", capture_items)
    with pytest.raises(KeyboardInterrupt):
        simulation.Simulation(scene()).run(checkpoints=checkpoint.Policy(tmp_path, interval=interval),
                                           chunk_steps=chunk_steps)
    monkeypatch.setattr(State, "capture_items", original)
    arrays, meta = checkpoint.read(tmp_path / checkpoint.CHECKPOINT)
    assert 0 < meta["step"] < reference.steps
    sim = simulation.Simulation(scene())
    resumed = sim.run(resume_from=checkpoint.load_for_resume(sim, tmp_path))
    # the resumed run, whatever order it now stores the particles in, writes checkpoints
    # that a next --resume takes (the scenario's fingerprint, not the stored order's)
    assert checkpoint.fingerprint(sim) == meta["fingerprint"]
    assert resumed.steps == reference.steps
    for name in ("position", "velocity", "angular_velocity", "force"):
        assert np.array_equal(getattr(resumed, name), getattr(reference, name)), name
    return arrays, sorts[-1]


def test_a_stored_order_resumes_bit_for_bit(tmp_path, monkeypatch, shuffle):
    arrays, _ = interrupted_then_resumed(
        tmp_path, monkeypatch, lambda: settle(lattice_positions()[shuffle], end_steps=600).scene(), copies=3,
        interval=2e-3, chunk_steps=100)
    assert "particle_id" in arrays


def test_a_fault_names_the_particle_as_the_scenario_numbers_it(shuffle):
    sim = simulation.Simulation(settle(lattice_positions()[shuffle]).scene(), compile=False)
    stored = 17
    given = int(sim.scene.particle_id[stored])
    assert given != stored
    message = sim._fault_message(np.array([kernel.TUNNELLED, stored, 0, kernel.PLANE]), 10)
    assert f"particle {given} passed through" in message


# --- sorting again during a run (Simulation.sort_in_space) -----------------------------
# scenarios/settle.toml's pile at 300 spheres (about four layers in a 20 mm box): by 0.05 s
# the lowest layers have landed off-centre on each other and slide, roll and twist, so most
# pair contacts carry tangential, rolling and twisting history. (Later the pile's chaos
# grows round-off: by 0.1 s two runs whose only difference is the storage order, fixed at
# the start, differ by 1e-10 m.)
PILE = ["fill.0.count=300", "run.end_time=0.05", "run.threads=1", "output.vtk=false"]


def reversing_every_build(monkeypatch):
    """Every list build after the first sorts the particles again, into the reverse of
    their stored order: every pair then turns over, and every live contact is carried to
    the pair seen from its other sphere (the hardest case for HistorySlot.exchange)."""
    monkeypatch.setattr(simulation, "REORDER_MIN_PARTICLES", 0)
    monkeypatch.setattr(simulation, "RESORT_RATIO", 0.0)
    monkeypatch.setattr(simulation, "spatial_order", lambda position, cell: np.arange(len(position))[::-1].copy())
    monkeypatch.setattr(simulation, "scattered", lambda position, order: False)  # the start keeps its order


def run_pile(law_overrides):
    scene = minidem.load("scenarios/settle.toml", PILE + law_overrides).scene()
    sim = simulation.Simulation(scene)
    return sim, sim.run()


def test_contacts_seen_from_their_other_sphere_give_the_same_forces(monkeypatch):
    # A pair's force does not depend on which sphere owns the contact: the run whose every
    # contact turns over at every list build (its history carried with the law's exchange
    # signs) is the run without, to round-off. A wrong sign reverses that slot's force or
    # couple at the next step: the negative control below shows it is seen.
    # settle.toml's law, hm + epsd rolling + sds twisting: tangential force and rolling
    # couple (vectors, -1), twisting couple about the normal (a scalar, +1)
    _, reference = run_pile([])
    reversing_every_build(monkeypatch)
    sim, turned = run_pile([])
    assert sim.state.sorts >= 3 and sim.scene.particle_id is not None
    assert turned.contacts == reference.contacts > 200
    # the same run to round-off (measured, hm+epsd+sds_twisting: 1.5e-15 m, 5e-13 m/s and
    # 7e-10 rad/s, as with the order reversed once at the start, where no history turns
    # over: 5.6e-16 m, 5.4e-13 m/s, 6.3e-10 rad/s); bounds 1e-9 of the 2 cm, 0.05 m/s and
    # 80 rad/s scales
    assert np.abs(turned.position - reference.position).max() < 2e-11
    speed, spin = np.abs(reference.velocity).max(), np.abs(reference.angular_velocity).max()
    assert np.abs(turned.velocity - reference.velocity).max() < 1e-9 * speed
    assert spin > 1.0 and np.abs(turned.angular_velocity - reference.angular_velocity).max() < 1e-9 * spin
    # negative control: every slot carried as it is (+1), the tangential and rolling
    # springs push the wrong way after each build and the runs part by far more
    monkeypatch.setattr(sim.law.__class__, "exchange_signs", property(lambda law: (1.0,) * law.history_size))
    _, wrong = run_pile([])
    assert np.abs(wrong.velocity - reference.velocity).max() > 1e-4 * speed


def test_a_run_sorts_again_only_when_the_particles_have_mixed(monkeypatch):
    # the pile of settle.toml keeps its neighbours (a sphere moves a fraction of its
    # diameter against its neighbours): no sort after the start, whatever the builds
    monkeypatch.setattr(simulation, "REORDER_MIN_PARTICLES", 0)
    sim, result = run_pile([])
    assert result.neighbour_builds > 3 and sim.state.sorts == 0


def test_files_written_after_a_sort_resume_bit_for_bit(tmp_path, monkeypatch):
    reversing_every_build(monkeypatch)
    # each sort moves the last stored particle to the front: after s sorts the order is
    # the scenario's rolled by s, never back to it within the run (a reversal, whose
    # second sort restores the order, made the check below depend on how many sorts fell
    # before the copy taken, whose spacing follows the wall clock)
    monkeypatch.setattr(simulation, "spatial_order", lambda position, cell: np.roll(np.arange(len(position)), 1))
    arrays, sorts = interrupted_then_resumed(
        tmp_path, monkeypatch, lambda: minidem.load("scenarios/settle.toml", PILE).scene(), copies=4, interval=0.02,
        chunk_steps=500)
    # the checkpoint holds a state sorted during the run, in that order
    assert 1 <= sorts < 300 and np.array_equal(arrays["particle_id"], np.roll(np.arange(300), sorts))


# (the rolling and twisting couples: settle.toml's pile above; jkr+mindlin and ls: their
# whole batteries, which must pass every check, this one included, in test_adhesion and
# test_verify; every other shipped law and part passes it too, `minidem verify`,
# docs/multi-particle.md: each case costs the suite the pair kernel's compile, ~15-20 s)
@pytest.mark.parametrize("law, overrides", [
    ("hmd", []),  # 26 floats: forces, displacements and directions (-1), reversal points, modes, flags (+1)
    # damped: its dashpots read the velocities predicted from each sphere's last force
    # (State.last_force), which a sort must carry with the particles (review: left
    # unpermuted, 1e-6 apart; the elastic case passes either way). The kernel is the one
    # the damped two-sphere tests compile
    ("hm", ["contact.restitution=0.5"]),
], ids=["hmd", "hm-damped"])
def test_verify_turns_every_contact_over_and_finds_the_same_collision(law, overrides):
    # minidem verify's check: the oblique collision of two spinning spheres, their order
    # reversed at every list build (the pair turned over each time), gives the same
    # bits as the run left in its order (measured: 0 difference over 254 reversals)
    check, = verify.Battery(law, overrides).exchange()
    assert check.passed, check.value
    assert "0.00e+00" in check.value


ROLLING_PART = ["contact.rolling=epsd", "contact.rolling_friction=0.1"]


def test_verify_turns_over_the_history_of_the_parts_a_combination_adds(monkeypatch):
    # hm with EPSD rolling resistance is a combination whose history is hm's tangential
    # force (3 slots) then EPSD's rolling moment on the first body (3 slots, exchange -1:
    # seen from the other sphere the relative spin and the moment change sign). The check
    # must carry the combination's six signs, not the named law's three: with those, the
    # rolling moment kept its sign at each reversal and the run drifted by 4e-2 of the
    # speed and spin (minidem verify before this test). The same bits with them.
    battery = verify.Battery("hm", ROLLING_PART)
    assert battery.law.exchange_signs == (-1.0,) * 6
    # and the battery's other checks see the combination too: the rigid-body sliding
    # limit (paper eqs 6-8, no rolling resistance) is not applicable, as for "hm+epsd"
    assert [check.passed for check in battery.sliding_limit()] == [None]
    check, = battery.exchange()
    assert check.passed and "0.00e+00" in check.value, check.value
    # negative control: the rolling slots carried unchanged (+1) must be caught
    monkeypatch.setattr(laws.ContactLaw, "exchange_signs",
                        property(lambda law: (-1.0,) * 3 + (1.0,) * (law.history_size - 3)))
    check, = verify.Battery("hm", ROLLING_PART).exchange()
    assert check.passed is False and float(check.value.split()[3]) > 1e-3, check.value


def test_verify_fails_a_law_whose_history_reads_the_same_from_both_spheres(monkeypatch):
    # negative control: hm's tangential spring force carried unchanged to the other sphere
    # (+1 where it is -1) pushes the wrong way after each reversal
    monkeypatch.setattr(laws.ContactLaw, "exchange_signs", property(lambda law: (1.0,) * law.history_size))
    check, = verify.Battery("hm").exchange()
    assert check.passed is False
    assert float(check.value.split()[3]) > 1e-3


def test_a_law_that_does_not_declare_its_exchange_is_never_sorted_during_a_run(monkeypatch):
    # a third party's law written before HistorySlot.exchange: every slot left at None
    battery = verify.Battery("hm")
    undeclared = dataclasses.replace(battery.law, history=tuple(
        dataclasses.replace(slot, exchange=None) for slot in battery.law.history))
    assert undeclared.exchange_signs is None
    battery.law = undeclared
    check, = battery.exchange()
    assert check.passed is None and "not declared for slot(s) tangential_force" in check.value
    monkeypatch.setattr(laws.ContactLaw, "exchange_signs", property(lambda law: None))
    monkeypatch.setattr(simulation, "REORDER_MIN_PARTICLES", 0)
    sim = simulation.Simulation(minidem.load("scenarios/settle.toml", PILE).scene())
    assert sim.exchange_signs is None


def test_a_run_sorted_at_every_build_gives_the_same_bits_on_one_and_two_threads(monkeypatch):
    # the scene of test_multiparticle's test_same_bits_on_one_and_two_threads (its kernel),
    # every pair turned over at every list build: the sort depends on the state alone, never
    # on the thread count, so the two-thread run is the one-thread run bit for bit
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs two threads")
    reversing_every_build(monkeypatch)
    monkeypatch.setattr(simulation, "PARALLEL_MIN_PARTICLES", 0)
    monkeypatch.setattr(LoopThreads, "PROBE_FIRST", 10**9)
    overrides = ["walls.0.upper=[0.02, 0.02, 1.0]", "fill.0.upper=[0.02, 0.02, 1.0]", "fill.0.count=200",
                 "run.end_time=0.012", "output.vtk=false"]
    runs, sims = [], []
    for threads in (1, 2):
        sims.append(simulation.Simulation(minidem.load("scenarios/bench/settle.toml",
                                                       overrides + [f"run.threads={threads}"]).scene()))
        runs.append(sims[-1].run())
    assert runs[0].threads == 1 and runs[1].threads == 2 and runs[1].contacts > 50
    assert sims[0].state.sorts == sims[1].state.sorts >= 2
    for name in ("position", "velocity", "angular_velocity", "energy"):
        assert np.array_equal(getattr(runs[0], name), getattr(runs[1], name)), name


def test_renumbered_lists_match_a_pair_by_pair_construction():
    # exchange_pairs and permute_rows against a brute-force construction, pair by pair, on
    # 300 random half lists (0-11 particles, 0-4 history floats, random signs): the same
    # offsets, partners (in their own integer type), history bits and overlaps
    rng = np.random.default_rng(1)
    for _ in range(300):
        n, h = int(rng.integers(0, 12)), int(rng.integers(0, 5))
        rows = [sorted(j for j in range(i + 1, n) if rng.random() < 0.3) for i in range(n)]
        offsets = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64)
        partners = np.array([j for r in rows for j in r], dtype=np.int32)
        history = rng.normal(size=(len(partners), h))
        history[rng.random(len(partners)) < 0.3] = 0.0
        overlap = rng.normal(size=len(partners))
        order, signs = rng.permutation(n), rng.choice([-1.0, 1.0], size=h)
        new = np.empty(n, dtype=np.int64)
        new[order] = np.arange(n)
        expected = {}
        for i in range(n):
            for e in range(offsets[i], offsets[i + 1]):
                a, b = new[i], new[partners[e]]
                expected[(min(a, b), max(a, b))] = (history[e] * (signs if a > b else 1.0) + 0.0, overlap[e])
        keys = sorted(expected)
        got = exchange_pairs(offsets, partners, history, overlap, order, signs)
        assert np.array_equal(got[0], np.searchsorted([a for a, _ in keys], np.arange(n + 1)))
        assert got[1].dtype == partners.dtype and np.array_equal(got[1], [b for _, b in keys])
        want = np.zeros((len(keys), h))
        for row, key in enumerate(keys):
            want[row] = expected[key][0]
        assert np.array_equal(got[2].view(np.uint64), want.view(np.uint64))
        assert np.array_equal(got[3], [expected[k][1] for k in keys])
        entries = np.array([e for k in range(n) for e in range(offsets[order[k]], offsets[order[k] + 1])],
                           dtype=np.int64)
        rows_offsets, (rows_partners, rows_history) = permute_rows(offsets, order, partners, history)
        assert np.array_equal(rows_offsets, np.concatenate([[0], np.cumsum(np.diff(offsets)[order])]))
        assert np.array_equal(rows_partners, partners[entries]) and np.array_equal(rows_history, history[entries])


def polydisperse_pile():
    scene = minidem.load("scenarios/settle.toml", PILE[:1] + ["run.end_time=0.02"] + PILE[2:]).scene()
    radius = np.random.default_rng(3).uniform(0.85e-3, 1.0e-3, scene.n_particles)
    return dataclasses.replace(scene, radius=radius)


def test_a_ctrl_c_checkpoint_from_a_copy_older_than_a_sort_resumes_bit_for_bit(tmp_path, monkeypatch):
    # Ctrl-C writes the checkpoint from the last good copy, which may predate a sort: its
    # Verlet list is made again with the radii in the copy's order (unequal radii here), or
    # the histories would meet another list (the review's find: 723 saved contacts against
    # a list of 721)
    reversing_every_build(monkeypatch)
    reference = simulation.Simulation(polydisperse_pile()).run()
    sorts_at_copy = []
    original = State.capture_items

    def capture_items(self):
        sorts_at_copy.append(self.sorts)
        return original(self)

    monkeypatch.setattr(State, "capture_items", capture_items)
    sim = simulation.Simulation(polydisperse_pile())

    def progress(steps, total, contacts):
        if steps > 200 and sim.state.sorts > sorts_at_copy[-1]:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sim.run(progress=progress, checkpoints=checkpoint.Policy(tmp_path, interval=1.0), chunk_steps=50)
    monkeypatch.setattr(State, "capture_items", original)
    resumed_sim = simulation.Simulation(polydisperse_pile())
    resumed = resumed_sim.run(resume_from=checkpoint.load_for_resume(resumed_sim, tmp_path))
    for name in ("position", "velocity", "angular_velocity"):
        assert np.array_equal(getattr(resumed, name), getattr(reference, name)), name


def test_a_simulation_run_twice_starts_from_its_start_order(monkeypatch):
    reversing_every_build(monkeypatch)
    # a shift by one at each build: no number of sorts brings the start order back
    monkeypatch.setattr(simulation, "spatial_order", lambda position, cell: np.roll(np.arange(len(position)), 1))
    sim = simulation.Simulation(polydisperse_pile())
    first, second = sim.run(), sim.run()
    assert sim.state.sorts >= 2
    assert np.array_equal(first.position, second.position) and np.array_equal(first.velocity, second.velocity)


def test_a_scene_that_records_a_trace_is_never_sorted(monkeypatch):
    # trace.csv follows the particle stored first: the scenario's particle 0 only while
    # nothing is sorted
    reversing_every_build(monkeypatch)
    monkeypatch.setattr(simulation, "scattered", lambda position, order: True)
    sim = simulation.Simulation(minidem.load("scenarios/settle.toml", PILE + ["output.trace=true"]).scene())
    assert sim.scene is sim.input_scene and sim.exchange_signs is None


def test_the_kernel_helper_is_found_for_a_sorted_scene(monkeypatch):
    # minidem run starts a helper compiling the kernel of the scene as read; the run looks
    # it up by that scene, not by the sorted copy it stores
    scene = settle(lattice_positions()[np.random.default_rng(7).permutation(N)]).scene()
    sim = simulation.Simulation(scene, compile=False)
    assert sim.scene is not sim.input_scene
    monkeypatch.setitem(warmup._KERNEL_HELPERS, id(scene), (scene, "the helper"))
    assert warmup.kernel_helper(sim.input_scene) == "the helper"
