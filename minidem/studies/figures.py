"""PNG figures of a sweep, laid out like the seed paper's (Thornton et al. 2011).

* ``y1``/``y2``: normalised rebound surface velocity / spin against the normalised angle
  x (Figs 2-3, 5-6, 8-9), with the rigid-body lines of eqs 6-8: y1 = max(x - 7 mu, 0),
  y2 = -5 min(x/7, mu).
* ``et``: tangential restitution against the impact angle (Figs 4, 7, 10), with the
  rigid-body et: 5/7 while the sphere ends rolling, 1 - mu (1 + en)/tan(theta) in gross
  sliding (en = 1).
* ``force_displacement``: tangential force against tangential displacement of each
  case's trace (Figs 11-12).
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

MARKERS = "os^vDx+*<>ph"


def _series_of(sweep, rows):
    """[(label, [rows])] in first-seen order of the non-angle swept values."""

    keys = sweep.series_keys
    positions = [sweep.keys.index(k) for k in keys]
    groups = {s: [] for s in sweep.series()}
    for row, case in zip(rows, sweep.cases):
        if not row.get("error"):
            groups[tuple(case[p] for p in positions)].append(row)
    labels = sweep.series_labels or [", ".join(_value_label(k, v) for k, v in zip(keys, s)) or "run"
                                     for s in groups]
    return list(zip(labels, groups.values()))


def _value_label(key, value):
    return str(value) if key == "contact.law" else f"{key.split('.')[-1]} = {value:g}" if isinstance(
        value, float) else f"{key.split('.')[-1]} = {value}"


def _finish(fig, ax, sweep, path, xlabel, ylabel):
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if sweep.title:
        ax.set_title(sweep.title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    # rendered in memory, then written atomically as every result is (minidem.files):
    # a full disk or a kill never leaves a truncated PNG under the final name
    import io

    from minidem.files import atomic_write

    buffer = io.BytesIO()
    try:
        fig.savefig(buffer, dpi=120, format="png")
    finally:
        plt.close(fig)
    return atomic_write(path, buffer.getvalue())


def rigid_body_y1(x, mu):
    return np.maximum(x - 7.0 * mu, 0.0)


def rigid_body_y2(x, mu):
    return -5.0 * np.minimum(x / 7.0, mu)


def rigid_body_et(angle_deg, mu, en=1.0):
    slide = 1.0 - mu * (1.0 + en) / np.tan(np.radians(angle_deg))
    return np.maximum(slide, 5.0 / 7.0)


def plot_measure(sweep, rows, measure, path, mu):
    """Left: the whole sweep; right: the small-angle range where the laws differ
    (x <= 15 mu, or angle <= 45 deg for et)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    xmax = 0.0
    for i, (label, group) in enumerate(_series_of(sweep, rows)):
        xs = np.array([r["angle_deg" if measure == "et" else "x"] for r in group], dtype=float)
        ys = np.array([r[measure] for r in group], dtype=float)
        order = np.argsort(xs)
        for ax in axes:
            ax.plot(xs[order], ys[order], marker=MARKERS[i % len(MARKERS)], ms=3, lw=1, label=label)
        xmax = max(xmax, float(np.nanmax(xs)) if xs.size else 0.0)
    zoom = 45.0 if measure == "et" else (15.0 * mu if math.isfinite(mu) and mu > 0 else xmax)
    if math.isfinite(mu) and xmax > 0:
        grid = np.linspace(1e-3, xmax, 2000)
        line = {"y1": rigid_body_y1, "y2": rigid_body_y2, "et": rigid_body_et}[measure](grid, mu)
        for ax in axes:
            ax.plot(grid, line, "k--", lw=0.8, label="rigid body (eqs 6-8)")
    axes[1].set_xlim(0.0, min(zoom, xmax))
    inside = [line.get_ydata()[line.get_xdata() <= zoom] for line in axes[1].get_lines()]
    values = np.concatenate([v for v in inside if len(v)]) if inside else np.zeros(1)
    if values.size and np.all(np.isfinite(values)):
        pad = 0.05 * (values.max() - values.min() + 1e-12)
        axes[1].set_ylim(values.min() - pad, values.max() + pad)
    if measure == "et":
        axes[0].set_ylim(0.0, 1.05)
        xlabel, ylabel = "impact angle (deg)", "tangential restitution et"
    else:
        xlabel = "x = 2 tan(theta) / (1 + en)"
        ylabel = {"y1": "y1 = 2 vtr / ((1 + en) Vni)", "y2": "y2 = 2 R wr / ((1 + en) Vni)"}[measure]
    axes[1].set_xlabel(xlabel)
    axes[1].grid(alpha=0.3)
    axes[1].set_title("small angles")
    return _finish(fig, axes[0], sweep, path, xlabel, ylabel)


def plot_force_displacement(sweep, rows, path):
    directory = Path(path).parent  # trace_file is relative to the sweep directory
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for i, (label, group) in enumerate(_series_of(sweep, rows)):
        for row in group:
            if not row.get("trace_file"):
                continue
            trace = np.genfromtxt(directory / row["trace_file"], delimiter=",", names=True)
            tangent = _tangent_of(sweep)
            force = sum(trace[f"tangential_force_{a}_n"] * tangent[j] for j, a in enumerate("xyz"))
            shift = sum(trace[f"tangential_displacement_{a}_m"] * tangent[j] for j, a in enumerate("xyz"))
            inside = trace["normal_overlap_m"] > 0
            suffix = f" ({row['angle_deg']:g} deg)" if len(group) > 1 else ""
            ax.plot(shift[inside] * 1e6, force[inside], lw=1.2, label=label + suffix)
    ax.axhline(0, color="k", lw=0.5)
    ax.axvline(0, color="k", lw=0.5)
    return _finish(fig, ax, sweep, path, "tangential displacement (um)", "tangential force Ft (N)")


def _tangent_of(sweep):
    from minidem.scene import scenario

    scene = scenario.build_scene(scenario.apply_overrides(sweep.base, sweep.overrides(0)), sweep.source)
    return scene.impact.tangent if scene.impact is not None else np.array([1.0, 0.0, 0.0])


def draw(sweep, rows, directory) -> list[Path]:

    directory = Path(directory)
    mu = sweep.friction
    written = []
    for figure in sweep.figures:
        path = directory / f"{figure}.png"
        if figure == "force_displacement":
            if sweep.keep_traces:
                written.append(plot_force_displacement(sweep, rows, path))
        else:
            written.append(plot_measure(sweep, rows, figure, path, mu))
    return written
