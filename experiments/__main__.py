"""Run the experiments: `python -m experiments all [--quick]` or `python -m experiments NAME [--quick]`.

Each experiment is a module experiments/<name>.py with `main(argv)` that writes its chart and table to
experiments/results/<name>[_quick].png/.md. `all` runs the evidence suite (EXPERIMENTS) each in its own
process (a failure in one does not stop the others) and prints the wall time of each; NAME may also be
any other experiments module with a `main(argv)` (the demos and benchmarks beside them).
"""
from __future__ import annotations

import importlib
import importlib.util
import subprocess
import sys
import time

# Order: validation first, then stability, then accuracy-vs-speed (the slowest).
EXPERIMENTS = ("rheometer", "poiseuille", "elastic_wave", "slump", "stability", "kappa_study", "grad_horizon",
               "fit_convergence", "fit_features", "plane_strain", "pareto")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__ + "\nexperiments: " + ", ".join(EXPERIMENTS))
        return 0
    name, rest = argv[0], argv[1:]
    if name == "all":
        failed = []
        t_all = time.perf_counter()
        for exp in EXPERIMENTS:
            t0 = time.perf_counter()
            rc = subprocess.call([sys.executable, "-m", "experiments", exp] + rest)
            print(f"== {exp}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} in {time.perf_counter() - t0:.0f} s",
                  flush=True)
            if rc:
                failed.append(exp)
        print(f"== all: {time.perf_counter() - t_all:.0f} s; failed: {failed or 'none'}")
        return 1 if failed else 0
    if not name.isidentifier() or name.startswith("_") or importlib.util.find_spec(f"experiments.{name}") is None:
        print(f"unknown experiment {name!r}; expected 'all' or one of {', '.join(EXPERIMENTS)} "
              f"(or another experiments module with a main)", file=sys.stderr)
        return 2
    module = importlib.import_module(f"experiments.{name}")
    if not hasattr(module, "main"):
        print(f"experiments.{name} has no main(argv)", file=sys.stderr)
        return 2
    module.main(rest)
    return 0


if __name__ == "__main__":
    sys.exit(main())
