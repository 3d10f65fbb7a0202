"""python -m experiments.reference generate [--case SCENE] [--set K] [--refine R] | validate [--quick]
  | convergence [--case SCENE] [--set K] [--report]"""
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
    g.add_argument("--out", default=None, help="output folder (default experiments/reference/data; "
                   "with --material data/materials)")
    g.add_argument("--material", type=int, action="append",
                   help="the shared foam K of generate.materials() instead of the case's own sets (repeatable)")
    g.add_argument("--scene", default=None, help="a scene JSON file to simulate (with --material, --duration, --frames)")
    g.add_argument("--duration", type=float, default=None, help="with --scene: recording length, s")
    g.add_argument("--frames", type=int, default=None, help="with --scene: frames on [0, duration]")
    g.add_argument("--name", default=None, help="with --scene: the file's stem (default <scene file stem>_mat<K>)")
    v = sub.add_parser("validate", help="analytic checks, written to validation.md")
    v.add_argument("--quick", action="store_true", help="coarser, shorter runs (not written to validation.md)")
    c = sub.add_parser("convergence", help="the data files against reruns at half resolution and another seed")
    c.add_argument("--case", action="append", help="scene name (repeatable; default all 2D)")
    c.add_argument("--set", type=int, action="append", help="parameter set index (repeatable; default all)")
    c.add_argument("--report", action="store_true", help="rebuild convergence.md from convergence.json, no runs")
    args = ap.parse_args(argv)
    if args.cmd == "convergence":
        from . import convergence as K

        return K.main(cases=args.case, sets=args.set, report=args.report)
    if args.cmd == "generate":
        from . import generate as G

        if args.material is not None:
            out = pathlib.Path(args.out) if args.out else G.MATERIALS_DIR
            for k in args.material:
                if not 0 <= k < G.N_MATERIALS:
                    ap.error(f"--material: {k} is not in [0, {G.N_MATERIALS - 1}]")
            if args.scene:
                if args.duration is None or args.frames is None or args.duration <= 0 or args.frames < 2:
                    ap.error("--scene needs --duration > 0 and --frames >= 2")
                stem = pathlib.Path(args.scene).stem
                dim = int(__import__("json").loads(pathlib.Path(args.scene).read_text())["dim"])
                case = G.Case(stem, args.duration, args.frames, 4.0 if dim == 2 else 2.5, 1, 0, path=args.scene)
                for k in args.material:
                    G.generate(stem, 0, out, refine=args.refine, material=k, case=case,
                               name=args.name if args.name and len(args.material) == 1 else None)
            else:
                for name in args.case or list(G.MATERIAL_SCENES):
                    if name not in G.CASES:
                        ap.error(f"unknown case {name!r}; known: {sorted(G.CASES)}")
                    for k in args.material:
                        G.generate(name, 0, out, refine=args.refine, material=k)
            (out / "README.md").write_text(G.MATERIALS_README_HEAD + G.index_table(out))
            return 0
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
