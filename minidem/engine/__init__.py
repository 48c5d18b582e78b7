"""The compiled simulation: a validated scene in, a :class:`RunResult` out.

``simulation`` prepares the contact law, chooses the time step and the integrator,
specialises ``kernel`` (the compiled step, a template) for the law and the scene shape,
and rebuilds the neighbour lists; ``run_loop`` runs the time loop in chunks of compiled
steps over the arrays of ``state``; ``law_signature`` holds the types the kernel calls a
law with (and why a law that breaks the compile does); ``integrate`` holds the
integrators, ``blocks`` the threads' shares of a step, ``blowup`` the fault detection,
``checkpoint`` the resumable state files, ``warmup`` the helper process that compiles
beside a first run."""
