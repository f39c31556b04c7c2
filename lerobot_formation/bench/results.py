"""The bench's results: per-controller metrics, ``results.json`` and ``tables.md``."""

from __future__ import annotations

import contextlib
import json
import os
import time
from pathlib import Path

import numpy as np

from lerobot_formation.bench.artifacts import bench_command, host_description
from lerobot_formation.bench.paper_tables import adaptive_table, three_way_table
from lerobot_formation.bench.settings import BenchSettings
from lerobot_formation.core.episodes.metrics import (
    FLAG_KEYS,
    STRUCK_KEY,
    episode_metrics,
    mover_strikes,
    summarize,
)
from lerobot_formation.core.episodes.rollout import OUTCOME_NAMES, EpisodeRecords
from lerobot_formation.core.world.dynamics import FormationParams
from lerobot_formation.core.world.sampling import SamplingReport
from lerobot_formation.core.world.scenes import Scenes

# the bench's own files in an output folder: one of them there means the folder holds a run
RUN_FILES = ("results.json", "tables.md")


def existing_run(out: Path) -> str | None:
    """The first of the bench's own files (``RUN_FILES``) in folder ``out``: it holds a run; else None."""
    return next((name for name in RUN_FILES if (Path(out) / name).exists()), None)


def _clean(x):
    if isinstance(x, float | np.floating):
        return None if not np.isfinite(x) else float(x)
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    return x


def safety_rates(stats: dict) -> dict:
    """The safety layer's intervention rates from a controller's ``stats`` counts
    (``policy.replanner.STAT_KEYS``): the share of steps whose action the CBF filter changed
    (``filter_intervention_rate``; x 100: per 100 steps), and the shares of replans where best-of-K
    found no safe candidate, kept an escape manoeuvre, stopped, or kept route pursuit's proposal
    (``proposal_rate``; with a route hint); the share of steps where a kept chunk failed its
    check on the newer view and the episode replanned (``recheck_rate``; ``safety_recheck``)."""
    replans = max(stats["replans"], 1)
    return {
        "filter_intervention_rate": stats["filter_interventions"] / max(stats["steps"], 1),
        "recheck_rate": stats.get("rechecks_failed", 0) / max(stats["steps"], 1),
        "replans_none_safe_rate": stats["replans_none_safe"] / replans,
        "escape_rate": stats["escapes"] / replans,
        "stop_rate": stats["stops"] / replans,
        "proposal_rate": stats.get("proposals", 0) / replans,
    }


def safety_table(results: dict, label: str, order: tuple[str, ...] = ()) -> str:
    """``tables.md``'s table of how often the safety layer intervened, per controller that has one
    (``results[name]["safety"]``); empty without any."""
    names = [n for n in dict.fromkeys((*order, *results)) if n in results and "safety" in results[n]]
    if not names:
        return ""
    lines = [
        f"### Safety layer interventions on {label}",
        "",
        "| Controller | Steps | Filter interventions / 100 steps | Replans | No safe candidate % | "
        "Escape manoeuvre % | Stop % | Route proposal % | Failed rechecks / 100 steps |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for n in names:
        st = results[n]["safety"]
        rates = safety_rates(st)
        lines.append(
            f"| {n} | {st['steps']} | {100 * rates['filter_intervention_rate']:.2f} | {st['replans']} | "
            f"{100 * rates['replans_none_safe_rate']:.1f} | {100 * rates['escape_rate']:.1f} | "
            f"{100 * rates['stop_rate']:.1f} | {100 * rates['proposal_rate']:.1f} | "
            f"{100 * rates['recheck_rate']:.2f} |"
        )
    lines += [
        "",
        "Filter interventions: actions the CBF filter changed; the percentages are of best-of-K's "
        "replans (an escape manoeuvre is kept only when no sampled chunk is safe; the route proposal is "
        "route pursuit's chunk, scored beside the sampled ones where the policy observes a route hint; a failed "
        "recheck: a kept chunk that no longer passed the check on a newer view, replanned at once, "
        "``safety_recheck``).",
        "",
    ]
    return "\n".join(lines)


def collisions_text(entry: dict) -> str:
    """A controller summary's collision count as printed, "collisions N", with "(k struck by a mover)"
    where k > 0 of them were a moving obstacle striking a team that was not closing on it
    (``core.episodes.metrics.mover_strikes``)."""
    struck = entry.get(STRUCK_KEY)
    return f"collisions {entry['collisions']}" + (f" ({struck} struck by a mover)" if struck else "")


def controller_results(
    rec: EpisodeRecords, scenes: Scenes, indices=None, agent_radius: float = FormationParams.agent_radius
) -> dict:
    """A controller's summary (``summarize``) plus ``episodes``: per episode its ``scene_index`` in
    the scene set (``indices[b]``, default b: a shard keeps the whole set's), seed, outcome, steps and
    metrics, ``struck_by_mover`` among them (``core.episodes.metrics.mover_strikes`` with the agents'
    ``agent_radius``)."""
    per = episode_metrics(rec, scenes.start, scenes.goal)
    per[STRUCK_KEY] = mover_strikes(rec, scenes.obstacles, scenes.mask, agent_radius)
    summary = summarize(per)
    indices = np.arange(len(rec)) if indices is None else np.asarray(indices)
    episodes = []
    for b in range(len(rec)):
        seed = int(scenes.seeds[b])
        e = {
            "scene_index": int(
                indices[b]
            ),  # in the whole scene set (a shard keeps it); names a scene of a file
            "seed": seed if seed >= 0 else None,  # None: a scene of a file, it has no seed
            "outcome": OUTCOME_NAMES[int(rec.outcome[b])],
            "steps": int(rec.steps[b]),
        }
        e.update({k: _clean(v[b]) for k, v in per.items() if k not in FLAG_KEYS})
        episodes.append(e)
    summary["episodes"] = episodes
    return summary


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file ``.NAME.tmp-PID`` beside it, flushed to disk,
    then renamed into place: ``path`` is either the old file or the whole new one, and on any error
    (a full disk) the temporary file is removed and the error raised."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())  # a full disk often shows only here
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_results(
    out: Path,
    results: dict,
    label: str,
    settings: BenchSettings,
    report: SamplingReport,
    error: str | None = None,
    conditions: dict | None = None,
    figure_errors: list[str] | None = None,
    unseen_conditions: dict | None = None,
    resumed: dict[str, list[str]] | None = None,
):
    """results.json and tables.md of the controllers in ``results`` (each written atomically,
    ``atomic_write_text``); ``error`` marks a run that stopped early (``meta.incomplete``,
    ``meta.error``), with what finished before it; ``conditions``: the realistic conditions that were
    on (``Conditions.changed()``), kept as ``meta.conditions``, and those of the unseen set as
    ``meta.unseen_conditions``; ``figure_errors`` lists figures that failed; ``resumed``: per scene
    set, the controllers whose results were kept from an earlier run in the folder (``--resume``)."""
    # results.json: keyed by controller for the main scene set (the world issue's keys), plus the
    # other scene sets under "by_scenes".
    payload = dict(results.get(label, {}))
    payload["by_scenes"] = {k: v for k, v in results.items()}
    payload["meta"] = {
        "scenes": settings.scenes,
        "unseen": settings.unseen,
        "seed": settings.seed,
        "policy_path": settings.options.policy_path,
        "candidates": settings.options.candidates,
        "num_inference_steps": settings.options.num_inference_steps,
        "seed_policy": settings.options.seed_policy,
        "date": time.strftime("%Y-%m-%d"),
        "command": bench_command(),  # None when main() is called from Python (a test)
        "host": host_description(),
        "device": settings.options.device,
        "scene_sampling": report.as_dict() if report.drawn else None,
        "shard": settings.shard,
        "incomplete": error is not None,
        "error": error,
        "figure_errors": figure_errors or [],
        "resumed": resumed or {},
    }
    payload["meta"]["conditions"] = conditions or {}  # the fields not at their default
    payload["meta"]["unseen_conditions"] = unseen_conditions or {}  # a level's own when --unseen is a level
    atomic_write_text(out / "results.json", json.dumps(payload, indent=1, default=_clean))
    tables = [three_way_table(results.get(label, {}), f"{label} scenes ({settings.scenes})", settings.order)]
    for name, by_controller in results.items():
        spec = settings.unseen if name == "unseen" else settings.scenes
        table = safety_table(by_controller, f"{name} scenes ({spec})", settings.order)
        if table:
            tables.append(table)
    sets = {k: v for k, v in results.items() if any(c in settings.policy_controllers for c in v)}
    if sets:
        specs = {label: settings.scenes, "unseen": settings.unseen or ""}
        tables.append(adaptive_table(sets, specs, settings.policy_controllers))
    if error is not None:
        tables.append(f"**Incomplete run**: {error}\n")
    atomic_write_text(out / "tables.md", "\n".join(tables))
