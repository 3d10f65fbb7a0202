"""The quick run of every study of the evidence suite (`python -m experiments NAME --quick`) ends without
error and writes its table: a broken study fails the suite. Slow tier (minutes each); the tables go to a
temporary directory (JAXFOAM_RESULTS_DIR), so the committed results are left as they are."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from experiments.__main__ import EXPERIMENTS  # noqa: E402


@pytest.mark.slow
@pytest.mark.parametrize("name", EXPERIMENTS)
def test_quick_run_of_each_experiment_succeeds(name, tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT), "JAXFOAM_RESULTS_DIR": str(tmp_path),
           "MPLBACKEND": "Agg"}
    res = subprocess.run([sys.executable, "-m", "experiments", name, "--quick"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=3600)
    assert res.returncode == 0, res.stderr[-4000:]
    assert "Traceback" not in res.stderr, res.stderr[-4000:]
    table = tmp_path / f"{name}_quick.md"
    assert table.exists() and table.stat().st_size > 200, sorted(p.name for p in tmp_path.iterdir())
