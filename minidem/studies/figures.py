"""PNG figures of a sweep, laid out like the seed paper's (Thornton et al. 2011).

* ``y1``/``y2``: normalised rebound surface velocity / spin against the normalised angle
  x (Figs 2-3, 5-6, 8-9), with the rigid-body lines of eqs 6-8: y1 = max(x - 7 mu, 0),
  y2 = -5 min(x/7, mu).
* ``et``: tangential restitution against the impact angle (Figs 4, 7, 10), with the
  rigid-body et: 5/7 while the sphere ends rolling, 1 - mu (1 + en)/tan(theta) in gross
  sliding (en = 1).
* ``force_displacement``: tangential force against tangential displacement of each
  case's trace (Figs 11-12).

and those of Chung & Ooi (2011), against the swept key ``[sweep].abscissa``:
``hertz`` (tests 1-2), ``restitution`` (test 3), ``rebound`` (tests 4-8) and
``force_time`` (the traced normal force of sphere-wall cases).
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
    groups = {s: [] for s in sweep.series()}
    for row, case in zip(rows, sweep.cases):
        if not row.get("error"):
            groups[sweep.series_of(case)].append(row)
    labels = sweep.series_labels or [", ".join(_value_label(k, v) for k, v in zip(sweep.series_keys, s)) or "run"
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
        elif figure == "force_time":
            if sweep.keep_traces:
                written.append(plot_force_time(sweep, rows, path))
        elif figure in COLLISION_PLOTS:
            written.append(COLLISION_PLOTS[figure](sweep, rows, path))
        else:
            written.append(plot_measure(sweep, rows, figure, path, mu))
    return written


# ---------------------------------------------------------------------------------
# Chung & Ooi (2011) figures: rows against the swept key sweep.abscissa
# ---------------------------------------------------------------------------------
def _abscissa_series(sweep, rows):
    """[(label, xs, rows sorted by x)] with x the value of sweep.abscissa of each row."""
    position = sweep.keys.index(sweep.abscissa)
    by_case = {row["case"]: row for row in rows}
    categories = _categories(sweep)
    out = []
    for label, group in _series_of(sweep, rows):
        values = [sweep.cases[row["case"]][position] for row in group]
        xs = np.array([categories.index(v) if categories else float(v) for v in values], dtype=float)
        order = np.argsort(xs, kind="stable")
        out.append((label, xs[order], [by_case[group[k]["case"]] for k in order]))
    return out


def _categories(sweep):
    """The abscissa's values in first-seen order when they are not numbers (materials,
    say), drawn at 0, 1, 2...; [] for a numeric abscissa."""
    position = sweep.keys.index(sweep.abscissa)
    values = list(dict.fromkeys(case[position] for case in sweep.cases))
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    return [] if numeric else values


def _category_ticks(sweep, ax):
    categories = _categories(sweep)
    if categories:
        ax.set_xticks(range(len(categories)), [str(c) for c in categories])
        ax.set_xlim(-0.5, len(categories) - 0.5)


def _column(group, name):
    return np.array([np.nan if row.get(name) in (None, "") else float(row[name]) for row in group])


def _panels(sweep, rows, path, panels, xlabel):
    """One subplot per (measure column, theory column or None, label, scale) with every
    series as markers and its theory as a dashed line of the same colour."""
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.2), squeeze=False)
    for ax, (measure, theory, ylabel, scale) in zip(axes[0], panels):
        drawn = []  # theory curves already drawn: laws that share materials share them
        series = _abscissa_series(sweep, rows)
        distinct = [] if theory is None else _distinct_curves(series, theory, scale)
        for i, (label, xs, group) in enumerate(series):
            (line,) = ax.plot(xs, _column(group, measure) * scale, marker=MARKERS[i % len(MARKERS)], ms=4, lw=0.8,
                              label=label)
            if theory is None:
                continue
            curve = _column(group, theory) * scale
            if any(len(x) == len(xs) and np.allclose(x, xs) and np.allclose(c, curve, equal_nan=True)
                   for x, c in drawn):
                continue
            drawn.append((xs, curve))
            kind = "Hertz theory" if theory.startswith("hertz") else "rigid-body theory"
            ax.plot(xs, curve, "--", color=line.get_color() if distinct > 1 else "k", lw=1.0,
                    label=f"{label}: {kind}" if distinct > 1 else kind)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        _category_ticks(sweep, ax)
    axes[0][0].legend(fontsize=7)
    if sweep.title:
        fig.suptitle(sweep.title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _distinct_curves(series, theory, scale) -> int:
    curves = []
    for _, xs, group in series:
        curve = _column(group, theory) * scale
        if not any(len(x) == len(xs) and np.allclose(x, xs) and np.allclose(c, curve, equal_nan=True)
                   for x, c in curves):
            curves.append((xs, curve))
    return len(curves)


def _abscissa_label(sweep):
    """The abscissa's key as a label with its unit from the scenario schema, e.g.
    "impact.spin (rad/s)", "particles.0.angular_velocity.2 (rad/s)"."""
    from minidem.scene import scenario

    parts = scenario.key_path(sweep.abscissa, "sweep.abscissa")
    keys = scenario.SCHEMA.get(parts[0], (None, ()))[1]
    names = [p for p in parts[1:] if not p.isdigit()]
    unit = next((k.unit for k in keys if names and k.name == names[-1]), "")
    return sweep.abscissa + (f" ({unit})" if unit and unit != "-" else "")


def plot_hertz(sweep, rows, path):
    """Tests 1-2: max overlap, peak force and contact duration beside Hertz theory."""
    return _panels(sweep, rows, path, [("max_overlap_m", "hertz_max_overlap_m", "max overlap (um)", 1e6),
                                       ("peak_normal_force_n", "hertz_peak_force_n", "peak normal force (kN)", 1e-3),
                                       ("contact_duration_s", "hertz_contact_time_s", "contact duration (us)", 1e6)],
                   _abscissa_label(sweep))


def plot_restitution(sweep, rows, path):
    """Test 3: the restitution obtained against the one requested (the line en = e)."""
    fig, ax = plt.subplots(figsize=(5.5, 4.8))
    for i, (label, xs, group) in enumerate(_abscissa_series(sweep, rows)):
        ax.plot(xs, _column(group, "en"), marker=MARKERS[i % len(MARKERS)], ms=5, lw=0.8, label=label)
    ax.plot([0, 1], [0, 1], "k--", lw=0.8, label="en = e (requested)")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    return _finish(fig, ax, sweep, path, "requested restitution e", "restitution obtained en")


def plot_rebound(sweep, rows, path):
    """Tests 4-8: particle 0's rebound beside rigid-body impulse theory."""
    return _panels(sweep, rows, path, [
        ("tangential_velocity_m_s", "rigid_tangential_velocity_m_s", "rebound tangential velocity (m/s)", 1.0),
        ("spin_rad_s", "rigid_spin_rad_s", "rebound spin (rad/s)", 1.0),
        ("rebound_angle_deg", "rigid_rebound_angle_deg", "rebound angle (deg)", 1.0),
        ("recoil_ratio", "rigid_recoil_ratio", "recoil ratio V'st / V'cn", 1.0)], _abscissa_label(sweep))


def plot_force_time(sweep, rows, path):
    """Tests 2-3: the normal force of each traced sphere-wall case against time from first touch."""
    directory = Path(path).parent
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for label, xs, group in _abscissa_series(sweep, rows):
        for x, row in zip(xs, group):
            if not row.get("trace_file"):
                continue
            trace = np.genfromtxt(directory / row["trace_file"], delimiter=",", names=True)
            inside = trace["normal_overlap_m"] > 0
            if not inside.any():
                continue
            start = trace["time_s"][inside][0]
            suffix = f" ({_abscissa_label(sweep)} = {x:g})" if len(group) > 1 else ""
            ax.plot((trace["time_s"][inside] - start) * 1e6, trace["normal_force_n"][inside], lw=1.2,
                    label=label + suffix)
    ax.axhline(0, color="k", lw=0.5)
    return _finish(fig, ax, sweep, path, "time from first touch (us)", "normal force Fn (N)")


COLLISION_PLOTS = {"hertz": plot_hertz, "restitution": plot_restitution, "rebound": plot_rebound}
