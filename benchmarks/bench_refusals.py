"""Bad input is refused before the work it would cost: a goal too far away, a scenes file with too
many scenes. Each refusal is timed beside the work it spares, in the same run.

- Far goal (300 m and 1e5 m; at most 50 m is supported): ``scenes_from_list``, ``cost_to_go`` (the
  wavefront grid, whose size grows with the distance: refused above 600 cells), ``SceneConfig`` and
  the bench's command line (a scenes file) each refuse it. The baseline is the same four calls on an
  ordinary goal ([5, 5]): the scene checked, its cost-to-go computed, the config built, and the bench
  refusing the file for another reason (an unknown controller), so both sides pay the same start-up.
- Too many scenes: a file of N + 1 scenes with the limit set to N (``MAX_SCENES_PER_FILE``) is
  refused before any scene is checked; the baseline loads the same file with the limit N + 1, which
  checks every scene (~5 ms a scene).

These were wall-clock assertions of tests/test_reliability.py (under 5 s and under 1 s); the tests
keep the refusals and their messages. Run: ``python benchmarks/bench_refusals.py`` (``--scenes 10
--repeats 1`` is a smoke run). The last line is the figure: refusal / the work it spares for each case
(target: far below 1).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
import time
from pathlib import Path

import numpy as np

ORDINARY_GOAL = [5.0, 5.0]


def best_of(fn, repeats: int) -> float:
    """Best wall time in seconds of ``repeats`` calls of ``fn`` (after one untimed call)."""
    fn()
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _refused(fn, *exceptions) -> None:
    """Call ``fn``; it must raise one of ``exceptions`` (a refusal), whose output is dropped."""
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        try:
            fn()
        except exceptions:
            return
    raise AssertionError(f"{fn} was not refused")


def goal_calls(goal: list[float], scenes_file: Path, out: Path, controller: str) -> dict:
    """The four calls of the far-goal check on ``goal``: each refuses a far goal and handles an
    ordinary one (the bench: ``controller`` unknown refuses the ordinary file before any episode)."""
    from lerobot_formation.bench.cli import main as bench
    from lerobot_formation.core.world.navigation import cost_to_go
    from lerobot_formation.core.world.presets import SceneConfig
    from lerobot_formation.core.world.scene_files import scenes_from_list

    far = float(np.hypot(*goal)) > 50
    scene = [{"obstacles": [], "goal": goal}]
    argv = ["--controllers", controller, "--scenes", str(scenes_file), "--out", str(out), "--no-progress"]

    def maybe_refused(fn, *exceptions):
        return (lambda: _refused(fn, *exceptions)) if far else fn

    return {
        "scenes_from_list": maybe_refused(lambda: scenes_from_list(scene), ValueError),
        "cost_to_go": maybe_refused(lambda: cost_to_go(np.zeros((1, 1, 3)), np.array([goal])), ValueError),
        "SceneConfig": maybe_refused(lambda: SceneConfig(goal=tuple(goal)), ValueError),
        "bench command line": lambda: _refused(lambda: bench(argv), SystemExit),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("--scenes", type=int, default=1000, help="N, the scenes file's limit (default 1000)")
    ap.add_argument(
        "--repeats", type=int, default=5, help="timed calls of each measurement (best; default 5)"
    )
    args = ap.parse_args(argv)
    if args.scenes < 1 or args.repeats < 1:
        ap.error(f"--scenes and --repeats must be >= 1, got {args.scenes}, {args.repeats}")

    from lerobot_formation.core.world import scene_files

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print("| far goal check | refusal, 300 m [ms] | refusal, 1e5 m [ms] | ordinary goal [5, 5] [ms] |")
        print("|---|---|---|---|")
        times = {}
        for goal, controller in (([300.0, 0.0], "pac"), ([1e5, 0.0], "pac"), (ORDINARY_GOAL, "no-such")):
            f = tmp / f"goal_{goal[0]:g}.json"
            f.write_text(json.dumps({"scenes": [{"obstacles": [], "goal": goal}]}))
            calls = goal_calls(goal, f, tmp / "out", controller)
            times[goal[0]] = {name: best_of(fn, args.repeats) for name, fn in calls.items()}
        for name in times[ORDINARY_GOAL[0]]:
            row = [times[x][name] * 1e3 for x in (300.0, 1e5, ORDINARY_GOAL[0])]
            print(f"| {name} | {row[0]:.2f} | {row[1]:.2f} | {row[2]:.2f} |")
        far = max(sum(times[x].values()) for x in (300.0, 1e5))
        ordinary = sum(times[ORDINARY_GOAL[0]].values())

        n = args.scenes
        f = tmp / "many.json"
        f.write_text(
            json.dumps({"scenes": [{"obstacles": [[3.0, 3.0, 0.5]], "goal": ORDINARY_GOAL}] * (n + 1)})
        )
        saved = scene_files.MAX_SCENES_PER_FILE
        try:
            scene_files.MAX_SCENES_PER_FILE = n
            refusal = best_of(lambda: _refused(lambda: scene_files.load_scenes(f), ValueError), args.repeats)
            scene_files.MAX_SCENES_PER_FILE = n + 1
            load = best_of(lambda: scene_files.load_scenes(f), args.repeats)
        finally:
            scene_files.MAX_SCENES_PER_FILE = saved
        print(f"\n| scenes file of {n + 1} scenes | ms |\n|---|---|")
        print(
            f"| refused (limit {n}) | {refusal * 1e3:.2f} |\n| loaded, every scene checked (limit {n + 1}) | {load * 1e3:.2f} |"
        )
    print(
        f"refusal / the work it spares: far goal {far / ordinary:.2f}x ({far * 1e3:.1f} ms vs {ordinary * 1e3:.1f} ms), "
        f"too many scenes {refusal / load:.3f}x ({refusal * 1e3:.1f} ms vs {load * 1e3:.1f} ms)"
    )


if __name__ == "__main__":
    main()
