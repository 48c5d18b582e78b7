"""Input: a scenario file (TOML) or a dict becomes a validated :class:`Scene`
(``scenario``), with its particles from the generators of ``fills`` (lattice, random
packing, CSV/VTK files). Every check that names a file, a key and what would be valid
lives here, before anything is compiled."""
