"""The start-up checks of a formation run (no torch; LeRobot and draccus only inside the installers).

- ``ConfigError`` (a ``ValueError``): a config value, a checkpoint or an output folder that a run
  refuses; the message names the value and what to do. draccus wraps a ``ValueError`` raised while it
  builds a config in ``ParsingError("Couldn't instantiate class ...")``; ``one_line_config_errors`` and
  ``config_errors_in_draccus_messages`` make LeRobot's CLIs print it as one ``error:`` line.
- ``lerobot-train``'s start (``install_train_checks``): a missing ``--dataset.root`` offline is one
  clear error, the output folder is locked (below), and a resumed run with nothing left to train says so.
- A ``formation_diffusion`` ``config.json`` of an earlier version (``install_config_upgrade``, installed
  when the policy config module is imported): every local one that ``PreTrainedConfig.from_pretrained``
  loads is read through ``drop_retired_fields`` (the file is left as it is): a retired field
  (``RETIRED_FIELDS``) is dropped where it holds the value the code now hard-wires, any other value is
  one line naming the field, its value and the wired one; a safety-layer setting that is now fixed
  (``FIXED_LAYER_FIELDS``) is dropped, with one warning line where the value it held (or, lacking
  it, ran with) is not the wired one; the six flat fields of what the layer knows of the world
  (``WORLD_FIELDS``) move into ``safety_world``, and the two lookaheads (``LOOKAHEAD_FIELDS``)
  become ``safety_horizon``; a field whose default now turns part of the shipped safety layer on
  (``FIELDS_BEFORE``) is, where the file lacks it (it predates the field), the value it ran with.
  ``compat.old_checkpoints`` rewrites such a folder in place.
- The env config meets the policy config (``hand_env_its_policy``): ``lerobot-train`` and
  ``lerobot-eval``'s pipeline configs hand ``FormationEnvConfig`` the run's policy config: an env
  whose obstacle encoding the user did not give takes the policy's (a given one that differs is an
  error naming both), and its ``get_env_processors`` checks the policy against the env's observation.

``install_run_hooks`` switches these on; our configs call it when they are built, so a LeRobot run of
another project is untouched. This module imports nothing else of ours: every config imports it.

One ``lerobot-train`` run per output folder: a lock file beside it, ``.NAME.train-lock``.

LeRobot refuses an existing ``--output_dir`` only when a run starts and creates the folder at its
first checkpoint, so two runs started into the same new folder (or two resumes of one run) both
train and overwrite each other's checkpoints. In a formation run ``TrainPipelineConfig.validate``
(the first thing ``lerobot-train`` does) takes an exclusive ``flock`` on ``.NAME.train-lock`` beside
an explicitly given ``--output_dir`` and writes its pid into it; a second run finds the lock held and
refuses with a ``ConfigError`` naming that pid. The lock belongs to the open file, so it ends with
the process however it ends (even SIGKILL): a lock file left by a dead process blocks nothing, the
next run simply takes it over. A run that exits normally removes the file. Only the main process of
a multi-process (``accelerate``) run locks. Where ``fcntl`` is missing (Windows) there is no lock.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import logging
import os
import sys
import tempfile
from pathlib import Path


class ConfigError(ValueError):
    """A config value, a checkpoint or an output folder that a run refuses; the message names the
    value and what to do."""


def config_error_in_chain(exc: BaseException | None) -> ValueError | None:
    """The first ``ConfigError`` in ``exc`` and its causes / contexts, or None. An error of a config
    value raised in the numpy core (which imports nothing of this module), e.g. by a nested settings
    dataclass that draccus builds before our config (``core.safety.layer.KnownWorld``), counts as
    one where its class says so (``config_error = True``)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, ConfigError) or getattr(type(exc), "config_error", False):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def config_error(message: str) -> ConfigError:
    """A ``ConfigError`` (a ValueError) for an invalid config value. draccus wraps it in
    "Couldn't instantiate class ..."; in a formation run LeRobot's CLIs print the message as one line
    (``install_run_hooks``)."""
    return ConfigError(message)


try:
    import fcntl
except ImportError:  # not POSIX
    fcntl = None

_held: dict[Path, int] = {}  # output folder -> file descriptor of its lock, held by this process


def lock_path(output_dir: Path) -> Path:
    """The lock file of ``output_dir``: ``.NAME.train-lock`` beside it (not inside: LeRobot refuses
    an existing output folder on a fresh run)."""
    output_dir = Path(output_dir).absolute()
    return output_dir.parent / f".{output_dir.name}.train-lock"


def is_main_process() -> bool:
    """False in the non-main processes of an ``accelerate launch`` (environment variable RANK)."""
    return os.environ.get("RANK", "0") in ("", "0")


def acquire_output_lock(output_dir: Path) -> Path | None:
    """Lock ``output_dir`` for this process (idempotent); returns the lock file, None without fcntl.

    Raises:
        ConfigError: another live process holds the lock (its pid is in the message).
    """
    if fcntl is None:
        return None
    output_dir = Path(output_dir).absolute()
    lock = lock_path(output_dir)
    if output_dir in _held:
        return lock
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise ConfigError(
                f"--output_dir {output_dir} is in use by another lerobot-train run (pid {holder}); wait for it "
                f"to finish or choose another --output_dir (lock file {lock})"
            ) from None
        try:  # the holder may have removed the file between our open and our lock: lock the new one
            current = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _held[output_dir] = fd
    return lock


def release_output_lock(output_dir: Path) -> None:
    """Remove the lock file of ``output_dir`` and unlock it (no-op if this process holds none)."""
    output_dir = Path(output_dir).absolute()
    fd = _held.pop(output_dir, None)
    if fd is None:
        return
    with contextlib.suppress(OSError):
        os.unlink(lock_path(output_dir))  # while still locked, so no one locks the old file meanwhile
    os.close(fd)


@atexit.register
def _release_all() -> None:
    for output_dir in list(_held):
        release_output_lock(output_dir)


def check_dataset_root_offline(root) -> None:
    """Refuse a ``--dataset.root`` folder that does not exist while the hub is offline.

    LeRobot looks a missing root up on the hub, which offline (``HF_HUB_OFFLINE=1``) surfaces as a
    ~60-line ``OfflineModeIsEnabled`` traceback from deep inside ``lerobot-train``. Online, a missing
    root is where LeRobot downloads to, and stays allowed.

    Raises:
        ConfigError: ``root`` is set, does not exist, and the hub is offline.
    """
    if root is None or Path(root).exists():
        return
    from huggingface_hub import constants

    if constants.HF_HUB_OFFLINE:
        raise ConfigError(
            f"--dataset.root {root} does not exist, and HF_HUB_OFFLINE is set, so LeRobot cannot download "
            f"it; check the path, or write the dataset there with lerobot-formation-generate --root {root}"
        )


def hand_env_its_policy(pipeline) -> None:
    """Give the run's env config its policy config: ``pipeline.env.run_policy = pipeline.policy`` when
    the env config declares ``run_policy`` (``FormationEnvConfig``; other env configs are left alone),
    and let it take the policy's observation encoding where the user gave none
    (``FormationEnvConfig.take_policy_encoding``; a given one that differs is a ``ConfigError``).

    LeRobot's ``make_env_pre_post_processors(env_cfg, policy_cfg)`` calls ``env_cfg.get_env_processors()``
    with no argument, and our env checks there that the policy takes its observation; the policy's
    input features are known only then (``make_policy`` fills them in place), so the env keeps the
    config object, not a copy."""
    env = getattr(pipeline, "env", None)
    if env is not None and hasattr(type(env), "run_policy"):
        env.run_policy = pipeline.policy
        if pipeline.policy is not None and hasattr(env, "take_policy_encoding"):
            env.take_policy_encoding(pipeline.policy)


def report_resume_with_nothing_to_train(resume: bool, steps: int, checkpoint_path, step: int) -> str | None:
    """When ``lerobot-train --resume=true`` resumes a run whose checkpoint is at ``step`` >= its
    ``--steps``, log why it will train 0 steps and return that line (else None). LeRobot then just
    saves nothing and ends ("End of training") without saying why."""
    if not resume or step < steps:
        return None
    line = (
        f"resume: the checkpoint {checkpoint_path} is at step {step} and the run's --steps is {steps}, so "
        f"there is nothing to train (0 steps); pass --steps=N with N > {step} to train on"
    )
    logging.getLogger("lerobot_formation").warning(line)
    return line


def _checkpoint_step(checkpoint_path) -> int | None:
    """The training step of a ``lerobot-train`` checkpoint folder (``training_state/training_step.json``,
    read as LeRobot reads it when it resumes); None if that file is missing."""
    from lerobot.common.train_utils import load_training_step
    from lerobot.utils.constants import TRAINING_STATE_DIR, TRAINING_STEP

    state_dir = Path(checkpoint_path) / TRAINING_STATE_DIR
    if not (state_dir / TRAINING_STEP).is_file():
        return None  # LeRobot reports it when it loads the checkpoint
    return load_training_step(state_dir)


def install_train_checks() -> None:
    """Wrap ``TrainPipelineConfig.validate`` (the start of ``lerobot-train``; idempotent). LeRobot has
    no hook for a plugin here. Around LeRobot's own checks, in this order:

    - a missing ``--dataset.root`` while offline is one ``ConfigError`` (``check_dataset_root_offline``);
    - an explicitly given ``--output_dir`` is locked for the run (``acquire_output_lock``): a second run
      into the same folder refuses with the first one's pid; the lock is dropped if LeRobot's checks fail;
    - then the env config gets the resolved policy config (``hand_env_its_policy``), and a resumed run
      that has nothing left to train says so (``report_resume_with_nothing_to_train``).
    """
    from lerobot.configs.train import TrainPipelineConfig

    original = TrainPipelineConfig.validate
    if getattr(original, "_formation_train_checks", False):
        return

    def validate(self) -> None:
        check_dataset_root_offline(getattr(self.dataset, "root", None))
        given = Path(self.output_dir) if self.output_dir and is_main_process() else None
        if given is not None:
            acquire_output_lock(given)
        try:
            original(self)
        except BaseException:
            if given is not None:
                release_output_lock(given)
            raise
        hand_env_its_policy(self)
        if self.resume and self.checkpoint_path is not None and is_main_process():
            step = _checkpoint_step(self.checkpoint_path)
            if step is not None:
                report_resume_with_nothing_to_train(True, self.steps, self.checkpoint_path, step)

    validate._formation_train_checks = True  # type: ignore[attr-defined]
    TrainPipelineConfig.validate = validate


def install_eval_checks() -> None:
    """Wrap ``EvalPipelineConfig.__post_init__`` (``lerobot-eval``'s config, which loads the policy
    config of ``--policy.path``; idempotent) so that the env config gets that policy config
    (``hand_env_its_policy``). Our env config, built first by draccus, installs this before the
    pipeline config is made."""
    from lerobot.configs.eval import EvalPipelineConfig

    original = EvalPipelineConfig.__post_init__
    if getattr(original, "_formation_eval_checks", False):
        return

    def post_init(self) -> None:
        original(self)
        hand_env_its_policy(self)
        env = getattr(self, "env", None)
        if env is not None and hasattr(type(env), "run_eval_seed"):
            env.run_eval_seed = self.seed if isinstance(self.seed, int) else None

    post_init._formation_eval_checks = True  # type: ignore[attr-defined]
    EvalPipelineConfig.__post_init__ = post_init


def config_errors_in_draccus_messages() -> None:
    """Make a draccus ``DecodingError`` caused by a ``ConfigError`` read as that error's message.

    ``lerobot-train --policy.type=...`` decodes the policy as an optional field (a union): draccus
    turns the error of a bad value into ``DecodingError("`policy`: Could not decode the value into any
    of the given types: ... Couldn't instantiate class FormationDiffusionConfig using the given
    arguments.")``, which LeRobot's parser prints as ``error: ...`` and exits: the reason is lost.
    With this (idempotent) wrap of ``DecodingError.__str__`` that line is ``error: <the reason>``; a
    DecodingError of any other cause reads as before.
    """
    from draccus.utils import DecodingError

    original = DecodingError.__str__
    if getattr(original, "_formation_config_error", False):
        return

    def message(self) -> str:
        error = config_error_in_chain(self.__cause__)
        return str(error) if error is not None else original(self)

    message._formation_config_error = True  # type: ignore[attr-defined]
    DecodingError.__str__ = message


def one_line_config_errors() -> None:
    """Install a ``sys.excepthook`` (idempotent) that prints an uncaught exception whose chain holds a
    ``ConfigError`` as one line ``error: <message>`` (exit status 1, as for any uncaught exception);
    every other exception goes to the previous hook unchanged. draccus wraps the error of a config
    value in "Couldn't instantiate class ..." and LeRobot's CLIs let that escape with the parser's
    ~70-line traceback."""

    previous = sys.excepthook
    if getattr(previous, "_formation_one_line", False):
        return

    def hook(exc_type, exc, tb):
        error = config_error_in_chain(exc)
        if error is None:
            previous(exc_type, exc, tb)
        else:
            print(f"error: {error}", file=sys.stderr)

    hook._formation_one_line = True  # type: ignore[attr-defined]
    sys.excepthook = hook


def install_run_hooks() -> None:
    """The start-up checks of a formation run, switched on when one of our configs is built (so a
    LeRobot run of another project is untouched): an uncaught ``ConfigError`` is one ``error:`` line
    (``one_line_config_errors``, ``config_errors_in_draccus_messages``), ``lerobot-train`` checks its
    ``--dataset.root`` and locks its ``--output_dir`` (``install_train_checks``), and ``lerobot-train``
    / ``lerobot-eval`` hand our env config the run's policy config (``install_train_checks``,
    ``install_eval_checks``). Idempotent."""
    one_line_config_errors()
    config_errors_in_draccus_messages()
    install_train_checks()
    install_eval_checks()


# -- a config.json of an earlier version -----------------------------------------------------------------
# field -> the value the code now runs with
RETIRED_FIELDS = {
    # experiment settings now (scripts/ablation.py, ReplanExperiment)
    "escape_advantage": None,
    "blocked_fallback": "widest",
    "replan_blend_steps": 0,
    "egocentric_state": False,
    # the shipped safety layer's, now wired (core.safety.layer's constants)
    "safety_escape_speeds": [0.0, 0.1, 0.2, 0.3, 0.45, 0.6],
    "safety_fallback_all": True,
    "safety_recheck": True,
    "safety_progress_resolution": 0.4,
    "safety_progress_interpolation": "bilinear",
    "warm_start_all_candidates": True,
    "replan_on_intervention": True,
    "guidance_distance": 0.3,
    "guidance_steps": 1,
    # experiments that were not kept
    "safety_fallback_lookahead": 0,
    "timestep_spacing": "leading",
    # one attention layer is all the token encoder was ever trained with (ObstacleTokenEncoder's default)
    "token_layers": 1,
    # diffusers' EMA defaults (modeling_formation_diffusion.EMA_*), and the env's action bounds
    "ema_inv_gamma": 1.0,
    "ema_min_decay": 0.0,
    "ema_max_decay": 0.9999,
    "ema_update_after_step": 0,
    "action_low": [0.0, -1.5],
    "action_high": [0.6, 1.5],
}

EXPERIMENT_SETTINGS = ("escape_advantage", "blocked_fallback", "replan_blend_steps")

# field -> the value a config.json without it ran with: fields whose default is now the shipped
# policy's layer (LeRobot writes every field, so a config.json lacking one predates it)
FIELDS_BEFORE = {
    "fixed_action_bounds": False,
    "num_candidates": 1,
    "safety_filter": "none",
    "safety_margin": 0.1,
    "safety_horizon": 0,
    "safety_mover_uncertainty": 0.0,
    "safety_search": 0,
    "warm_start_step": 0,
    "chunk_smoothing": 0,
    "sampling_guidance": 0.0,
    "inference_backend": "eager",
}

# The safety layer's settings that are fixed now (core.safety.layer's constants CBF_RATE,
# FOLLOWER_MARGIN, ROUTE_PROPOSAL, PROPOSAL_BLEND, COHERENCE): field -> (the wired value, the value a
# config.json written before the field ran with). Dropped; another value is one warning line, not a
# refusal (a K = 1 checkpoint never used them).
FIXED_LAYER_FIELDS = {
    "cbf_rate": (4.0, 2.0),
    "safety_follower_margin": (0.03, 0.0),
    "safety_route_proposal": (True, False),
    "safety_proposal_blend": (4, 0),
    "safety_coherence": (1.0, 0.0),
}
# What the layer knows of the world, once six flat fields: field -> its name in ``safety_world``
WORLD_FIELDS = {
    "safety_moving_obstacles": "moving_obstacles",
    "safety_action_delay": "action_delay",
    "safety_max_linear_accel": "max_linear_accel",
    "safety_max_angular_accel": "max_angular_accel",
    "safety_obstacle_noise": "obstacle_noise",
    "safety_pose_noise": "pose_noise",
}
# The route and the halt lookahead, now one ``safety_horizon`` (each 0 in a config.json before it)
LOOKAHEAD_FIELDS = ("safety_route_lookahead", "safety_halt_lookahead")
# A config.json that has one of these was written after the fields above were folded in.
CURRENT_LAYER_FIELDS = ("safety_horizon", "safety_world")


class OldCheckpointError(ConfigError):
    """A checkpoint that cannot be carried over as it is (the message says which field and why); a
    ``ConfigError``, so a LeRobot CLI prints it as one line."""


def _as_json(value):
    return list(value) if isinstance(value, tuple) else value


def _warn(line: str) -> None:
    logging.getLogger("lerobot_formation").warning(line)


def _fold_layer_fields(out: dict, where: str) -> None:
    """The safety layer's fields of an earlier version folded into the current ones, in ``out``
    (the module docstring): ``WORLD_FIELDS`` into ``safety_world``, ``LOOKAHEAD_FIELDS`` into
    ``safety_horizon`` (where they differ, the route lookahead's value and a warning naming both),
    ``FIXED_LAYER_FIELDS`` dropped (a warning where the value is not the wired one)."""
    current = any(key in out for key in CURRENT_LAYER_FIELDS)
    flat = {name: out.pop(key) for key, name in WORLD_FIELDS.items() if key in out}
    if flat:
        out["safety_world"] = {**flat, **(out.get("safety_world") or {})}
    lookaheads = {key: out.pop(key) for key in LOOKAHEAD_FIELDS if key in out}
    if lookaheads and "safety_horizon" not in out:
        route, halt = (lookaheads.get(key, 0) for key in LOOKAHEAD_FIELDS)
        if route != halt:
            _warn(
                f"{where}: safety_route_lookahead={json.dumps(route)} and safety_halt_lookahead="
                f"{json.dumps(halt)} are one safety_horizon now; it takes the route lookahead's "
                f"{json.dumps(route)}"
            )
        out["safety_horizon"] = route
    for key, (wired, before) in FIXED_LAYER_FIELDS.items():
        given = key in out
        if not given and current:
            continue
        value = out.pop(key, before)
        if value != wired:
            ran = "" if given else " (the file predates the field: it ran with that)"
            _warn(
                f"{where}: {key}={json.dumps(value)}{ran} is not run any more: the layer's setting is now "
                f"fixed at {json.dumps(wired)}"
            )


def drop_retired_fields(raw: dict, where: str = "config.json") -> dict:
    """The policy config dict ``raw`` without retired fields, with the safety layer's fields of an
    earlier version folded into the current ones (``_fold_layer_fields``) and with ``FIELDS_BEFORE``
    where it lacks them (the module docstring); ``raw`` itself is left as it is.

    Raises:
        OldCheckpointError: a retired field holds another value than the one the code runs.
    """
    out = dict(raw)
    for key, wired in RETIRED_FIELDS.items():
        if key not in out:
            continue
        if _as_json(out[key]) != wired:
            gone = (
                "it is an experiment setting now (scripts/ablation.py, ReplanExperiment)"
                if key in EXPERIMENT_SETTINGS
                else "no setting of this version runs another"
            )
            raise OldCheckpointError(
                f"{where}: retired field {key}={json.dumps(out[key])} differs from the value the policy "
                f"now runs with ({json.dumps(wired)}); {gone}"
            )
        del out[key]
    _fold_layer_fields(out, where)
    for key, before in FIELDS_BEFORE.items():
        out.setdefault(key, before)
    return out


def install_config_upgrade() -> None:
    """Read every local ``formation_diffusion`` ``config.json`` that ``PreTrainedConfig.from_pretrained``
    loads through ``drop_retired_fields`` (idempotent; the file is left as it is, the upgraded dict
    is parsed from a temporary folder). Other policy types, hub ids and current configs go to LeRobot's
    loader unchanged. A refused field is an ``OldCheckpointError`` (one ``error:`` line)."""
    from lerobot.configs.policies import PreTrainedConfig

    original = PreTrainedConfig.from_pretrained.__func__
    if getattr(original, "_formation_upgrade", False):
        return

    def from_pretrained(cls, pretrained_name_or_path, **kwargs):
        config_file = Path(str(pretrained_name_or_path)) / "config.json"
        try:
            raw = json.loads(config_file.read_text()) if config_file.is_file() else None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            raw = None  # LeRobot's loader reports it
        if isinstance(raw, dict) and raw.get("type") == "formation_diffusion":
            install_run_hooks()  # a formation run: the refusal below is one error line
            if raw.get("obstacle_encoding") is None:  # older than the field: its size decides, once
                raise OldCheckpointError(
                    f"{config_file} has no obstacle_encoding; carry the checkpoint over with "
                    f"python -m lerobot_formation.compat.old_checkpoints {config_file.parent}"
                )
            upgraded = drop_retired_fields(raw, str(config_file))
            if upgraded != raw:
                with tempfile.TemporaryDirectory() as tmp:
                    (Path(tmp) / "config.json").write_text(json.dumps(upgraded))
                    return original(cls, tmp, **kwargs)
        return original(cls, pretrained_name_or_path, **kwargs)

    from_pretrained._formation_upgrade = True  # type: ignore[attr-defined]
    PreTrainedConfig.from_pretrained = classmethod(from_pretrained)
