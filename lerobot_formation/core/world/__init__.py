"""The world (floor 1 of the core): the team and its physics (``formation_graph``, ``dynamics``), clearance
and collision (``geometry``), the grid cost-to-go and PAC's path check (``navigation``), and scenes: the
container (``scenes``), its distributions (``presets``), which scenes are possible (``validity``), files
(``scene_files``) and sampling from seeds (``sampling``). Imports nothing else of the core."""
