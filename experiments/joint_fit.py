"""Joint against single fits: one foam recorded in the three 2D fit scenes (hanging plate, drop, squeeze).

The scenes, frame times and cameras are those of the reference data's set 0 (`experiments/reference/data`);
the silhouettes are made by `jaxfoam synth` at half the fit's dx for one material (MATERIAL), with 2%
boundary noise. Each recording is fitted alone, then the three jointly (`fitting.joint`), with the same
settings: dx 1 cm, 2 starts of up to 15 LM iterations, statistical intervals (no discretization check:
the study compares what the data inform, at a grid every fit shares). Reports per parameter the value,
the 95% interval and its width relative to the truth, and the ratio of the best single recording's width
to the joint one's; the joint fit's information shares; wall times.
Writes experiments/results/joint_fit.md and .json. Usage: python -m experiments joint_fit
"""
from __future__ import annotations

import json
import math
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from experiments._common import machine_line, md_table, out_path, write_md  # noqa: E402
from fitting import FitSettings, calibrate, read_silhouettes, synthesize  # noqa: E402
from fitting.joint import calibrate_joint  # noqa: E402
from jaxfoam.guards import atomic_output  # noqa: E402

KINDS = ("hanging_plate", "drop", "squeeze")
MATERIAL = {"mu": 150.0, "sigma_y": 30.0, "eta": 8.0, "m": 0.6}
FIT_DX, DATA_DX, NOISE = 0.01, 0.005, 0.02
SETTINGS = FitSettings(dx=FIT_DX, starts=2, max_iter=15, dx_check=False)
REF = os.path.join(os.path.dirname(__file__), "reference", "data")


def recordings():
    out = []
    for kind in KINDS:
        ref = read_silhouettes(os.path.join(REF, f"{kind}_2d_set0.h5"))
        times = np.asarray(ref.times)
        data = synthesize(ref.scene_json, MATERIAL, dx=DATA_DX, frames=len(times),
                          duration=float(times[-1]), pixel_size=ref.camera.pixel_size, noise=NOISE, seed=1)
        out.append((kind, data))
        print(f"made {kind}: {data.shape}", flush=True)
    return out


def width(interval, value):
    lo, hi = interval
    return (hi - lo) / value if math.isfinite(lo) and math.isfinite(hi) else math.inf


def main(argv=None):
    recs = recordings()
    rows, record = [], dict(material=MATERIAL, settings=SETTINGS.to_dict(), single={}, joint=None)
    for kind, data in recs:
        t = time.perf_counter()
        fit = calibrate(data, SETTINGS, progress=None)
        record["single"][kind] = dict(params=fit.params, interval=fit.interval, identifiable=fit.identifiable,
                                      wall=time.perf_counter() - t, loss=fit.loss)
        print(f"{kind}: {({n: round(fit.params[n], 3) for n in fit.fitted})} in {record['single'][kind]['wall']:.0f} s",
              flush=True)
    t = time.perf_counter()
    joint = calibrate_joint([d for _, d in recs], SETTINGS, progress=None)
    record["joint"] = dict(params=joint.params, interval=joint.interval, identifiable=joint.identifiable,
                           wall=time.perf_counter() - t, shares=joint.information_share,
                           scales=[r["scale"] for r in joint.recordings], loss=joint.loss)
    names = ("mu", "sigma_y", "eta", "m")
    for n in names:
        truth = MATERIAL[n]
        cells = [n, f"{truth:g}"]
        widths = []
        for kind in KINDS:
            s = record["single"][kind]
            w = width(s["interval"][n], truth)
            widths.append(w)
            cells.append(f"{s['params'][n]:.4g} [{s['interval'][n][0]:.3g}, {s['interval'][n][1]:.3g}]")
        jw = width(joint.interval[n], truth)
        cells.append(f"{joint.params[n]:.4g} [{joint.interval[n][0]:.3g}, {joint.interval[n][1]:.3g}]")
        best = min(widths)
        cells.append(f"{best / jw:.2f}" if math.isfinite(best) and jw > 0 else "-")
        cells.append(" / ".join(f"{100 * v:.0f}%" for v in joint.information_share[n]))
        rows.append(cells)
    walls = [record["single"][k]["wall"] for k in KINDS]
    body = (f"Material {MATERIAL}; data by `jaxfoam synth` at dx {DATA_DX} m on the reference scenes of set 0 "
            f"({NOISE:.0%} boundary noise); every fit at dx {FIT_DX} m, 2 starts, up to 15 LM iterations, "
            f"statistical 95% intervals.\n\n"
            + md_table(["parameter", "truth"] + [f"{k} alone" for k in KINDS]
                       + ["joint", "best single width / joint width", "joint information share (h / d / s)"], rows)
            + f"\n\nWall times: alone {', '.join(f'{w:.0f} s' for w in walls)}; joint {record['joint']['wall']:.0f} s. "
            f"Noise scales of the joint fit: {', '.join(f'{s:.3g}' for s in record['joint']['scales'])}.\n")
    write_md("joint_fit", False, "Joint against single fits of one foam in three scenes", body)
    with atomic_output(out_path("joint_fit", "json", False)) as tmp:
        with open(tmp, "w") as fh:
            json.dump(record, fh, indent=1, default=float)
    print(machine_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
