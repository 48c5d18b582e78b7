"""Wall geometry: the shapes a scenario's ``[[walls]]`` tables describe, turned into
the flat arrays the kernel reads, and surfaces for VTK.

Kinds (``type``):

* ``plane``: an infinite plane through ``point`` with unit ``normal`` towards the spheres;
* ``box``: the inside of the axis-aligned box ``lower``..``upper``, as 6 planes (5 with
  ``open_top``: no plane at the upper z face);
* ``cylinder``: the inside surface of a finite cylinder (a silo) of ``radius`` whose
  axis runs from ``point`` along ``axis`` for ``length``; ``bottom`` adds a plane
  closing it at ``point``. Open ends: beyond its length the surface does not exist;
* ``mesh``: triangles read from an STL/OBJ/... file with meshio, scaled by ``scale`` and
  shifted by ``offset``. A sphere-triangle contact is with the closest point of the
  triangle (face, edge or vertex); see ``minidem.engine.kernel.mesh_forces`` for how one
  contact per feature is kept where triangles share edges. Both sides of a triangle
  repel, so a mesh need not be closed or consistently oriented.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np


@dataclasses.dataclass
class WallSet:
    """Every wall of a scene, flattened per kind (SI units, float64)."""

    plane_point: np.ndarray  # (P, 3)
    plane_normal: np.ndarray  # (P, 3) unit
    plane_material: np.ndarray  # (P,) int64
    cylinder_base: np.ndarray  # (C, 3)
    cylinder_axis: np.ndarray  # (C, 3) unit
    cylinder_radius: np.ndarray  # (C,)
    cylinder_length: np.ndarray  # (C,)
    cylinder_material: np.ndarray  # (C,) int64
    triangles: np.ndarray  # (T, 3, 3): vertex k of triangle t is triangles[t, k]
    triangle_material: np.ndarray  # (T,) int64
    meshes: list  # (vertices, faces) per mesh wall, for display
    # where each cylinder / triangle came from, for messages: the index of its [[walls]]
    # table and, for meshes, the file
    cylinder_table: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    triangle_table: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    mesh_files: dict = dataclasses.field(default_factory=dict)  # [[walls]] index -> file path
    # per plane: its [[walls]] table, what it is ("plane", "box lower-x face", "cylinder
    # bottom"), and extra half-spaces that bound it for display only (an open box's
    # sides end at its upper corner; physically they are infinite planes)
    plane_table: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    plane_label: list = dataclasses.field(default_factory=list)
    plane_display_bounds: list = dataclasses.field(default_factory=list)
    mesh_table: list = dataclasses.field(default_factory=list)  # per entry of ``meshes``

    def set_planes(self, point, normal, material, origin=None) -> None:
        """The plane walls, with where each came from: ``origin`` per plane is
        ([[walls]] table, what it is, display bounds), see the fields above; None for
        planes that belong to no table (a Scene built by hand)."""
        self.plane_point, self.plane_normal, self.plane_material = point, normal, material
        if origin is None:
            origin = [(-1, "plane", [])] * point.shape[0]
        self.plane_table = np.array([table for table, _, _ in origin], dtype=np.int64)
        self.plane_label = [label for _, label, _ in origin]
        self.plane_display_bounds = [bounds for _, _, bounds in origin]

    def plane_name(self, w: int) -> str:
        """The plane wall w as a user wrote it: its [[walls]] table and what it is."""
        geometry = f"the plane through {self.plane_point[w].tolist()} with normal {self.plane_normal[w].tolist()}"
        if self.plane_table[w] >= 0:
            label = "" if self.plane_label[w] == "plane" else f"{self.plane_label[w]}: "
            return f"walls[{int(self.plane_table[w])}] ({label}{geometry})"
        return f"plane {w} ({geometry})"

    def display_tables(self) -> np.ndarray:
        """The [[walls]] table of every surface of :func:`display_meshes`, in its order."""
        return np.concatenate([np.asarray(self.plane_table, dtype=np.int64),
                               np.asarray(self.cylinder_table, dtype=np.int64),
                               np.asarray(self.mesh_table, dtype=np.int64)])

    @classmethod
    def empty(cls) -> "WallSet":
        z3, zi = np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        return cls(z3, z3.copy(), zi, z3.copy(), z3.copy(), np.zeros(0), np.zeros(0), zi.copy(),
                   np.zeros((0, 3, 3)), zi.copy(), [])


def box_planes(lower, upper, open_top: bool = False) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """(point, inward normal, which face) of the faces of an axis-aligned box."""
    lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    planes = []
    for axis in range(3):
        for corner, sign, side in ((lower, 1.0, "lower"), (upper, -1.0, "upper")):
            if open_top and axis == 2 and sign < 0:
                continue
            normal = np.zeros(3)
            normal[axis] = sign
            planes.append((corner.copy(), normal, f"{side}-{'xyz'[axis]} face"))
    return planes


def read_mesh(path: str | Path, scale: float = 1.0, offset=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (K, 3) m, triangles (F, 3) int) of a surface mesh file; polygons with
    more than three corners are fanned into triangles. Raises ValueError on a file
    meshio cannot read or one without surface cells."""
    import meshio

    if Path(path).is_dir():
        raise ValueError(f"mesh file '{path}' is a directory; give a surface mesh file (STL, OBJ, PLY, VTK, ...)")
    if not Path(path).is_file():
        raise ValueError(f"no such mesh file '{path}'")
    if Path(path).suffix.lower() == ".stl":
        _check_stl(Path(path))
    try:
        with warnings.catch_warnings():
            # meshio first tries an ASCII STL as binary, overflowing a header count
            warnings.simplefilter("ignore", RuntimeWarning)
            mesh = meshio.read(str(path))
    except UnicodeDecodeError as exc:  # a text format's reader given bytes that are not text
        kind = Path(path).suffix.lstrip(".").upper() or "mesh"
        raise ValueError(f"cannot read mesh '{path}': not {'an' if kind[0] in 'AEIOU' else 'a'} {kind} file "
                         f"meshio can read (it reads text where the file has bytes that are not: "
                         f"{exc.object[exc.start:exc.start + 1]!r} at byte {exc.start})") from None
    except Exception as exc:  # noqa: BLE001 - meshio raises many types for bad files
        raise ValueError(f"cannot read mesh '{path}': {exc}") from None
    faces = []
    for block in mesh.cells:
        data = np.asarray(block.data)
        if block.type == "triangle":
            faces.append(data)
        elif block.type in ("quad", "polygon") and data.ndim == 2:
            for k in range(1, data.shape[1] - 1):
                faces.append(data[:, [0, k, k + 1]])
    if not faces:
        raise ValueError(f"mesh '{path}' has no triangles or polygons (cell types: "
                         f"{', '.join(b.type for b in mesh.cells) or 'none'})")
    vertices = np.asarray(mesh.points, dtype=np.float64)
    if vertices.shape[1] == 2:
        vertices = np.column_stack([vertices, np.zeros(len(vertices))])
    with np.errstate(all="ignore"):
        vertices = vertices * scale + np.asarray(offset, dtype=np.float64)
    faces = np.concatenate(faces).astype(np.int64)
    _check_triangles(path, vertices, faces, scale)
    return vertices, faces


def _check_stl(path: Path) -> None:
    """A file named .stl that is neither a whole binary STL (84-byte header, then 50 bytes
    a triangle) nor ASCII STL text: say which, before meshio reports a decode error or a
    mesh with no triangles."""
    data = path.read_bytes()
    if data[:5].lower() == b"solid":
        try:
            text = data.decode("ascii")
        except UnicodeDecodeError as exc:
            text = None
            where = exc.start
        if text is not None:
            # facets but no closing line: cut short (text without facets is left to meshio)
            if "facet" in text.lower() and "endsolid" not in text[-4096:].lower():
                raise ValueError(f"mesh '{path}' is truncated: an ASCII STL ({len(data)} bytes) without its "
                                 "closing 'endsolid' line (a copy or download cut short?)")
            return
        if len(data) < 84 or len(data) != 84 + 50 * int.from_bytes(data[80:84], "little"):
            raise ValueError(f"mesh '{path}' is not an STL file: it starts like ASCII STL ('solid') but byte "
                             f"{where} is not ASCII text, and it is not a binary STL either")
        return  # a binary STL whose header happens to start with 'solid' (common)
    if len(data) < 84:
        raise ValueError(f"mesh '{path}' is not an STL file or is truncated: {len(data)} bytes, less than the "
                         "84-byte header of a binary STL")
    count = int.from_bytes(data[80:84], "little")
    expected = 84 + 50 * count
    if len(data) < expected:
        raise ValueError(f"mesh '{path}' is truncated or not an STL file: its binary STL header announces "
                         f"{count} triangles ({expected} bytes), the file has {len(data)} bytes")
    if len(data) > expected:
        raise ValueError(f"mesh '{path}' is not an STL file: neither ASCII STL (starting with 'solid') nor a "
                         f"binary STL ({len(data)} bytes where its header's {count} triangles need {expected})")


def _check_triangles(path, vertices: np.ndarray, faces: np.ndarray, scale: float) -> None:
    """Every vertex finite and every triangle a real one (non-zero area): a NaN corner or a
    degenerate triangle has no normal, and a sphere would pass through it unseen."""
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"mesh '{path}': a triangle refers to vertex {int(faces.max())}, the file has "
                         f"{len(vertices)} vertices")
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if bad.size:
        raise ValueError(f"mesh '{path}': vertex {int(bad[0])} is {vertices[bad[0]].tolist()} after scale = "
                         f"{scale:g} (a NaN or infinite coordinate{', and ' + str(bad.size - 1) + ' more' if bad.size > 1 else ''}); "
                         "repair the file or give a scale that keeps coordinates finite")
    corners = vertices[faces]
    with np.errstate(all="ignore"):
        edge1, edge2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
        twice_area = np.linalg.norm(np.cross(edge1, edge2), axis=1)
        longest = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
        # zero area, or collinear corners to round-off: no normal can be defined
        degenerate = np.flatnonzero(~(twice_area > 1e-12 * longest**2) | ~np.isfinite(twice_area))
    if degenerate.size:
        first = [int(t) for t in degenerate[:5]]
        raise ValueError(f"mesh '{path}': {degenerate.size} of {len(faces)} triangles have zero area (corners "
                         f"coincident or in a line), e.g. triangle(s) {first}: {corners[first[0]].tolist()}; "
                         "remove them (e.g. MeshLab 'Remove Zero Area Faces') or check the file's scale")


def cylinder_surface(base, axis, radius, length, segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A triangulated tube for display."""
    axis = np.asarray(axis, dtype=np.float64)
    helper = np.zeros(3)
    helper[np.argmin(np.abs(axis))] = 1.0
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    angle = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring = radius * (np.cos(angle)[:, None] * u + np.sin(angle)[:, None] * v)
    vertices = np.concatenate([base + ring, base + length * axis + ring])
    k = np.arange(segments)
    nxt = (k + 1) % segments
    faces = np.concatenate([np.column_stack([k, nxt, k + segments]),
                            np.column_stack([nxt, nxt + segments, k + segments])])
    return vertices, faces


def plane_to_quad(point, normal, half_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Finite square stand-in for an infinite plane, for display only.

    Returns ``(vertices (4, 3), faces (1, 4))``: a square of side ``2 * half_size``
    [m] centred on ``point`` and lying in the plane; the vertices are ordered
    counter-clockwise seen from the side ``normal`` points to, so the quad's normal
    (right-hand rule) equals ``normal`` and ParaView's lighting/back-face culling
    treat the side the particles live on as the front.
    """
    p = np.asarray(point, dtype=np.float64).reshape(3)
    n = np.asarray(normal, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(n)
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError("plane normal must be a non-zero finite vector")
    if not half_size > 0.0:
        raise ValueError("half_size must be positive")
    n = n / norm
    # Cross with the axis least aligned with n, which keeps the result well
    # conditioned for every normal direction.
    helper = np.zeros(3)
    helper[np.argmin(np.abs(n))] = 1.0
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)  # u x v == n
    h = float(half_size)
    vertices = np.array([p - h * u - h * v, p + h * u - h * v,
                         p + h * u + h * v, p - h * u + h * v])
    return vertices, np.array([[0, 1, 2, 3]], dtype=np.int64)


def display_meshes(walls: WallSet, extent_lower, extent_upper) -> list[tuple[np.ndarray, np.ndarray]]:
    """Surfaces of all walls for VTK, one mesh per wall in the order of ``WallSet``.

    An infinite plane is drawn as the part of it that faces the particles' side of every
    other plane (a box's faces come out as the box's own rectangles, a hopper's walls
    meet at their edges), within a square around the scene: the particles' extent, grown
    to reach every plane's reference point."""

    lower, upper = np.asarray(extent_lower, dtype=np.float64), np.asarray(extent_upper, dtype=np.float64)
    centre = 0.5 * (lower + upper)
    half = 0.5 * float(np.max(upper - lower)) or 1.0
    planes = list(zip(walls.plane_point, walls.plane_normal))
    if len(planes) > 1:
        # 2x the farthest reference point: large enough that the clipping planes, not
        # the square, bound a box face
        half = max(half, 2.0 * max(float(np.linalg.norm(point - centre)) for point, _ in planes))
    out = []
    for index, (point, normal) in enumerate(planes):
        # the square is centred on the projection of the scene's centre onto the plane
        foot = centre - float(np.dot(centre - point, normal)) * normal
        square = plane_to_quad(foot, normal, half)
        polygon = square[0]
        for other, (other_point, other_normal) in enumerate(planes + list(walls.plane_display_bounds[index])):
            if other != index:
                polygon = _clip_polygon(polygon, other_point, other_normal, 1e-12 * half)
        if len(polygon) < 3:  # nothing faces the particles: show the plain square
            out.append(square)
        else:  # a convex polygon: a fan of triangles
            fan = np.array([[0, k, k + 1] for k in range(1, len(polygon) - 1)], dtype=np.int64)
            out.append((np.asarray(polygon), fan))
    for c in range(walls.cylinder_base.shape[0]):
        out.append(cylinder_surface(walls.cylinder_base[c], walls.cylinder_axis[c], walls.cylinder_radius[c],
                                    walls.cylinder_length[c]))
    out.extend(walls.meshes)
    return out


def _clip_polygon(vertices, point, normal, tolerance: float) -> np.ndarray:
    """The part of a convex polygon on the side ``normal`` points to (Sutherland-Hodgman
    against one plane); the vertex order, and so the face normal, is kept."""
    vertices = np.asarray(vertices)
    if len(vertices) == 0:
        return vertices
    side = (vertices - point) @ normal
    kept = []
    for k in range(len(vertices)):
        current, following = vertices[k], vertices[(k + 1) % len(vertices)]
        here, there = side[k], side[(k + 1) % len(vertices)]
        if here >= -tolerance:
            kept.append(current)
        if (here >= -tolerance) != (there >= -tolerance):
            kept.append(current + (here / (here - there)) * (following - current))
    return np.array(kept).reshape(-1, 3)


def initial_wall_overlaps(walls: WallSet, position: np.ndarray, radius: np.ndarray,
                          tolerance: float) -> list[tuple[int, str, float, bool]]:
    """Particles that overlap a cylinder or a mesh triangle by more than ``tolerance``
    times their radius: (particle, description of the wall, overlap m, centre behind it).

    The overlaps are those the kernel computes (``minidem.geometry.primitives.cylinder_overlap``,
    ``triangle_closest_point``); planes are checked by ``minidem.scene.scenario`` itself.
    """
    from minidem.geometry.primitives import cylinder_overlap, triangle_closest_point
    from minidem.geometry.neighbours import mesh_candidates

    found = []
    for c in range(walls.cylinder_base.shape[0]):
        where = (f"walls[{int(walls.cylinder_table[c])}]" if c < len(walls.cylinder_table) else f"cylinder {c}")
        text = (f"{where} (the cylinder of radius {walls.cylinder_radius[c]:g} m from "
                f"{walls.cylinder_base[c].tolist()} along {walls.cylinder_axis[c].tolist()})")
        for i in range(position.shape[0]):
            overlap = cylinder_overlap(position[i, 0], position[i, 1], position[i, 2], radius[i], walls.cylinder_base,
                                       walls.cylinder_axis, walls.cylinder_radius, walls.cylinder_length, c)[0]
            if overlap > tolerance * radius[i]:
                found.append((i, text, float(overlap), bool(overlap >= radius[i])))
    if walls.triangles.shape[0] and position.shape[0]:
        # a zero skin lists exactly the triangles closer than the radius
        offsets, candidates = mesh_candidates(position, radius, 0.0, walls.triangles)
        for i in range(position.shape[0]):
            for t in candidates[offsets[i]:offsets[i + 1]]:
                cx, cy, cz, _ = triangle_closest_point(position[i, 0], position[i, 1], position[i, 2],
                                                        walls.triangles, t)
                overlap = float(radius[i] - np.linalg.norm(position[i] - (cx, cy, cz)))
                if overlap > tolerance * radius[i]:
                    table = int(walls.triangle_table[t]) if t < len(walls.triangle_table) else -1
                    name = walls.mesh_files.get(table, "")
                    text = (f"triangle {int(t)} of the mesh walls[{table}]" + (f" ('{name}')" if name else "")
                            if table >= 0 else f"mesh triangle {int(t)}")
                    found.append((i, text, overlap, False))
    return found
