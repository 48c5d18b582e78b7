"""Studies built on the engine: parameter sweeps (``sweep``, run by ``executors`` on
local processes or Dask, drawn by ``figures``), the law battery (``verify``), the
independent reference solution of the paper's impact (``reference``) and the
benchmarks (``bench``, ``bench_multi``, ``bench_sweeps``)."""
