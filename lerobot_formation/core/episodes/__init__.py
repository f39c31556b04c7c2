"""Episodes (floor 6 of the core): closed-loop rollouts of B episodes at once (``rollout``), their
metrics (``metrics``) and the graded benchmark's levels (``levels``). Imports only lower floors."""
