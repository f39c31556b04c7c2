"""``formation_diffusion``: LeRobot's ``DiffusionPolicy`` plus an EMA of its weights used for inference.

Only the EMA is added; the U-Net, noise scheduler, loss and action queue are LeRobot's.

EMA (as diffusers' ``EMAModel`` and the original Diffusion Policy define it):

- ``ema_diffusion`` is a second ``DiffusionModel``, never trained (``requires_grad=False``, left out of
  ``get_optim_params``). ``ema_step`` (a buffer) counts the optimizer steps seen so far. Both are in
  ``model.safetensors``, so a checkpoint and ``--resume=true`` restore them.
- ``update()``, which ``lerobot-train`` calls once after every optimizer step on the unwrapped
  policy, runs diffusers' ``EMAModel.step`` on ``ema_diffusion``'s parameters: decay
  ``EMAModel.get_decay(k)`` at the k-th step (see ``FormationDiffusionConfig``), then
  ``ema <- ema - (1 - decay) (ema - live)``. Buffers are copied.
- In eval mode (``policy.eval()``, as ``lerobot-eval`` and the in-training env evaluation set it),
  ``predict_action_chunk`` and so ``select_action`` run ``ema_diffusion.generate_actions``
  directly: no attribute swap, so concurrent calls cannot see the wrong weights. In train mode
  they use the live model.

Multi-GPU (``accelerate launch --multi_gpu --num_processes=N $(which lerobot-train) ...``): DDP
averages the gradients, so after each optimizer step the live weights are identical on every process;
``lerobot-train`` calls ``accelerator.unwrap_model(policy).update()`` on every process after that step,
so every process applies the same EMA update (one per optimizer step, not per sample or per process)
and holds the same EMA weights; the main process saves them. The EMA parameters do not require
gradients, so DDP neither reduces nor waits for them.
"""

from __future__ import annotations

import logging

import torch
from diffusers.training_utils import EMAModel
from lerobot.policies.diffusion.modeling_diffusion import DiffusionModel, DiffusionPolicy
from lerobot.utils.constants import OBS_ENV_STATE
from safetensors import safe_open
from torch import Tensor

from lerobot_formation.configuration_formation_diffusion import ENV_STATE_DIMS, FormationDiffusionConfig
from lerobot_formation.core.obstacle_grid import ENCODINGS

EMA_PREFIX = "ema_diffusion."


class FormationDiffusionPolicy(DiffusionPolicy):
    """LeRobot's diffusion policy with an EMA copy of the diffusion model (see the module docstring)."""

    config_class = FormationDiffusionConfig
    name = "formation_diffusion"

    def __init__(self, config: FormationDiffusionConfig, **kwargs):
        if not isinstance(config, FormationDiffusionConfig):
            try:
                got = config.type
            except Exception:  # not a registered PreTrainedConfig at all
                got = None
            raise TypeError(
                "FormationDiffusionPolicy (type 'formation_diffusion') needs a FormationDiffusionConfig, "
                f"got {type(config).__name__} (type {got!r}). A checkpoint of another policy type must be "
                f"loaded with that type's policy class (lerobot.policies.factory.get_policy_class({got!r}))."
            )
        super().__init__(config, **kwargs)
        self.ema_diffusion: DiffusionModel | None = None
        self._ema: EMAModel | None = None
        if config.use_ema:
            self.ema_diffusion = DiffusionModel(config)
            self.ema_diffusion.load_state_dict(self.diffusion.state_dict())
            self.ema_diffusion.requires_grad_(False)
            self.register_buffer("ema_step", torch.zeros((), dtype=torch.long))
            # The schedule and the update are diffusers' own; this object holds no weights (its
            # shadow parameters are pointed at ema_diffusion's for the duration of each update).
            self._ema = EMAModel(
                [],
                decay=config.ema_max_decay,
                min_decay=config.ema_min_decay,
                update_after_step=config.ema_update_after_step,
                use_ema_warmup=True,
                inv_gamma=config.ema_inv_gamma,
                power=config.ema_power,
                foreach=True,
            )

    def get_optim_params(self) -> dict:
        """The live diffusion model's parameters only (never the EMA copy)."""
        return self.diffusion.parameters()

    def ema_decay(self, step: int) -> float:
        """EMA decay applied at optimizer step ``step`` (1-based), diffusers' ``EMAModel.get_decay``."""
        if self._ema is None:
            raise RuntimeError("use_ema is False: this policy keeps no EMA")
        return float(self._ema.get_decay(step))

    @torch.no_grad()
    def update(self) -> None:
        """EMA update; ``lerobot-train`` calls it once after every optimizer step."""
        if self._ema is None:
            return
        ema_params = list(self.ema_diffusion.parameters())
        live_params = list(self.diffusion.parameters())
        self._ema.shadow_params = ema_params
        self._ema.optimization_step = int(self.ema_step)
        try:
            self._ema.step(live_params)  # increments optimization_step, then updates ema_params in place
        finally:
            self._ema.shadow_params = []
        self.ema_step.fill_(self._ema.optimization_step)
        for ema_buf, live_buf in zip(self.ema_diffusion.buffers(), self.diffusion.buffers(), strict=True):
            ema_buf.copy_(live_buf)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        """``DiffusionPolicy.predict_action_chunk``, with the EMA model in eval mode.

        Returns (B, n_action_steps, action_dim) actions (normalized, as the postprocessor expects).
        """
        self._check_observation_sizes(batch)
        if self.ema_diffusion is None or self.training:
            return super().predict_action_chunk(batch, noise=noise)
        # As DiffusionPolicy does: stack the observation history (B, n_obs_steps, ...) from the
        # queues select_action fills, or take an offline batch as given. No image features here.
        if any(len(q) > 0 for q in self._queues.values()):
            batch = {k: torch.stack(list(self._queues[k]), dim=1) for k in batch if k in self._queues}
        return self.ema_diffusion.generate_actions(batch, noise=noise)

    def _check_observation_sizes(self, batch: dict[str, Tensor]) -> None:
        """Observations must have the sizes the policy was trained on (e.g. the env's obstacle encoding)."""
        for key, feature in self.config.input_features.items():
            if key in batch and batch[key].shape[-1] != feature.shape[0]:
                hint = ""
                if key == OBS_ENV_STATE and feature.shape[0] in ENV_STATE_DIMS:
                    encoding = ENCODINGS[ENV_STATE_DIMS.index(feature.shape[0])]
                    hint = f" Evaluate with --env.obstacle_encoding={encoding}."
                raise ValueError(
                    f"'{key}' has {batch[key].shape[-1]} values per step, but this policy was trained on "
                    f"{feature.shape[0]}.{hint}"
                )

    @classmethod
    def _load_as_safetensor(cls, model, model_file: str, map_location: str, strict: bool):
        model = super()._load_as_safetensor(model, model_file, map_location, strict)
        if model.ema_diffusion is not None:
            with safe_open(model_file, framework="pt") as f:
                has_ema = any(k.startswith(EMA_PREFIX) for k in f.keys())  # noqa: SIM118
            if not has_ema:
                logging.warning(
                    "%s holds no EMA weights (trained with use_ema=false?): the EMA starts from the live "
                    "weights with ema_step=0.",
                    model_file,
                )
                model.ema_diffusion.load_state_dict(model.diffusion.state_dict())
                model.ema_step.zero_()
        return model
