"""The GPU benchmark's contract: each case is recorded as it finishes (a run cut short keeps its cases),
and the table and goal verdict are rebuilt from those records alone."""
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # experiments/ is a folder of the repository
from experiments import bench_gpu  # noqa: E402


def test_step_case_counts_particle_steps_and_checks_finiteness():
    import jax.numpy as jnp
    r = bench_gpu.step_case(2, 256, 16, jnp.float32, 5, 1, "sorted")
    assert r["finite"] and r["n"] == 256 and r["steps"] == 5
    assert np.isclose(r["rate"], 256 * 5 / r["median_s"], rtol=1e-12)


def test_records_append_and_report_rebuilds_the_goal(tmp_path):
    stem = str(tmp_path / "b")
    bench_gpu._append(stem + ".json", dict(kind="machine", backend="gpu", device="X", jax="0", date="d"))
    row = dict(kind="step", dim=2, n=1_000_000, cells=1414, dtype="float32", variant="backend", steps=100,
               compile_s=1.0, median_s=0.5, rate=2e8, best_rate=2.1e8, finite=True)
    bench_gpu._append(stem + ".json", row)
    bench_gpu._append(stem + ".json", dict(row, rate=5e7, variant="sorted"))
    assert [r["kind"] for r in json.loads(Path(stem + ".json").read_text())] == ["machine", "step", "step"]
    bench_gpu.report(stem)
    text = Path(stem + ".md").read_text()
    assert "| 2D | 1,000,000 | 1414^2 | float32 | backend | 100 | 200.0 |" in text
    # the verdict reads the backend-tuned row, not the sorted one
    assert "200.0 M, met" in text
