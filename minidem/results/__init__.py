"""Results: rebound measures and summaries of a run (``analysis``) and the VTK series
ParaView opens (``vtk``)."""
