"""A multi-particle scene built in code: 64 glass beads from arrays, dropped into an
open box under gravity; the run's output read back and drawn.

    python docs/examples/multi_particle.py [OUTPUT_DIRECTORY]

Every value goes through the scenario validator of `minidem run`, so a mistake here is
the same message a scenario file would get (naming the key, e.g. particles[3].radius).
"""

import sys

import numpy as np

import minidem

radius = 1e-3  # m
# a 4 x 4 x 4 block of centres 2.5 radii apart, its lowest spheres 2 mm above the floor
# (centres at 2 radii + 1 mm)
grid = np.arange(4) * 2.5 * radius + 2.0 * radius
x, y, z = np.meshgrid(grid, grid, grid + 1e-3, indexing="ij")
centres = np.column_stack([x.ravel(), y.ravel(), z.ravel()])

scenario = (minidem.Scenario()
            .material("glass", youngs_modulus=5e6, poisson_ratio=0.3, density=2500.0)
            .contact("hm", friction=0.5, restitution=0.5)
            .wall("box", lower=[0.0, 0.0, 0.0], upper=[0.013, 0.013, 0.05], open_top=True, material="glass")
            .particles(centres, radius, "glass")
            .run_settings(dt=2e-5, stop="time", end_time=0.04, gravity=[0.0, 0.0, -9.81])
            .output(interval=0.004))
out = sys.argv[1] if len(sys.argv) > 1 else "out/multi_particle"
result = scenario.run(out=out)

print(f"{result.scene.n_particles} particles, {result.summary['steps']} steps; "
      f"kinetic energy {result.summary['kinetic_energy_j']:.3g} J at t = {result.time:.3g} s")
print(f"lowest centre {result.position[:, 2].min() * 1e3:.3f} mm (radius {radius * 1e3:g} mm)")

output = minidem.open_results(out)
for time_s, frame in output.series:
    speeds = np.linalg.norm(frame.point_data["velocity"], axis=1)
    print(f"t = {time_s:.3f} s: mean speed {speeds.mean():.4f} m/s, "
          f"mean height {frame.points[:, 2].mean() * 1e3:.2f} mm")

from minidem.results.render import render  # also `minidem render OUT`

for path in render(out, array="velocity"):
    print(f"wrote {path}")
