"""Geometry, the base layer: contact geometry of spheres with planes, cylinders and
triangles (``primitives``, compiled), neighbour search (``neighbours``: cells, Verlet
lists, mesh candidates) and wall shapes (``walls``: what ``[[walls]]`` tables describe,
flattened for the kernel, and their display surfaces). Imports nothing else of minidem."""
