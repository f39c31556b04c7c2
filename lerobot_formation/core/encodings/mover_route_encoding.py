"""The ``nearest+moverroute+velocity`` obstacle encoding: ``nearest+route+velocity`` whose route hint
plans around the observed moving obstacles where they are now.

Why: ``nearest+route+velocity``'s hint plans on the team's map, which leaves the movers out, so a
network that corrects route pursuit's chunk (``action_space: route-residual``) must add the whole
avoidance of the movers. Route pursuit itself (``core/controllers/route_pursuit.py``) rebuilds its
cost-to-go with each observed mover where it is now; this hint is that same route, so the residual's
prior is route pursuit's own chunk (the first command equal to route pursuit's).

Layout: that of ``nearest+route+velocity`` (``core/encodings/route_velocity_encoding.py``); only the 5
route values differ, and only while a mover is observed (an observed velocity that is not zero):
the cost-to-go is then built on the map with every observed mover in place of its map entry, at every
step (no cache hit, as route pursuit's).
"""

from __future__ import annotations

from lerobot_formation.core.encodings.route_velocity_encoding import route_velocity_encoding

ENCODING = route_velocity_encoding("nearest+moverroute+velocity", movers_on_map=True)
