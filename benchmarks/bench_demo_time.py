"""Wall time of the main job (``scripts/run.sh demo``), quiet and beside a CPU-bound neighbour.

The demo (``lerobot_formation.bench.demo``: PAC, MPPI, the pretrained diffusion policy and its best-of-10
safety layer on 50 unseen scenes, the diffusion controllers on 20 hard scenes, tables and figures)
is run as a subprocess twice in one run:

- **quiet**: nothing else started by this script;
- **loaded**: with ``--load-procs`` CPU-bound neighbour processes started before it (each spins on one
  core: ``--load matmul``, a 256x256 numpy matmul loop with one BLAS thread, or ``--load busy``, a
  pure-Python loop) and killed after it.

By default the demo is run as ``<this python> -m lerobot_formation.bench.demo ARGS``, which is exactly what
``scripts/run.sh demo ARGS`` runs after its environment check (same variables: HF_HUB_OFFLINE=1,
HF_DATASETS_OFFLINE=1, TOKENIZERS_PARALLELISM=false, OMP_NUM_THREADS / MKL_NUM_THREADS /
LEROBOT_FORMATION_THREADS = ``--threads``). ``--via-run-sh`` runs ``scripts/run.sh demo ARGS`` itself
(the bash start-up and the check that .venv is installed are timed too); it is refused when .venv's
install stamp is stale, because run.sh would then reinstall the project inside the timed run.

ARGS: ``--out <work dir>/demo_<run> --no-progress`` (the demo's outputs go to the work dir, not to
outputs/demo), then whatever follows ``--`` on this command line (later flags win, e.g.
``-- --scenes random:100 --unseen hard:100`` for the full protocol). The demo's stdout and stderr go
to ``<work dir>/demo_<run>.log`` (the work dir is a new temp dir unless ``--work-dir``; it is kept and
its path printed). Each run's wall time is the subprocess's, start to exit (Python start-up and imports
included); the demo's CPU time (user + sys of its process tree) is printed beside it. The load average
before each run is printed too: on a machine that is already busy, "quiet" means "without our load".

Run (full size: the demo's time twice, the loaded run longer; ``--warmup`` adds one more)::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 python benchmarks/bench_demo_time.py --threads 1

``--quick`` is a smoke run (about half a minute on an idle 2-core machine): the demo made tiny by its own
flags, ``--controllers pac,diffusion --scenes random:1 --unseen hard:1 --no-figures`` (before the args
after ``--``), no warm-up. The goal (<= 120 s quiet) is judged only for the default demo (no demo args
changed). The last line is the headline: ``demo wall time: quiet X s, loaded Y s (ratio Z)``,
Z = loaded / quiet.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lerobot_formation.threads import ENV_VAR, add_threads_argument, apply_threads

REPO = Path(__file__).resolve().parents[1]
GOAL_S = 120.0
QUICK_ARGS = ["--controllers", "pac,diffusion", "--scenes", "random:1", "--unseen", "hard:1", "--no-figures"]

# One neighbour: one core, one thread; prints "ready" once its imports are done.
LOAD_CODE = {
    "matmul": (
        "import numpy as np\n"
        "a = np.random.default_rng(0).random((256, 256))\n"
        "print('ready', flush=True)\n"
        "while True:\n"
        "    b = a @ a\n"
    ),
    "busy": "print('ready', flush=True)\nx = 0\nwhile True:\n    x += 1\n",
}


def run_sh_stamp_current() -> bool:
    """True if scripts/run.sh's setup would skip the install (.venv/.installed matches, as it checks)."""
    stamp = REPO / ".venv" / ".installed"
    if not (REPO / ".venv" / "bin" / "python").exists() or not stamp.is_file():
        return False
    data = b"".join(
        p.read_bytes()
        for p in (REPO / "pyproject.toml", REPO / "plugin_shim" / "pyproject.toml")
        if p.is_file()
    )
    return stamp.read_text().strip() == hashlib.sha256(data).hexdigest()[:16]


def child_env(threads: int) -> dict[str, str]:
    """The environment scripts/run.sh sets up for the demo."""
    return {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "TOKENIZERS_PARALLELISM": "false",
        "OMP_NUM_THREADS": str(threads),
        "MKL_NUM_THREADS": str(threads),
        "OPENBLAS_NUM_THREADS": str(threads),
        ENV_VAR: str(threads),
    }


def start_load(kind: str) -> subprocess.Popen:
    """A CPU-bound neighbour on one core (one BLAS thread), returned once it is spinning."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-c", LOAD_CODE[kind]], env=env, stdout=subprocess.PIPE, text=True
    )
    line = proc.stdout.readline()
    if line.strip() != "ready":
        proc.kill()
        proc.wait()
        raise RuntimeError(f"the {kind} load process did not start (printed {line!r})")
    return proc


def stop_load(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    proc.stdout.close()


def run_demo(cmd: list[str], log: Path, env: dict[str, str]) -> tuple[float, float]:
    """Run the demo command with its output in ``log``; return (wall s, CPU s of its process tree)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(log, "w") as f:
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=REPO, env=env, stdout=f, stderr=subprocess.STDOUT)
        wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-30:])
        raise RuntimeError(f"the demo failed ({proc.returncode}): {' '.join(cmd)}\n{tail}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1 :]
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        usage="%(prog)s [options] [-- DEMO ARGS...]",
        epilog="Arguments after -- are passed on to the demo (lerobot-formation-bench flags; later ones win).",
    )
    ap.add_argument(
        "--via-run-sh",
        action="store_true",
        help="run scripts/run.sh demo (default: <this python> -m lerobot_formation.bench.demo, what run.sh runs "
        "after its setup check); refused if .venv's install stamp is stale",
    )
    ap.add_argument(
        "--load",
        choices=sorted(LOAD_CODE),
        default="matmul",
        help="the neighbour of the loaded run: a one-thread numpy matmul loop (matmul, default) or a "
        "pure-Python loop (busy)",
    )
    ap.add_argument(
        "--load-procs", type=int, default=1, help="neighbour processes of the loaded run, one core each"
    )
    ap.add_argument(
        "--work-dir",
        default=None,
        help="folder for the demo logs and outputs (default: a new temp dir, kept; its path is printed)",
    )
    ap.add_argument(
        "--warmup",
        action="store_true",
        help="one untimed demo run first (file cache, .pyc), so the quiet run is not the cold one",
    )
    add_threads_argument(ap, "torch threads of the demo (its --threads, OMP_NUM_THREADS)")
    ap.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke run: the demo with {' '.join(QUICK_ARGS)} (before the args after --)",
    )
    args = ap.parse_args(argv)
    if args.load_procs < 1:
        ap.error(f"--load-procs must be >= 1, got {args.load_procs}")
    if args.via_run_sh and not run_sh_stamp_current():
        ap.error(
            ".venv/.installed does not match pyproject.toml: scripts/run.sh would reinstall the project "
            "inside the timed run; run `scripts/run.sh setup` first, or drop --via-run-sh"
        )
    threads = apply_threads(args.threads)
    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix="bench_demo_time_"))
    work.mkdir(parents=True, exist_ok=True)
    base = (
        [str(REPO / "scripts" / "run.sh"), "demo"]
        if args.via_run_sh
        else [sys.executable, "-m", "lerobot_formation.bench.demo"]
    )
    size = QUICK_ARGS if args.quick else []
    env = child_env(threads)

    def command(run: str) -> list[str]:
        return base + ["--out", str(work / f"demo_{run}"), "--no-progress"] + size + extra

    shown = " ".join(command("<run>")).replace(str(work), "<work>").replace(str(REPO) + "/", "")
    print(
        f"demo command: {shown}\nwork dir {work}; threads {threads}, {os.cpu_count()} CPUs; loaded run beside "
        f"{args.load_procs} {args.load} process(es)",
        flush=True,
    )
    if args.warmup:
        wall, _ = run_demo(command("warmup"), work / "demo_warmup.log", env)
        print(f"warm-up (untimed): {wall:.1f} s", flush=True)

    load1 = os.getloadavg()[0]
    quiet, quiet_cpu = run_demo(command("quiet"), work / "demo_quiet.log", env)
    print(
        f"quiet:  {quiet:6.1f} s wall, {quiet_cpu:6.1f} s CPU (load average before {load1:.2f}) "
        f"log {work / 'demo_quiet.log'}",
        flush=True,
    )

    loads = []
    try:
        for _ in range(args.load_procs):
            loads.append(start_load(args.load))
        load2 = os.getloadavg()[0]
        loaded, loaded_cpu = run_demo(command("loaded"), work / "demo_loaded.log", env)
    finally:
        for p in loads:
            stop_load(p)
    print(
        f"loaded: {loaded:6.1f} s wall, {loaded_cpu:6.1f} s CPU (load average with the neighbours running "
        f"{load2:.2f}) log {work / 'demo_loaded.log'}",
        flush=True,
    )
    busy = load1 >= 0.5 * (os.cpu_count() or 1)
    if busy:
        print(
            f"note: the load average was {load1:.2f} on {os.cpu_count()} CPUs before the quiet run: the machine "
            "was busy with other jobs, so 'quiet' is only 'without our neighbour'"
        )
    if args.quick or size or extra:
        print(f"goal: quiet <= {GOAL_S:.0f} s for the default demo (not judged: demo args changed)")
    else:
        verdict = "met" if quiet <= GOAL_S else "NOT met"
        print(f"goal: quiet <= {GOAL_S:.0f} s for the default demo: {verdict} ({quiet:.1f} s)")
    print(f"demo wall time: quiet {quiet:.1f} s, loaded {loaded:.1f} s (ratio {loaded / quiet:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
