"""The ``formation_diffusion`` policy: config, model, processors (LeRobot finds them by name), the replanner."""
