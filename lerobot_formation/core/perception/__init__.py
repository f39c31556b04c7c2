"""What a team perceives (floor 3 of the core): realistic conditions and the ``Perception`` a controller
sees (``conditions``), the policy's observation (``observation``), moving-obstacle prediction and
tracking (``obstacle_tracker``) and the filter of noisy obstacles (``obstacle_filter``). Imports only
``core.world`` and ``core.encodings``."""
