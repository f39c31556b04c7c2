"""The gym env (registered as ``gym_formation/FormationNav-v0``), its vector env, LeRobot env config, render and episode metrics."""
