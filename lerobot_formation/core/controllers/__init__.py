"""Controllers (floor 4 of the core) behind one interface (``protocol.Controller``): PAC, the demonstrator
(``pac``), MPPI (``mppi``), route pursuit (``route_pursuit``), and the whole formation's footprint along
a plan that they and the safety layer check (``footprint``). Imports only lower floors of the core."""
