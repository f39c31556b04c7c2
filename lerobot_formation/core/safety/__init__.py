"""The safety layer (floor 5 of the core): best-of-K chunk selection, rechecks and the CBF filter
(``filters``), the sampler's clearance guidance (``guidance``), replan blending and chunk smoothing
(``replan_blend``), and the layer as one unit with its settings and per-episode state (``layer``).
Imports only lower floors of the core."""
