"""How well the reference data determine their own silhouettes: each committed 2D file against the
reference MPM rerun (a) at half its resolution (same seed: same sampling law and grid offset) and (b) at
its own resolution with another seed (another stratified-jitter sampling and grid offset).

(b) is the data's own discretization noise: two equally valid reference runs of the same truth. A fitter
scored on the file cannot be asked to reproduce it more closely than (b) does; (a) says whether the file
is converged in dx. Both compare masks per frame with jaxfoam's `silhouette_mismatch` (IoU, and the mean
boundary displacement: the area of the symmetric difference over the observed perimeter, m).

python -m experiments.reference convergence [--case SCENE] [--set K] [--report]
Writes experiments/reference/convergence.md and convergence.json (per-frame rows; resumes from it).
"""
from __future__ import annotations

import json
import pathlib
import time

import numpy as np

from jaxfoam.guards import atomic_output

from .generate import CASES, DATA_DIR, parameter_sets, simulate_case

HERE = pathlib.Path(__file__).resolve().parent
RECORD = HERE / "convergence.json"
PAGE = HERE / "convergence.md"
OTHER_SEED = 1000  # added to the set index: another sampling and grid offset at the file's resolution
VARIANTS = ("half", "reseed")  # half the file's resolution (same seed); the file's resolution, other seed


def mismatch(masks_a, masks_b, weights, pixel_size):
    """Per-frame (IoU, boundary m) of masks_a against masks_b (the file's) over pixels of weight > 0."""
    from fitting import silhouette_mismatch

    return silhouette_mismatch(np.asarray(masks_a, np.float64), masks_b, weights, pixel_size)


def run_variant(path: pathlib.Path, variant: str, progress=print) -> dict:
    """Rerun the file's case and set as `variant` and compare with the file: a JSON-ready row."""
    from fitting import read_silhouettes

    case_name, set_index = path.stem.rsplit("_set", 1)
    case, k = CASES[case_name], int(set_index)
    data = read_silhouettes(str(path))
    src = data.source if isinstance(data.source, dict) else json.loads(data.source)
    refine = float(src["refine"])
    seed = k if variant == "half" else k + OTHER_SEED
    run_refine = refine / 2.0 if variant == "half" else refine
    t0 = time.perf_counter()
    masks, times, weights, camera, _, source = simulate_case(case, parameter_sets(case)[k], seed=seed,
                                                             refine=run_refine, progress=lambda s: None)
    if not np.allclose(times, data.times):
        raise ValueError(f"{path.name}: rerun frame times {times} differ from the file's {data.times}")
    iou, boundary = mismatch(masks, data.masks, np.minimum(weights, data.weights), camera.pixel_size)
    row = dict(file=path.name, variant=variant, refine=run_refine, dx=source["dx"], file_dx=float(src["dx"]),
               seed=seed, particles=source["particles"], iou=[float(v) for v in iou],
               boundary=[float(v) for v in boundary], wall=round(time.perf_counter() - t0, 1))
    progress(f"{path.name} {variant}: dx {row['dx'] * 1e3:.3g} mm, IoU min {min(row['iou']):.3f}, "
             f"boundary mean {np.mean(row['boundary']) * 1e3:.2f} mm ({row['wall']:.0f} s)")
    return row


def load_record() -> list[dict]:
    return json.loads(RECORD.read_text())["rows"] if RECORD.exists() else []


def save_record(rows: list[dict]) -> None:
    with atomic_output(RECORD) as tmp:
        pathlib.Path(tmp).write_text(json.dumps(dict(rows=rows), indent=1))


def page(rows: list[dict]) -> str:
    """The markdown page of the record's rows."""
    lines = ["# The reference data against reruns of themselves", "",
             "_Regenerate with `python -m experiments.reference convergence` (rows resume from convergence.json; "
             "`--report` rebuilds this page only)._", "",
             "Each 2D file of `data/` against the reference MPM rerun of its truth: **half** at half the file's "
             "resolution (2x its dx, same seed), **reseed** at the file's own dx with another sampling and grid "
             "offset. Boundary: the mean displacement between the silhouettes (area of the symmetric difference "
             "over the file's perimeter), per frame. A reseeded run is as valid as the file, so its boundary "
             "distance is the data's own discretization noise: no model on any grid can be expected to come "
             "closer to the file than that.", "",
             "| file | variant | dx (mm) | particles | IoU min | IoU mean | boundary mean (mm) | boundary max (mm) | "
             "worst frame | wall (s) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["file"], VARIANTS.index(r["variant"]))):
        iou, b = np.asarray(r["iou"]), np.asarray(r["boundary"])
        lines.append(f"| {r['file']} | {r['variant']} | {r['dx'] * 1e3:.3g} | {r['particles']} | {iou.min():.3f} | "
                     f"{iou.mean():.3f} | {b.mean() * 1e3:.2f} | {b.max() * 1e3:.2f} | {int(np.argmax(b))} | "
                     f"{r['wall']:.0f} |")
    fams = {}
    for r in rows:
        fams.setdefault((r["file"].split("_set")[0], r["variant"]), []).append(float(np.mean(r["boundary"])) * 1e3)
    lines += ["", "## Summary", ""]
    for (fam, var), vals in sorted(fams.items()):
        lines.append(f"- {fam}, {var}: mean boundary distance {', '.join(f'{v:.2f}' for v in vals)} mm "
                     f"({len(vals)} files).")
    return "\n".join(lines) + "\n"


def main(cases=None, sets=None, report=False, progress=print) -> int:
    rows = load_record()
    if not report:
        files = sorted(p for p in DATA_DIR.glob("*_2d_set*.h5"))
        for path in files:
            case_name, k = path.stem.rsplit("_set", 1)
            if (cases and case_name not in cases) or (sets and int(k) not in sets):
                continue
            for variant in VARIANTS:
                if any(r["file"] == path.name and r["variant"] == variant for r in rows):
                    continue
                rows.append(run_variant(path, variant, progress))
                save_record(rows)
    with atomic_output(PAGE) as tmp:
        pathlib.Path(tmp).write_text(page(rows))
    progress(f"wrote {PAGE}")
    return 0
