"""python -m experiments.reference generate [--case SCENE] [--set K] [--refine R] | validate [--quick]"""
from __future__ import annotations

import argparse
import pathlib
import sys


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m experiments.reference", description=__doc__)
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="write the reference silhouette files (data/*.h5)")
    g.add_argument("--case", action="append", help="scene name (repeatable; default all)")
    g.add_argument("--set", type=int, action="append", help="parameter set index (repeatable; default all)")
    g.add_argument("--refine", type=float, default=None, help="fit default dx / reference dx (default per case)")
    g.add_argument("--out", default=None, help="output folder (default experiments/reference/data)")
    v = sub.add_parser("validate", help="analytic checks, written to validation.md")
    v.add_argument("--quick", action="store_true", help="coarser, shorter runs (not written to validation.md)")
    args = ap.parse_args(argv)
    if args.cmd == "generate":
        from . import generate as G

        out = pathlib.Path(args.out) if args.out else G.DATA_DIR
        for name in args.case or list(G.CASES):
            if name not in G.CASES:
                ap.error(f"unknown case {name!r}; known: {sorted(G.CASES)}")
            for k in args.set or range(G.CASES[name].n_sets):
                G.generate(name, k, out, refine=args.refine)
        (out / "README.md").write_text(G.README_HEAD + G.index_table(out))
        return 0
    from . import validate as V

    return V.main(quick=args.quick)


if __name__ == "__main__":
    sys.exit(main())
