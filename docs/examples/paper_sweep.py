"""The paper's oblique impact swept from Python: HMD and LS (Thornton, Cummins & Cleary
2011, Figs 5-7) over a few impact angles, the table as arrays, Fig 6 (y2 against x) drawn.

    python docs/examples/paper_sweep.py [OUTPUT.png]

The full figure is `minidem run scenarios/paper/figs05-07_hmd_ls_hm.toml` (31 angles,
three laws); this script keeps to five angles so that it runs in seconds once the two
kernels are compiled.
"""

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display needed
import matplotlib.pyplot as plt

import minidem

SCENARIO = Path(__file__).resolve().parents[2] / "scenarios" / "oblique.toml"

table = minidem.sweep(SCENARIO, cases={"contact.law": ["hmd", "ls"],
                                       "impact.angle_deg": [2.0, 5.0, 10.0, 20.0, 45.0]}, workers=1)
print(f"{'law':<5} {'angle':>6} {'x':>8} {'y1':>9} {'y2':>9} {'et':>8}")
for row in table.rows:
    print(f"{row['law']:<5} {row['angle_deg']:>6.1f} {row['x']:>8.4f} {row['y1']:>9.5f} {row['y2']:>9.5f} "
          f"{row['et']:>8.5f}")

# Fig 6: normalised rebound spin against the normalised impact angle, with the
# gross-sliding limit y2 = -5 mu (paper eq 8) the curves reach at large x
mu = minidem.load(SCENARIO).data["contact"]["friction"]
figure, axes = plt.subplots(figsize=(5, 4))
for law in ("hmd", "ls"):
    mine = table["law"] == law
    axes.plot(table["x"][mine], table["y2"][mine], "o-", label=law)
axes.axhline(-5 * mu, color="grey", linestyle="--", label="gross sliding, eq 8")
axes.set_xlabel("x = 2 tan(theta) / (1 + en)")
axes.set_ylabel("y2 (normalised rebound spin)")
axes.legend()
figure.tight_layout()
target = sys.argv[1] if len(sys.argv) > 1 else "paper_sweep.png"
figure.savefig(target, dpi=100)
print(f"wrote {target}")
