"""Obstacle encodings (floor 2 of the core): what every encoding builds on, the body frame included
(``encoding``), the registry by name and the observation's obstacle part (``obstacle_grid``), and one
file per encoding. Imports only ``core.world``."""
