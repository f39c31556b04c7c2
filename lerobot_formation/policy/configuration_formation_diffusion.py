"""Config of the ``formation_diffusion`` policy: LeRobot's diffusion policy plus EMA, paper defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from lerobot.configs import FeatureType, NormalizationMode, PolicyFeature, PreTrainedConfig
from lerobot.optim import AdamWConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_formation.compat.run_checks import config_error, install_config_upgrade, install_run_hooks
from lerobot_formation.core.encodings.obstacle_grid import (
    ENCODINGS,
    egocentric_encodings,
    environment_state_dim,
    get_encoding,
    route_encodings,
)
from lerobot_formation.core.perception.observation import STATE_DIM
from lerobot_formation.core.safety.layer import KnownWorld
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.policy.obstacle_tokens import TOKEN_HEADS, token_layout

ACTION_DIM = 2  # [v, omega]
SAFETY_FILTERS = ("none", "cbf")
INFERENCE_BACKENDS = ("eager", "lean", "trace")
OBSTACLE_ENCODERS = ("flat", "tokens")  # how the network reads environment_state
ACTION_SPACES = ("velocity", "route-residual")  # what the network's chunk is
_BOUNDS = FormationParams()
# The env's action bounds [v, omega] (``FormationParams``): what ``fixed_action_bounds`` normalises with.
ACTION_LOW = (0.0, -_BOUNDS.omega_max)
ACTION_HIGH = (_BOUNDS.v_max, _BOUNDS.omega_max)
# The standard policy: one sample per replan, no filter, no clearance guidance (the safety layer off;
# warm starts and chunk smoothing stay as configured). The bench's "diffusion" controller runs it.
LAYER_OFF = {"num_candidates": 1, "safety_filter": "none", "sampling_guidance": 0.0}


def _non_finite_fields(config) -> list[str]:
    """``name=value`` of every float field (or float in a tuple / list field) that is NaN or inf."""
    bad = []
    for f in fields(config):
        value = getattr(config, f.name)
        values = value if isinstance(value, tuple | list) else (value,)
        if any(isinstance(v, float) and not math.isfinite(v) for v in values):
            bad.append(f"{f.name}={value}")
    return bad


def _is_finite_nonnegative(value) -> bool:
    """A finite number >= 0 (a bool is not one)."""
    return not isinstance(value, bool) and isinstance(value, (int, float)) and 0 <= value < math.inf


def _encoding_sizes() -> str:
    return ", ".join(f"{e} {environment_state_dim(e)} values" for e in ENCODINGS)


def _describe(features: dict[str, PolicyFeature] | None) -> str:
    if not features:
        return "none"
    return ", ".join(f"'{k}' ({ft.type.name}, shape {tuple(ft.shape)})" for k, ft in features.items())


# The clearance guidance of the bench's ``diffusion-guided`` where a checkpoint sets none: eta = 1 (with
# the safety layer's GUIDANCE_DISTANCE 0.3 m and one gradient step per denoising step), chosen on level3's
# and level5's tuning scenes (docs/benchmark.md, "Clearance guidance").
TUNED_SAMPLING_GUIDANCE = 1.0


@PreTrainedConfig.register_subclass("formation_diffusion")
@dataclass
class FormationDiffusionConfig(DiffusionConfig):
    """LeRobot's ``DiffusionConfig`` with an EMA of the weights. The network and training defaults are
    the paper's hyperparameters; the observation, sampling and safety defaults are the shipped
    policy's (``pretrained/formation_diffusion_route_v1``: best-of-10 with the CBF filter and the rest of
    its safety layer, below).

    Every ``DiffusionConfig`` field keeps its meaning (see its docstring). The defaults differ where
    the paper's Table "Training and Model Hyperparameters" (SPEC "The policy") sets a value: U-Net
    ``down_dims`` (256, 512, 1024), ``kernel_size`` 5, ``n_groups`` 8, ``diffusion_step_embed_dim``
    256; 100 training timesteps, ``squaredcos_cap_v2``, epsilon prediction, ``clip_sample``; T_p =
    ``horizon`` 64, T_o = ``n_obs_steps`` 2, T_a = ``n_action_steps`` 10; AdamW (the optimizer preset
    is ``AdamWConfig``, where ``DiffusionConfig``'s is Adam) with ``optimizer_lr`` 1.05e-4,
    ``optimizer_weight_decay`` 1e-6, cosine schedule with 1000 warm-up steps; EMA power 0.75. The
    batch size (256) is ``lerobot-train``'s ``--batch_size``, not a policy field. The sampler is the
    shipped policy's: DDIM (``noise_scheduler_type``; its training loss is DDPM's, the same forward
    process) with ``num_inference_steps`` 4, where the paper samples DDPM's 100 steps
    (``configs/formation_diffusion_paper.json`` sets that).

    Features (checked by ``validate_features`` when the policy is built, i.e. at start-up):
    ``observation.state`` (STATE, (7,)): the midpoint [x, y, cos phi, sin phi, x', y', omega];
    ``observation.environment_state`` (ENV, (51,) "grid" or (66,) "grid+list"); ``action``
    (ACTION, (2,)) = [v, omega]. No image features. Other inputs are ignored by the model.

    Normalization: STATE and ACTION MIN_MAX (to [-1, 1]; ``clip_sample`` relies on the action range);
    ENV IDENTITY. The environment state holds obstacle radii in [0, 0.8] m, the goal and (with
    "grid+list") obstacle coordinates, all within a few metres already. The dataset's goal is constant
    (5, 5), so MIN_MAX or MEAN_STD statistics would divide by ~0 and blow up any other goal, and a
    cell that never held an obstacle in the data would do the same for an unseen scene.

    Args:
        egocentric_obstacles: give the network the goal and the obstacle list in the midpoint's frame,
            nearest obstacle first (a preprocessor step; needs the "grid+list" encoding). Off by default
            (the paper feeds world coordinates).
        obstacle_encoding: name of the ``observation.environment_state`` encoding
            (``core.encodings.obstacle_grid.ENCODING_REGISTRY``: "nearest+route" (default, the shipped policy's:
            the safety layer needs the "nearest" family, route pursuit's proposal a route hint),
            "grid" (the paper's), "grid+list", "nearest", "nearest+maproute", "nearest+velocity",
            "nearest+route+velocity", "nearest+moverroute+velocity"). ``lerobot-eval`` and ``lerobot-train`` give the env this encoding
            when ``--env.obstacle_encoding`` is not given (another given one is an error). Stored in
            every checkpoint, never guessed from the feature's size.
        max_obstacles: obstacle rows of the encoding (None: the encoding's default, 5 for
            "grid+list", 12 for the "nearest" family).
        obstacle_encoder: how the network reads ``observation.environment_state``. "flat" (default):
            LeRobot's, the values flattened with the state into the U-Net's FiLM conditioning. "tokens":
            each obstacle slot a token and the team an ego token that attends to the present ones,
            plus a max-pool over them (``policy.obstacle_tokens``: permutation-invariant, indifferent
            to the obstacle count); needs an encoding of the "nearest" family and ENV IDENTITY.
        token_dim: width d of the tokens (a multiple of ``TOKEN_HEADS`` = 4); the U-Net sees 2 d
            values per observation step instead of the environment state. Only with "tokens".
        action_space: what the network's chunk is. "velocity" (default): the commands [v, omega]
            themselves, normalised to [-1, 1]. "route-residual": a correction to route pursuit's
            chunk (``core.controllers.route_pursuit.pursuit_chunk`` from the route hint of the current
            observation): the network denoises r = (a - a_rp) / 2 in normalised units and the chunk
            is clip(a_rp + 2 r, -1, 1) (``FormationDiffusionModel.route_prior``). A residual over a
            hand-written rule, reported as such beside the rule alone; needs an encoding with a route
            hint ("nearest+route", "nearest+route+velocity", "nearest+maproute") and
            ``fixed_action_bounds``.
        fixed_action_bounds: normalise actions with the env's fixed bounds ``action_low`` /
            ``action_high`` (``ACTION_LOW`` / ``ACTION_HIGH``: v in [0, 0.6], omega in [-1.5, 1.5]), so
            the policy itself knows the action in physical units (the safety layer needs it). True
            (default); false: the dataset's min/max (the paper's).
        num_candidates: K action chunks drawn per replan in one batched call; with K > 1 the safety
            layer keeps the best (``core.safety.filters.select_chunk``: no predicted collision of the whole
            formation's footprint, then cost-to-go progress toward the goal on a 0.4 m grid read
            bilinearly, less ``core.safety.layer.COHERENCE`` m per unit of deviation from the plan it
            replaces unless the filter cut that plan short; with a route encoding route pursuit's
            chunk, blended in from the command being executed, competes too; the escape manoeuvres of
            ``core.safety.layer.ESCAPE_SPEEDS`` where no candidate is safe, else the widest of every
            candidate scored), and at every step checks the rest of the kept chunk again on the newest
            view (``core.safety.filters.plan_is_safe``), replanning at once where it fails. 10
            (default, the shipped policy's); 1: the standard policy.
        safety_filter: "none", or "cbf" (default): every executed action passes a control-barrier-
            function filter on [v, omega] for all four agents (``core.safety.filters.cbf_filter``, dh/dt
            >= -alpha h with alpha ``core.safety.layer.CBF_RATE``); an episode whose action it
            changed replans at its next step. Needs an egocentric encoding ("nearest")
            and ``fixed_action_bounds``; it uses only the observed obstacles.
        safety_margin: clearance [m] the safety layer keeps between every agent disc and every
            obstacle (followers lag their square slots by up to ~0.1 m; the layer keeps them
            ``core.safety.layer.FOLLOWER_MARGIN`` more where it predicts no moving obstacles).
            Default 0.05.
        safety_horizon: n >= 0 steps the safety layer looks past every candidate chunk. Best-of-K
            follows every candidate with n steps of route pursuit from its end pose (``pursuit_chunk``,
            with a route encoding), checks the footprint over both (a chunk that ends facing a wall
            the team cannot turn away from, the leaders unable to back up, is not safe, unless no
            candidate's continuation is) and measures cost-to-go progress at the continuation's end
            (so the heading a chunk leaves counts). Where no candidate passes so and the layer
            predicts moving obstacles (``safety_world.moving_obstacles``), it prefers the candidates
            after which the team, braking to a standstill (rate limited) and standing for the rest of
            n steps, keeps the margin (``core.safety.filters.FootprintCheck.halted``): a place where
            a standing team is struck by a mover it could have left is not one to stop in. Default
            20; 0: the chunk alone.
        safety_mover_uncertainty: u >= 0 [m/s]. Where the layer predicts moving obstacles, best-of-K
            grows a moving obstacle's predicted radius by u t at t seconds ahead (over the chunk and
            its horizon; ``core.perception.obstacle_tracker.predict_obstacles``): its constant-velocity
            prediction drifts with the velocity estimate's error and with every bounce, so a chunk
            that passes a mover closely late in the horizon is not safe. Default 0.1; 0: the
            prediction as exact.
        safety_world: what the safety layer is told of the robot and its world, not tuned settings
            (``core.safety.layer.KnownWorld``, whose docstring describes each field):
            ``moving_obstacles`` (predict the observed obstacles at constant velocity),
            ``action_delay`` [control steps], ``max_linear_accel`` [m/s^2] / ``max_angular_accel``
            [rad/s^2] (None: no limit), ``obstacle_noise`` / ``pose_noise`` [m, rad] (the sensors'
            noise stds). The bench sets it from each level's conditions; on the command line
            ``--policy.safety_world.action_delay=1``. Default: nothing known (``KnownWorld()``).
        safety_search: n >= 0. Where the layer predicts moving obstacles
            (``safety_world.moving_obstacles``), best-of-K's candidates also hold n paths of a lattice
            search in space and time (``core.safety.lattice_search``): a beam search over held
            [v, omega] primitives of 0.5 s, 3 s deep, that keeps only paths whose footprint clears
            every obstacle where it is predicted at that time; the best path of each of its n best
            first manoeuvres, checked and scored like every candidate. They give the team composite
            ways out (turn away, then run) that no sample holds where a mover comes towards it; among
            standing obstacles the route hint already follows the cost-to-go the search ranks by
            (there it cost level3's tuning scenes 4 of 200 in timeouts). Default 3; 0: no search.
            The layer's other settings are wired (``core.safety.layer``: ``CBF_RATE``,
            ``FOLLOWER_MARGIN``, ``ROUTE_PROPOSAL``, ``PROPOSAL_BLEND``, ``COHERENCE``,
            ``ESCAPE_SPEEDS``, ...).
        warm_start_step: j >= 0. j > 0: a replan starts at the sampler's j-th timestep from the
            unexecuted rest of the episode's previous chunk, noised to that level (SDEdit; the module
            docstring of ``modeling_formation_diffusion``), every best-of-K candidate with its own
            noise: the plan keeps its way round an obstacle from one replan to the next, and costs j
            fewer denoiser calls. Must be below ``num_inference_steps``. Default 1; 0: every replan
            samples from pure noise, as LeRobot does.
        chunk_smoothing: n >= 0 passes of the [1, 2, 1] / 4 kernel over every sampled chunk along
            time, entered from the command being executed (``core.safety.replan_blend.smooth_chunks``), before
            best-of-K scores the candidates (so it judges what will run); with K = 1 too. A diffusion
            sample's step-to-step noise is most of the jerk where a chunk runs on. Route pursuit's
            proposal is smoothed too where it is blended in (``core.safety.layer.PROPOSAL_BLEND``).
            Default 2; 0: the samples as drawn.
        sampling_guidance: eta >= 0. With eta > 0 every denoising step moves the sampler's estimate
            of the clean chunk down the gradient of a clearance barrier on the whole formation's
            footprint against the observed obstacles (movers at their velocities; from the actuator's
            predicted start where the layer knows it): the commands change by -eta dJ/da, J the sum
            of 0.5 max(0, delta - clearance)^2 over steps, agents and obstacles, delta =
            ``core.safety.layer.GUIDANCE_DISTANCE`` (0.3 m), one gradient step per denoising step
            (``core.safety.guidance``; cost guidance of diffusion planners). With K = 1 too: it shapes the
            sample itself, before best-of-K or the filter. Needs the lean or trace backend and DDIM.
            Default 1; 0: unguided sampling.
        inference_backend: how chunks are sampled at inference (``select_action``, ``lerobot-eval``,
            the engine). "eager": LeRobot's own ``DiffusionModel.conditional_sample``. "lean":
            under ``torch.inference_mode``, with the DDIM steps' timesteps and coefficients precomputed
            once per scheduler and step count (checked against diffusers' ``step``; other schedulers
            keep diffusers' ``step``). "trace": "lean" with a ``torch.jit`` traced and frozen U-Net,
            built on first use in eval mode, rebuilt when the weights change, never saved (the
            ``state_dict`` is unchanged); falls back to the eager U-Net if tracing fails. On a CPU
            it traces ``policy.unet_inference``'s copies (matrix-product convolutions up to 64 rows).
            Same noise, same chunks within 1e-5 (modeling_formation_diffusion.py). "trace" (default).
        drop_n_last_frames: frames at each episode's end the training sampler never starts a window
            at; must be ``horizon - n_action_steps - n_obs_steps + 1`` (the original Diffusion
            Policy's rule, 53 for the paper). None (default): derived from that formula; a set value
            that differs raises ``ValueError``.
        use_ema: keep an exponential moving average of the diffusion model (``ema_diffusion``) and
            use it for inference in eval mode. ``--policy.use_ema=false`` at evaluation uses the live
            weights of an EMA checkpoint.
        ema_power: EMA warm-up power (paper: 0.75).

    The EMA decay after the k-th optimizer step is diffusers' ``EMAModel.get_decay(k)`` with
    ``use_ema_warmup=True`` and diffusers' other defaults (inverse gamma 1, decay bounds 0 and
    0.9999, no steps before the first update; ``modeling_formation_diffusion.EMA_MAX_DECAY``): with
    s = k - 1, 0 if s <= 0, else min(1 - (1 + s) ** -ema_power, 0.9999).
    """

    # Inputs / output structure.
    n_obs_steps: int = 2
    horizon: int = 64
    n_action_steps: int = 10
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MIN_MAX,
            "ENV": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )
    drop_n_last_frames: int | None = None  # None: horizon - n_action_steps - n_obs_steps + 1
    # Goal and obstacle list in the midpoint's frame, nearest first (processor_formation_diffusion.py).
    egocentric_obstacles: bool = False
    obstacle_encoding: str = "nearest+route"
    max_obstacles: int | None = None
    obstacle_encoder: str = "flat"
    token_dim: int = 64
    action_space: str = "velocity"
    fixed_action_bounds: bool = True

    # Sampling and safety layer (inference only; see the Args above): the shipped policy's settings.
    num_candidates: int = 10
    safety_filter: str = "cbf"
    safety_margin: float = 0.05
    safety_horizon: int = 20
    safety_mover_uncertainty: float = 0.1
    safety_world: KnownWorld = field(default_factory=KnownWorld)
    safety_search: int = 3
    warm_start_step: int = 1
    chunk_smoothing: int = 2
    sampling_guidance: float = 1.0
    # Inference path (see the Args above; not a training setting).
    inference_backend: str = "trace"

    # Unet.
    down_dims: tuple[int, ...] = (256, 512, 1024)
    kernel_size: int = 5
    n_groups: int = 8
    diffusion_step_embed_dim: int = 256

    # Noise scheduler (training as the paper's; the sampler is the shipped policy's, see above).
    noise_scheduler_type: str = "DDIM"
    num_train_timesteps: int = 100
    num_inference_steps: int | None = 4
    beta_schedule: str = "squaredcos_cap_v2"
    prediction_type: str = "epsilon"
    clip_sample: bool = True

    # Training presets.
    optimizer_lr: float = 1.05e-4
    optimizer_betas: tuple = (0.95, 0.999)
    optimizer_eps: float = 1e-8
    optimizer_weight_decay: float = 1e-6
    scheduler_name: str = "cosine"
    scheduler_warmup_steps: int = 1000

    # EMA (diffusers EMAModel with use_ema_warmup=True, as in the original Diffusion Policy).
    use_ema: bool = True
    ema_power: float = 0.75

    def __post_init__(self):
        install_run_hooks()  # a formation run: one-line config errors, the training output lock
        # Every number finite: a NaN passes every comparison below unnoticed.
        non_finite = _non_finite_fields(self)
        if non_finite:
            raise config_error(f"config values must be finite numbers, got {', '.join(non_finite)}")
        if self.num_train_timesteps < 1:
            raise config_error(f"num_train_timesteps must be >= 1, got {self.num_train_timesteps}")
        if (
            self.num_inference_steps is not None
            and not 1 <= self.num_inference_steps <= self.num_train_timesteps
        ):
            raise config_error(
                f"num_inference_steps must be null (the training steps) or in [1, num_train_timesteps] = "
                f"[1, {self.num_train_timesteps}], got {self.num_inference_steps}"
            )
        # Horizon first, so that this message (not DiffusionConfig's) explains a bad horizon.
        if self.n_obs_steps < 1:
            raise config_error(f"n_obs_steps must be >= 1, got {self.n_obs_steps}")
        factor = 2 ** len(self.down_dims)
        if self.horizon < factor or self.horizon % factor != 0:
            below = self.horizon // factor * factor
            nearest = [h for h in (below, below + factor) if h > 0]
            raise config_error(
                f"horizon={self.horizon} does not fit the U-Net: with down_dims={list(self.down_dims)} "
                f"({len(self.down_dims)} stages) LeRobot's diffusion U-Net needs a horizon that is a "
                f"positive multiple of 2**len(down_dims) = {factor}; nearest valid horizons: "
                f"{nearest}. Change --policy.horizon or --policy.down_dims."
            )
        max_action_steps = self.horizon - self.n_obs_steps + 1
        if not 1 <= self.n_action_steps <= max_action_steps:
            raise config_error(
                f"n_action_steps={self.n_action_steps} must be in [1, horizon - n_obs_steps + 1] = "
                f"[1, {max_action_steps}] (horizon={self.horizon}, n_obs_steps={self.n_obs_steps})"
            )
        expected_drop = self.horizon - self.n_action_steps - self.n_obs_steps + 1
        if self.drop_n_last_frames is None:
            self.drop_n_last_frames = expected_drop
        elif self.drop_n_last_frames != expected_drop:
            raise config_error(
                f"drop_n_last_frames={self.drop_n_last_frames} does not match horizon - n_action_steps - "
                f"n_obs_steps + 1 = {self.horizon} - {self.n_action_steps} - {self.n_obs_steps} + 1 = "
                f"{expected_drop}. Set it to {expected_drop}, or to null to derive it."
            )
        if self.ema_power <= 0:
            raise config_error(f"ema_power must be > 0, got ema_power={self.ema_power}")
        if self.obstacle_encoding not in ENCODINGS:
            raise config_error(
                f"obstacle_encoding must be one of {ENCODINGS}, got {self.obstacle_encoding!r}"
            )
        if self.obstacle_encoder not in OBSTACLE_ENCODERS:
            raise config_error(
                f"obstacle_encoder must be one of {OBSTACLE_ENCODERS}, got obstacle_encoder={self.obstacle_encoder!r}"
            )
        if self.obstacle_encoder == "tokens":
            self._check_tokens()
        if self.action_space not in ACTION_SPACES:
            raise config_error(
                f"action_space must be one of {ACTION_SPACES}, got action_space={self.action_space!r}"
            )
        if self.action_space == "route-residual":
            if not get_encoding(self.obstacle_encoding).map:
                raise config_error(
                    "action_space='route-residual' corrects route pursuit's chunk, which reads the route hint: "
                    f"it needs an encoding with one ({route_encodings()}), got obstacle_encoding="
                    f"{self.obstacle_encoding!r}"
                )
            if not self.fixed_action_bounds:
                raise config_error(
                    "action_space='route-residual' adds route pursuit's chunk in physical units: it needs "
                    "fixed_action_bounds=true, got fixed_action_bounds=false"
                )
        if self.inference_backend not in INFERENCE_BACKENDS:
            raise config_error(
                f"inference_backend must be one of {INFERENCE_BACKENDS}, got {self.inference_backend!r}"
            )
        steps = self.num_inference_steps or self.num_train_timesteps
        if not 0 <= self.warm_start_step < steps:
            raise config_error(
                f"warm_start_step must be in [0, {steps}) (num_inference_steps {steps}), got {self.warm_start_step}"
            )
        if self.num_candidates < 1:
            raise config_error(f"num_candidates must be >= 1, got {self.num_candidates}")
        if self.safety_filter not in SAFETY_FILTERS:
            raise config_error(f"safety_filter must be one of {SAFETY_FILTERS}, got {self.safety_filter!r}")
        if not _is_finite_nonnegative(self.safety_margin):
            raise config_error(f"safety_margin must be a number >= 0 [m], got {self.safety_margin!r}")
        if isinstance(self.safety_horizon, bool) or not (
            isinstance(self.safety_horizon, int) and self.safety_horizon >= 0
        ):
            raise config_error(f"safety_horizon must be an integer >= 0 [steps], got {self.safety_horizon!r}")
        if isinstance(self.safety_search, bool) or not (
            isinstance(self.safety_search, int) and self.safety_search >= 0
        ):
            raise config_error(f"safety_search must be an integer >= 0 [paths], got {self.safety_search!r}")
        if not _is_finite_nonnegative(self.safety_mover_uncertainty):
            raise config_error(
                f"safety_mover_uncertainty must be a number >= 0 [m/s], got {self.safety_mover_uncertainty!r}"
            )
        if not isinstance(self.safety_world, KnownWorld):  # its fields are checked where it is made
            raise config_error(
                f"safety_world must be a KnownWorld (core.safety.layer), got {self.safety_world!r}"
            )
        if isinstance(self.chunk_smoothing, bool) or not (
            isinstance(self.chunk_smoothing, int) and self.chunk_smoothing >= 0
        ):
            raise config_error(
                f"chunk_smoothing must be an integer >= 0 [passes], got {self.chunk_smoothing!r}"
            )
        if not _is_finite_nonnegative(self.sampling_guidance):
            raise config_error(
                f"sampling_guidance must be a finite step >= 0, got {self.sampling_guidance!r}"
            )
        if self.sampling_guidance and self.inference_backend == "eager":
            raise config_error(
                "sampling_guidance > 0 runs in the lean and trace samplers, got inference_backend='eager' "
                "(pass --policy.inference_backend=trace)"
            )
        if self.sampling_guidance and self.noise_scheduler_type != "DDIM":
            raise config_error(
                "sampling_guidance > 0 guides DDIM's steps, got noise_scheduler_type="
                f"{self.noise_scheduler_type!r} (pass --policy.noise_scheduler_type=DDIM, or "
                "--policy.sampling_guidance=0)"
            )
        if self.safety_layer and not (
            get_encoding(self.obstacle_encoding).egocentric and self.fixed_action_bounds
        ):  # the layer reads body-frame obstacles and scores physical actions
            raise config_error(
                f"the safety layer (num_candidates={self.num_candidates}, safety_filter={self.safety_filter!r}, "
                f"sampling_guidance={self.sampling_guidance}) "
                f"needs an egocentric obstacle encoding ({' or '.join(map(repr, egocentric_encodings()))}) and "
                "fixed_action_bounds=true; this policy "
                f"has obstacle_encoding={self.obstacle_encoding!r}, fixed_action_bounds={self.fixed_action_bounds} "
                f"(the standard policy, the layer off: {' '.join(f'--policy.{k}={v}' for k, v in LAYER_OFF.items())})"
            )
        super().__post_init__()

    @property
    def action_low(self) -> tuple[float, float]:
        """The env's lower action bounds [v, omega] (``ACTION_LOW``), not a setting."""
        return ACTION_LOW

    @property
    def action_high(self) -> tuple[float, float]:
        """The env's upper action bounds [v, omega] (``ACTION_HIGH``), not a setting."""
        return ACTION_HIGH

    def _check_tokens(self) -> None:
        """The checks of ``obstacle_encoder="tokens"``, each a one-line error naming field and value."""
        if token_layout(get_encoding(self.obstacle_encoding), self.max_obstacles) is None:
            raise config_error(
                "obstacle_encoder='tokens' needs an obstacle-slot encoding of the 'nearest' family, "
                f"got obstacle_encoding={self.obstacle_encoding!r} (max_obstacles={self.max_obstacles})"
            )
        env_norm = self.normalization_mapping.get("ENV", NormalizationMode.IDENTITY)
        if env_norm != NormalizationMode.IDENTITY:  # the encoder reads metres and the present flags
            raise config_error(
                f"obstacle_encoder='tokens' reads environment_state in metres, got normalization_mapping "
                f"ENV={getattr(env_norm, 'value', env_norm)!r} (set it to IDENTITY)"
            )
        dim = self.token_dim
        if isinstance(dim, bool) or not (isinstance(dim, int) and dim > 0 and dim % TOKEN_HEADS == 0):
            raise config_error(
                f"token_dim must be a positive multiple of {TOKEN_HEADS} (the attention heads), got token_dim={dim!r}"
            )

    @property
    def safety_layer(self) -> bool:
        """Whether anything reads the observed obstacles at inference: best-of-K, the filter or the
        clearance guidance."""
        return self.num_candidates > 1 or self.safety_filter != "none" or self.sampling_guidance > 0

    @property
    def plans_per_episode(self) -> bool:
        """Whether ``select_action`` runs the ``Replanner`` (safety layer, warm starts or chunk
        smoothing: each needs the episode's own plan and last command) instead of LeRobot's action
        queue."""
        return self.safety_layer or self.warm_start_step > 0 or self.chunk_smoothing > 0

    def validate_features(self) -> None:
        """Check the formation features; the error names the feature, its shape and what was found."""
        inputs = self.input_features or {}
        found = f"Input features found: {_describe(inputs)}."
        state = inputs.get(OBS_STATE)
        if state is None or state.type is not FeatureType.STATE:
            raise ValueError(
                f"formation_diffusion needs the input feature '{OBS_STATE}' (STATE, shape ({STATE_DIM},): "
                f"midpoint [x, y, cos phi, sin phi, x', y', omega]). {found}"
            )
        if tuple(state.shape) != (STATE_DIM,):
            raise ValueError(
                f"'{OBS_STATE}' must have shape ({STATE_DIM},) (midpoint [x, y, cos phi, sin phi, x', y', "
                f"omega]), got {tuple(state.shape)}"
            )
        env_state = inputs.get(OBS_ENV_STATE)
        if env_state is None or env_state.type is not FeatureType.ENV:
            raise ValueError(
                f"formation_diffusion needs the input feature '{OBS_ENV_STATE}' (ENV, shape "
                f"({environment_state_dim(self.obstacle_encoding, self.max_obstacles)},): obstacle_encoding "
                f"{self.obstacle_encoding!r}). {found}"
            )
        expected = environment_state_dim(self.obstacle_encoding, self.max_obstacles)
        if tuple(env_state.shape) != (expected,):
            raise ValueError(
                f"'{OBS_ENV_STATE}' has shape {tuple(env_state.shape)}, but obstacle_encoding="
                f"{self.obstacle_encoding!r} with max_obstacles={self.max_obstacles} has ({expected},): set "
                f"--policy.obstacle_encoding to the dataset's encoding ({_encoding_sizes()}), or use a "
                f"dataset and env of --env.obstacle_encoding={self.obstacle_encoding}"
            )
        if self.egocentric_obstacles and get_encoding(self.obstacle_encoding).egocentric:
            raise ValueError(
                f"egocentric_obstacles=true rewrites a world-frame list; '{self.obstacle_encoding}' is already "
                "egocentric: set --policy.egocentric_obstacles=false"
            )
        grid_list_dim = environment_state_dim("grid+list", self.max_obstacles)
        if self.egocentric_obstacles and tuple(env_state.shape) != (grid_list_dim,):
            raise ValueError(
                f"egocentric_obstacles=true needs '{OBS_ENV_STATE}' in the 'grid+list' encoding "
                f"({grid_list_dim} values), got {tuple(env_state.shape)}; "
                "set --policy.egocentric_obstacles=false or --env.obstacle_encoding=grid+list"
            )
        if self.image_features:
            raise ValueError(
                f"formation_diffusion takes no image features, got {sorted(self.image_features)}. {found}"
            )
        action = self.action_feature
        if action is None or tuple(action.shape) != (ACTION_DIM,):
            raise ValueError(
                f"formation_diffusion needs the output feature '{ACTION}' (ACTION, shape ({ACTION_DIM},): "
                f"[v, omega]). Output features found: {_describe(self.output_features)}."
            )
        super().validate_features()

    def set_dataset_feature_metadata(self, dataset_features: dict) -> None:
        """Refuse a dataset whose observation sizes differ from this policy's (LeRobot's ``make_policy``
        calls this with the dataset's ``meta.features`` before it builds the policy). Fine-tuning a
        checkpoint (``--policy.path``) keeps the checkpoint's input features, so a dataset of another
        obstacle encoding would otherwise fail at the first step with a matrix-shape error."""
        for key, feature in (self.input_features or {}).items():
            theirs = (
                dataset_features.get(key, {}).get("shape") if isinstance(dataset_features, dict) else None
            )
            if theirs is None or tuple(theirs) == tuple(feature.shape):
                continue
            if key != OBS_ENV_STATE:
                raise config_error(
                    f"the dataset gives '{key}' shape {tuple(theirs)}, but the policy takes {tuple(feature.shape)}"
                )
            # the encoding is stored (never guessed); the dataset's is named when its size says which
            dims = {environment_state_dim(e, self.max_obstacles): e for e in ENCODINGS}
            ours = self.obstacle_encoding
            named = f" ({dims[theirs[0]]!r})" if len(theirs) == 1 and theirs[0] in dims else ""
            raise config_error(
                f"the dataset gives '{key}' shape {tuple(theirs)}{named}, but the policy takes "
                f"{tuple(feature.shape)} ({ours!r}): train on a dataset of the policy's encoding "
                f"(lerobot-formation-generate --obstacle-encoding {ours})"
            )

    def get_optimizer_preset(self) -> AdamWConfig:
        """AdamW, as the paper and the original Diffusion Policy train (DiffusionConfig's preset is Adam)."""
        return AdamWConfig(
            lr=self.optimizer_lr,
            betas=self.optimizer_betas,
            eps=self.optimizer_eps,
            weight_decay=self.optimizer_weight_decay,
        )


# A formation_diffusion config.json written before a field was retired or turned on loads through
# compat.run_checks (its field dropped where the code runs its value, else a one-line error).
install_config_upgrade()
