"""The bench's ``tables.md``: the paper's two tables (its numbers beside ours)."""

from __future__ import annotations

# The paper's Table "Three-way controller comparison on dataset" (100 episodes) and Table "Standard
# vs adaptive"; mean and std as printed.
PAPER_THREE_WAY = {
    "success_rate": (
        "Success Rate (%)",
        {"mppi": 65.0, "diffusion": 62.0, "pac": 100.0, "diffusion-bestof": 70.0},  # adaptive: Table 2
    ),
    "path_length": (
        "Path Length (m)",
        {"mppi": (9.35, 1.52), "diffusion": (9.12, 1.33), "pac": (9.38, 1.83)},
    ),
    "path_optimality": (
        "Path Optimality",
        {"mppi": (0.775, 0.120), "diffusion": (0.791, 0.110), "pac": (0.780, 0.133)},
    ),
    "tracking_deviation": (
        "Tracking Deviation (m)",
        {"mppi": (1.067, 0.447), "diffusion": (1.064, 0.419), "pac": (1.139, 0.513)},
    ),
    "min_clearance": (
        "Min Clearance (m)",
        {"mppi": (0.440, 0.193), "diffusion": (0.305, 0.237), "pac": (0.488, 0.140)},
    ),
    "mean_clearance": (
        "Mean Clearance (m)",
        {"mppi": (0.974, 0.164), "diffusion": (0.895, 0.174), "pac": (1.078, 0.180)},
    ),
    "mean_control": (
        "Mean Control Magnitude",
        {"mppi": (0.602, 0.079), "diffusion": (0.370, 0.031), "pac": (0.452, 0.050)},
    ),
    "control_smoothness": (
        "Control Smoothness",
        {"mppi": (4.538, 1.151), "diffusion": (0.336, 0.102), "pac": (1.164, 0.650)},
    ),
    "energy": ("Energy Usage", {"mppi": (10.20, 3.11), "diffusion": (5.31, 1.34), "pac": (6.95, 2.00)}),
    "time": ("Time (s)", {"mppi": (25.98, 10.20), "diffusion": (31.05, 6.75), "pac": (27.81, 6.49)}),
    "mean_velocity": (
        "Mean Velocity (m/s)",
        {"mppi": (0.390, 0.084), "diffusion": (0.297, 0.023), "pac": (0.340, 0.040)},
    ),
    "mean_curvature": (
        "Mean Curvature",
        {"mppi": (28.29, 52.73), "diffusion": (0.787, 0.606), "pac": (0.733, 0.388)},
    ),
    "peak_curvature": (
        "Peak Curvature",
        {"mppi": (6767, 15229), "diffusion": (5.28, 2.77), "pac": (5.51, 3.57)},
    ),
    "jerk": ("Motion Jerk", {"mppi": (23.10, 3.51), "diffusion": (0.359, 0.055), "pac": (0.576, 0.114)}),
    "orientation_stability": (
        "Orientation Stability",
        {"mppi": (0.202, 0.028), "diffusion": (0.188, 0.023), "pac": (0.225, 0.026)},
    ),
}
CLEARANCE_NOTE = (
    "Min and mean clearance (ours): the distance from the formation's midpoint to the nearest obstacle "
    "surface (SPEC's definition), minimum / mean over the episode. The paper does not define its "
    "clearance, so its 0.3-0.5 m may measure something else (e.g. from an agent's disc, which is "
    "smaller: our whole formation's minimum is the row 'Formation Min Clearance'); compare the two "
    "columns with that caveat."
)
EXTRA_ROWS = {
    "formation_min_clearance": "Formation Min Clearance (m), all episodes",
    "final_formation_error": "Final Formation Error (m)",
    "mean_follower_velocity_error": "Mean Follower Velocity Error (m/s)",
}
PAPER_ADAPTIVE = {
    ("unseen", "diffusion"): 25.0,
    ("unseen", "diffusion-bestof"): 26.0,
    ("dataset", "diffusion"): 62.0,
}
PAPER_ADAPTIVE[("dataset", "diffusion-bestof")] = 70.0
SET_TITLES = {
    "unseen": "Random seeds (unseen)",
    "random": "Random seeds (unseen)",
    "dataset": "Dataset episodes",
}


def is_paper_protocol(spec: str) -> bool:
    """Whether a --scenes value is one of the paper's protocols (random or dataset scenes), whose
    numbers the tables show beside ours."""
    return spec.split(":")[0] in ("random", "dataset", "")


def _fmt(mean, std, digits=3):
    if mean is None:
        return "n/a"
    return f"{mean:.{digits}g} ± {std:.{digits}g}" if std is not None else f"{mean:.{digits}g}"


def three_way_table(results: dict, label: str, order: tuple[str, ...] = ()) -> str:
    """The paper's Table "Three-way comparison" with ours; ``order``: the controllers' registry order."""
    # the paper's column order (MPPI, diffusion, PAC); other controllers before PAC, in registry order
    middle = [n for n in (*order, *results) if n not in ("mppi", "pac")]
    middle = list(dict.fromkeys(middle))
    cols = [c for c in ("mppi", *middle, "pac") if c in results]
    head = "| Metric | " + " | ".join(f"{c} (ours) | {c} (paper)" for c in cols) + " |"
    lines = [f"### Three-way comparison on {label}", "", head, "|---" * (1 + 2 * len(cols)) + "|"]
    for key, (title, paper) in PAPER_THREE_WAY.items():
        row = [title]
        for c in cols:
            r = results[c]
            if key == "success_rate":
                lo, hi = r["success_ci95"]
                row.append(f"{100 * r['success_rate']:.1f} [{100 * lo:.0f}, {100 * hi:.0f}]")
                row.append(f"{paper[c]:.1f}" if c in paper else "—")
            else:
                m = r.get(key) or {}
                row.append(_fmt(m.get("mean"), m.get("std")))
                p = paper.get(c) if c in ("mppi", "diffusion", "pac") else None
                row.append(_fmt(*p) if p else "—")
        lines.append("| " + " | ".join(row) + " |")
    for key, title in EXTRA_ROWS.items():
        row = [title]
        for c in cols:
            m = results[c].get(key) or {}
            row += [_fmt(m.get("mean"), m.get("std")), "—"]
        lines.append("| " + " | ".join(row) + " |")
    n = {c: results[c]["n_episodes"] for c in cols}
    lines += [
        "",
        f"Episodes per controller: {n}. Success in % with Wilson 95 % interval. Path and motion rows are "
        "mean ± std over successful episodes; the formation minimum clearance is over all episodes.",
        "",
        CLEARANCE_NOTE,
        "",
    ]
    return "\n".join(lines)


def adaptive_table(
    by_set: dict[str, dict], specs: dict[str, str] | None = None, policy_controllers: tuple[str, ...] = ()
) -> str:
    """Success of every diffusion controller per scene set; ``specs`` maps a set to its --scenes value
    (the paper's numbers are shown only for the paper's protocols)."""
    specs = specs or {}
    lines = [
        "### Standard vs adaptive diffusion policy",
        "",
        "| Scenes | Method | Success % (ours) [95 % CI] | Collisions | Timeouts | Success % (paper) |",
        "|---|---|---|---|---|---|",
    ]
    for set_name, results in by_set.items():
        for c in policy_controllers:
            if c not in results:
                continue
            r = results[c]
            lo, hi = r["success_ci95"]
            spec = specs.get(set_name, "")
            paper_protocol = is_paper_protocol(spec)
            key = "unseen" if set_name == "random" else set_name
            paper = PAPER_ADAPTIVE.get((key, c)) if paper_protocol else None
            title = SET_TITLES.get(set_name, set_name + " scenes") if paper_protocol else f"{spec} (unseen)"
            lines.append(
                f"| {title} | "
                f"{'Standard' if c == 'diffusion' else c} | {100 * r['success_rate']:.1f} "
                f"[{100 * lo:.0f}, {100 * hi:.0f}] | {r['collisions']} | {r['timeouts']} | "
                f"{paper if paper is not None else '—'} |"
            )
    return "\n".join(lines) + "\n"
