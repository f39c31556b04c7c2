"""The gymnasium id of the formation env, ``gym_formation/FormationNav-v0``, and its registration.

This module imports nothing but the standard library. ``register_env()`` registers the id in
gymnasium's registry (importing gymnasium). ``register_when_gymnasium_loads()``, which ``import
lerobot_formation`` calls, registers it without importing gymnasium: at once when gymnasium's
registry is already loaded, else when gymnasium loads it (a one-shot import hook on
``gymnasium.envs.registration``, removed from ``sys.meta_path`` as soon as it fires). So both

    import lerobot_formation          # or: import gym_formation
    import gymnasium as gym
    env = gym.make("gym_formation/FormationNav-v0")

and the same with the two imports swapped work, while ``import lerobot_formation`` alone still loads
neither gymnasium, torch nor LeRobot (the NumPy core stays importable without them).
"""

from __future__ import annotations

import importlib.abc
import sys
import warnings

ENV_ID = "gym_formation/FormationNav-v0"
ENTRY_POINT = "lerobot_formation.envs.env:FormationEnv"
VECTOR_ENTRY_POINT = "lerobot_formation.envs.vector_env:FormationVectorEnv"
MAX_EPISODE_STEPS = 600
REGISTRY_MODULE = "gymnasium.envs.registration"


def register_env(registration=None) -> None:
    """Register ``ENV_ID`` in gymnasium's registry (``registration``: the module
    ``gymnasium.envs.registration``, imported when None); nothing when it is there already."""
    if registration is None:
        import gymnasium.envs.registration as registration
    if ENV_ID not in registration.registry:
        registration.register(
            id=ENV_ID,
            entry_point=ENTRY_POINT,
            vector_entry_point=VECTOR_ENTRY_POINT,
            max_episode_steps=MAX_EPISODE_STEPS,
        )


class _RegisterOnLoad(importlib.abc.MetaPathFinder):
    """Finds ``gymnasium.envs.registration`` through the other finders and makes its loader register
    ``ENV_ID`` right after running the module. One shot: it leaves ``sys.meta_path`` when it fires."""

    def find_spec(self, fullname, path, target=None):
        if fullname != REGISTRY_MODULE:
            return None
        _remove_hook()
        for finder in sys.meta_path:
            find = getattr(finder, "find_spec", None)
            spec = find(fullname, path, target) if find is not None else None
            if spec is not None:
                break
        else:
            return None
        loader = spec.loader
        exec_module = getattr(loader, "exec_module", None)
        if exec_module is None:
            return spec

        def exec_and_register(module):
            exec_module(module)
            try:
                register_env(module)
            except Exception as e:  # never break gymnasium's own import
                warnings.warn(f"lerobot_formation: could not register {ENV_ID}: {e}", stacklevel=2)

        loader.exec_module = exec_and_register  # this spec's own loader object
        return spec


def _remove_hook() -> None:
    sys.meta_path[:] = [f for f in sys.meta_path if not isinstance(f, _RegisterOnLoad)]


def register_when_gymnasium_loads() -> None:
    """Register ``ENV_ID`` now if gymnasium's registry is loaded, else as soon as it is (see the module
    docstring); never imports gymnasium itself. Idempotent."""
    registration = sys.modules.get(REGISTRY_MODULE)
    if registration is not None and hasattr(registration, "register"):
        register_env(registration)
    elif not any(isinstance(f, _RegisterOnLoad) for f in sys.meta_path):
        sys.meta_path.insert(0, _RegisterOnLoad())
