"""lerobot_formation: multi-agent formation navigation with a diffusion planner, as a LeRobot plugin.

Subpackages (docs/design.md): ``core`` (numpy), ``compat`` (LeRobot internals), ``envs`` (the gym env,
registered as ``gym_formation/FormationNav-v0`` when ``envs`` is imported), ``policy``
(``formation_diffusion``), ``data`` (the dataset generator), ``bench`` (evaluation); ``plugin`` is
what LeRobot's CLIs import. Importing this package itself imports nothing.
"""
