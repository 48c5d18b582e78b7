"""The compiled simulation: a validated scene in, a :class:`RunResult` out.

``simulation`` prepares the contact law, chooses the time step and the integrator,
specialises ``kernel`` (the compiled step, a template) for the law and the scene shape,
and runs the time loop in chunks; ``integrate`` holds the integrators, ``blowup`` the
fault detection, ``checkpoint`` the resumable state files."""
