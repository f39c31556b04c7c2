"""The ``nearest+maproute`` obstacle encoding: ``nearest+route`` with its route planned on the whole map.

Why: ``nearest+route`` builds its cost-to-go from the 12 map obstacles nearest the midpoint, so in a
scene of more (a bend's walls, a crowd: 20-30 obstacles) the route can lead into a wall that is not
among them, where the team stalls (docs/log.md, "The route hint from the whole map"). PAC plans
on every obstacle of its map; this hint does too.

Layout: that of ``nearest+route`` (2 + 4 slots + 5 values, the same names): the ``nearest`` encoding,
then the carrots 1 m and 3 m down PAC's cost-to-go and PAC's path-blocked flag, with the cost-to-go
built from every obstacle of the team's map (``core.perception.conditions.Perception.map_obstacles``: the
observed static obstacles, moving ones left out) instead of the ``slots`` nearest. With ``slots`` or
fewer obstacles on the map the two encodings are equal, value for value. A checkpoint trained on
``nearest+route`` reads it unchanged (``scripts/derive_checkpoint.py --set
obstacle_encoding=nearest+maproute``).
"""

from __future__ import annotations

from lerobot_formation.core.encodings.route_encoding import route_encoding

ENCODING = route_encoding("nearest+maproute", whole_map=True)
