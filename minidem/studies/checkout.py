"""Where the project's own files are: the studies that measure the shipped scenes
(``minidem bench``) read ``scenarios/`` and write ``docs/benchmarks.md`` of a clone of
minidem, and its LIGGGHTS comparison reads ``../shared/bench`` beside the clone. An
installed package (``pip install .``) holds none of them, so the clone is the one the
package was installed from in place (an editable install), else the working directory or
a folder above it."""

from __future__ import annotations

from pathlib import Path


def _is_clone(folder: Path) -> bool:
    return (folder / "pyproject.toml").is_file() and (folder / "scenarios" / "oblique.toml").is_file()


def find_root(package_parent: Path | None = None, cwd: Path | None = None) -> Path:
    """The clone's top folder; the package's parent folder when no clone is found (then
    :func:`require` refuses). Defaults: this package's parent folder, the working
    directory."""
    package_parent = package_parent or Path(__file__).resolve().parents[2]
    cwd = (cwd or Path.cwd()).resolve()
    for folder in (package_parent, cwd, *cwd.parents):
        if _is_clone(folder):
            return folder
    return package_parent


ROOT = find_root()


class NoCheckout(Exception):
    """The project's files are not where a study needs them."""


def require(root: Path | None = None) -> Path:
    """``root`` (default ROOT), or NoCheckout naming what is missing and how to get it."""
    root = root or ROOT
    if not _is_clone(root):
        raise NoCheckout(
            "minidem bench measures the project's shipped scenes: it needs a clone of minidem "
            "(pyproject.toml and scenarios/ in one folder), and none was found in the installed "
            f"package's folder ({Path(__file__).resolve().parents[2]}) nor in {Path.cwd()} or a folder "
            "above it; run it from the clone you installed from (cd minidem && minidem bench)")
    return root
