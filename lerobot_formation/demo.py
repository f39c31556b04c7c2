"""The README's main job: runs the controllers on a built-in scene set and writes tables and figures."""

from __future__ import annotations

import sys

from lerobot_formation.bench import main as bench_main


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    defaults = ["--controllers", "pac", "--scenes", "random:20", "--out", "outputs/demo"]
    return bench_main(defaults + argv)


if __name__ == "__main__":
    raise SystemExit(main())
