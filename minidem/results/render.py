"""Pictures of a run without ParaView: ``minidem render OUT`` (docs/cli.md).

The particle series an output directory holds (particles.pvd, see
:mod:`minidem.results.vtk`) is drawn with pyvista: every particle a sphere of its
radius, coloured by one of its arrays (a vector by its magnitude), the walls (walls.vtu)
translucent grey. A PNG of one frame (the last by default), and a GIF of the series
when it has more than one frame (the same camera and colour range in every frame, so
the frames compare).

Off-screen on a machine without a display: VTK's pip wheels (9.4 and later) render
through EGL when there is no X server; on Linux that needs Mesa's EGL driver (Debian:
libegl1, libegl-mesa0, libgl1-mesa-dri; llvmpipe renders on the CPU). The default
window is chosen before VTK tries X (``VTK_DEFAULT_OPENGL_WINDOW``), so a headless run
prints no X error.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np

from minidem.errors import MinidemError
from minidem.results.output import PARTICLE_ARRAYS, Output

SPHERE_RESOLUTION = 16  # facets around a glyph sphere: round at a few hundred pixels, cheap for 10^4 particles
WINDOW = (1024, 768)


class RenderError(MinidemError):
    """Nothing to render: no such directory, no particle series, no such array or frame."""


class NoRenderWindow(RenderError):
    """No off-screen OpenGL context on this machine (a missing EGL driver)."""


def off_screen() -> None:
    """Off-screen rendering: with no X display, VTK's EGL window (not an X one that
    fails with an error message first)."""
    if not os.environ.get("DISPLAY") and sys.platform.startswith("linux"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista

    pyvista.OFF_SCREEN = True


def colour_array(mesh, name: str) -> tuple[np.ndarray, str]:
    """The values to colour by (a vector array by its magnitude) and the colour bar's title."""
    if name not in mesh.point_data:
        raise RenderError(f"--array {name}: not a particle array; arrays: {', '.join(mesh.point_data.keys())}")
    values = np.asarray(mesh.point_data[name], dtype=np.float64)
    unit = PARTICLE_ARRAYS.get(name, "")
    title = f"{name} ({unit})" if unit else name
    if values.ndim == 2:
        values, title = np.linalg.norm(values, axis=1), f"{name} magnitude" + (f" ({unit})" if unit else "")
    return values, title


def _spheres(mesh, values: np.ndarray):
    import pyvista

    cloud = pyvista.PolyData(np.asarray(mesh.points))
    cloud.point_data["radius"] = np.asarray(mesh.point_data["radius"])
    cloud.point_data["colour"] = values
    # the glyph source has unit diameter: scaled by 2 radius it is the particle
    source = pyvista.Sphere(radius=0.5, theta_resolution=SPHERE_RESOLUTION, phi_resolution=SPHERE_RESOLUTION)
    return cloud.glyph(scale="radius", factor=2.0, geom=source, orient=False)


class _Scene:
    """A plotter with the walls, one particle frame at a time, a fixed camera and colour range."""

    def __init__(self, walls, frames: list, name: str, window=WINDOW):
        import pyvista

        off_screen()
        try:
            self.plotter = pyvista.Plotter(off_screen=True, window_size=list(window))
        except Exception as exc:  # noqa: BLE001 - VTK raises many kinds when no OpenGL context can be had
            raise NoRenderWindow(f"cannot open an off-screen render window: {type(exc).__name__}: {exc}. On Linux "
                              "without a display VTK renders through EGL: install Mesa's EGL driver (Debian: "
                              "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)") from None
        self.name = name
        values = [colour_array(m, name) for m in frames]
        self.title = values[0][1]
        low = min(float(v.min()) for v, _ in values) if frames else 0.0
        high = max(float(v.max()) for v, _ in values) if frames else 1.0
        # one value everywhere (a bed at rest: every force its weight): a range around it
        self.range = (low, high) if high > low else (low - abs(low) - 1e-300, high + abs(high) + 1e-300)
        self.plotter.set_background("white")
        # the camera sees every frame's particles, placed once on their joint bounds; the
        # walls are cut to a margin around them (a settling box 1 m tall would hide a
        # 2 cm bed, an infinite plane's rectangle dwarf the spheres)
        radius = max(float(np.max(m.point_data["radius"])) for m in frames)
        bounds = np.array([m.bounds for m in frames])
        lower, upper = bounds[:, 0::2].min(axis=0) - radius, bounds[:, 1::2].max(axis=0) + radius
        margin = 0.25 * float(np.max(upper - lower))
        self.bounds = [lower[0], upper[0], lower[1], upper[1], lower[2], upper[2]]
        if walls is not None and walls.n_cells:
            box = [lower[0] - margin, upper[0] + margin, lower[1] - margin, upper[1] + margin,
                   lower[2] - margin, upper[2] + margin]
            shown = walls.clip_box(box, invert=False)
            if shown.n_cells:
                # back faces culled: a wall's normal points to the particles (walls.vtu keeps it), so
                # the walls between the camera and the particles are not drawn over them
                self.plotter.add_mesh(shown, color="lightgrey", opacity=0.5, culling="back")
        self.actor = None
        self.text = None
        self.placed = False

    def show(self, mesh, time_s: float | None):
        values, _ = colour_array(mesh, self.name)
        if self.actor is not None:
            self.plotter.remove_actor(self.actor)
        self.actor = self.plotter.add_mesh(
            _spheres(mesh, values), scalars="colour", clim=self.range, cmap="viridis", smooth_shading=True,
            scalar_bar_args={"title": self.title, "color": "black", "vertical": False, "width": 0.5,
                             "height": 0.1, "position_x": 0.25, "position_y": 0.01, "fmt": "%.3g",
                             "title_font_size": 14, "label_font_size": 12})
        # the labels and the title under the bar, a few pixels apart: over it (VTK's
        # default) the title was written across the middle label
        bar = self.plotter.scalar_bars[self.title]
        bar.SetTextPositionToPrecedeScalarBar()
        bar.SetVerticalTitleSeparation(6)
        if self.text is not None:
            self.plotter.remove_actor(self.text)
        if time_s is not None:
            self.text = self.plotter.add_text(f"t = {time_s:.6g} s", position="upper_left", font_size=12,
                                              color="black")
        if not self.placed:
            self.plotter.view_isometric()
            self.plotter.reset_camera(bounds=self.bounds)
            self.placed = True

    def image(self) -> np.ndarray:
        return self.plotter.screenshot(return_img=True)

    def close(self):
        self.plotter.close()


def render(directory: str | Path, array: str = "velocity", png: str | Path | None = None,
           animation: str | Path | None = None, frame: int = -1, fps: float = 10.0, max_frames: int = 200,
           window=WINDOW, notify=None) -> list[Path]:
    """Draw the particle series in ``directory``: frame ``frame`` to ``png`` (default
    DIR/render.png) and, when the series has more than one frame, every frame (at most
    ``max_frames``, evenly picked) to the GIF ``animation`` (default DIR/render.gif;
    "" for none). Returns the files written. ``notify(text)``: told, in one line, what
    is being read and drawn (the CLI prints it: a long series takes tens of seconds)."""
    from PIL import Image

    from minidem import files

    # checked before any work: a GIF frame lasts a whole number of centiseconds, and
    # browsers play a delay below 2 of them at 10 frames per second
    if not (math.isfinite(fps) and 0.0 < fps <= 50.0):
        raise RenderError(f"--fps {fps:g}: expected frames per second in (0, 50], e.g. 10")
    try:
        output = Output(directory)
    except MinidemError as exc:
        raise RenderError(str(exc)) from None
    series = output.series
    if series is None or len(series) == 0:
        raise RenderError(f"{output.directory}: no particle series (particles.pvd) to render: run the scene with "
                          "output.vtk = true (the default for scenes without [impact])")
    if not -len(series) <= frame < len(series):
        raise RenderError(f"--frame {frame}: the series has {len(series)} frame(s) (0..{len(series) - 1}, or "
                          "negative from the end)")
    # an array the frames do not have is refused before the long read (a user's audit)
    shown = series[frame % len(series)]
    colour_array(shown, array)
    png = Path(png) if png else output.directory / "render.png"
    written = []
    picked = (np.unique(np.linspace(0, len(series) - 1, min(len(series), max_frames)).round().astype(int))
              if len(series) > 1 and animation != "" else np.array([], dtype=int))
    if notify is not None:
        notify(f"reading and drawing {len(picked) or 1} frame(s) of {output.directory / 'particles.pvd'}"
               + (f" (the GIF: {len(picked)} of {len(series)})" if len(picked) else ""))
    meshes = {int(k): series[int(k)] for k in set(picked.tolist()) - {frame % len(series)}}
    meshes[frame % len(series)] = shown
    scene = _Scene(output.walls, list(meshes.values()), array, window)
    try:
        scene.show(meshes[frame % len(series)], float(series.times[frame]))
        written.append(_write_png(png, scene.image(), files))
        if len(picked):
            target = Path(animation) if animation else output.directory / "render.gif"
            images = []
            for k in picked:
                scene.show(meshes[int(k)], float(series.times[k]))
                images.append(Image.fromarray(scene.image()).convert("P", palette=Image.ADAPTIVE))
            import io

            buffer = io.BytesIO()
            images[0].save(buffer, format="GIF", save_all=True, append_images=images[1:],
                           duration=int(round(1000.0 / fps)), loop=0)
            written.append(files.atomic_write(target, buffer.getvalue()))
    finally:
        scene.close()
    return written


def _write_png(path: Path, image: np.ndarray, files) -> Path:
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return files.atomic_write(path, buffer.getvalue())
