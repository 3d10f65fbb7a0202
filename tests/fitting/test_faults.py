"""Faults: a killed fit resumes to the uninterrupted result, damaged logs are refused, concurrent and
killed writers never leave a mixed or truncated file, and the same command twice is bit-identical.

Each test runs `jaxfoam` in fresh processes (the kill is a real SIGKILL), so the module is in the
slow tier.
"""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import jaxfoam
from fitting.optim import read_fitlog

ROOT = Path(__file__).resolve().parents[2]
DROP = ROOT / "experiments" / "scenes" / "drop_2d.json"
HANGING = ROOT / "experiments" / "scenes" / "hanging_plate_2d.json"
ENV = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
TINY_SIM = ["--dx", "0.02", "--frames", "4", "--duration", "0.04", "--quiet"]
FIT_ARGS = ["--dx", "0.02", "--fix", "mu=200,eta=10,m=0.5", "--starts", "1", "--max-iter", "6", "--no-dx-check",
            "--no-plots"]

pytestmark = pytest.mark.slow


def jaxfoam_cmd(*args):
    return [sys.executable, "-m", "jaxfoam", *map(str, args)]


def run(*args, cwd, timeout=600):
    res = subprocess.run(jaxfoam_cmd(*args), capture_output=True, text=True, timeout=timeout, env=ENV, cwd=cwd)
    return res


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Synthetic drop silhouettes (the yield stress to fit) and the uninterrupted reference fit."""
    d = tmp_path_factory.mktemp("faults")
    path = d / "drop.h5"
    res = run("synth", DROP, "--params", "mu=200,sigma_y=30,eta=10,m=0.5", "--dx", "0.01", "--frames", "5",
              "--duration", "0.2", "--out", path, cwd=d)
    assert res.returncode == 0, res.stderr
    ref = d / "ref.json"
    res = run("fit", path, "--out", ref, *FIT_ARGS, cwd=d)
    assert res.returncode == 0, res.stderr
    return d, path, json.loads(ref.read_text()), read_fitlog(d / "ref.fitlog.h5")["runs"][0]


@pytest.mark.slow
def test_sigkill_after_the_third_iteration_then_resume_gives_the_uninterrupted_fit(data, tmp_path):
    d, path, ref, ref_log = data
    assert ref["iterations"] >= 4, "the reference fit must run past the kill"
    out, log = tmp_path / "fit.json", tmp_path / "fit.fitlog.h5"
    proc = subprocess.Popen(jaxfoam_cmd("fit", path, "--out", out, *FIT_ARGS), stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env=ENV, cwd=tmp_path)
    try:
        for line in proc.stdout:  # the log commits an iteration before its line is printed
            if "iter   3" in line:
                proc.send_signal(signal.SIGKILL)
                break
    finally:
        proc.wait(timeout=600)
    assert proc.returncode == -signal.SIGKILL
    killed = read_fitlog(log)["runs"][0]
    kept = len(killed["loss"])
    assert kept >= 4  # iterations 0..3 all committed
    res = run("fit", path, "--out", out, "--resume", *FIT_ARGS, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    fit = json.loads(out.read_text())
    np.testing.assert_allclose(fit["loss_history"], ref["loss_history"], rtol=1e-10, atol=0)
    np.testing.assert_allclose(fit["params"]["sigma_y"], ref["params"]["sigma_y"], rtol=1e-10, atol=0)
    assert fit["iterations"] == ref["iterations"]
    resumed = read_fitlog(log)["runs"][0]
    # No iteration lost or repeated: the resumed log holds every row of the reference, the killed rows unchanged.
    assert len(resumed["loss"]) == len(ref_log["loss"])
    np.testing.assert_array_equal(resumed["x"][:kept], killed["x"])
    np.testing.assert_allclose(resumed["x"], ref_log["x"], rtol=1e-10, atol=0)


@pytest.mark.slow
def test_truncated_or_altered_fit_log_is_refused_on_resume(data, tmp_path):
    d, path, ref, _ = data
    log = tmp_path / "cut.fitlog.h5"
    blob = (d / "ref.fitlog.h5").read_bytes()
    log.write_bytes(blob[:int(0.6 * len(blob))])
    res = run("fit", path, "--out", tmp_path / "fit.json", "--log", log, "--resume", *FIT_ARGS, cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "jaxfoam fit: error:" in res.stderr and str(log) in res.stderr and "fit log" in res.stderr
    # A log whose parameters were changed in place fails its checksum instead of resuming to another answer.
    altered = tmp_path / "altered.fitlog.h5"
    altered.write_bytes(blob)
    with h5py.File(altered, "a") as f:
        x = f["runs/0000/x"][1]
        x[0] += 0.1
        f["runs/0000/x"][1] = x
        f["runs/0000"].attrs["rows"] = 3  # an unfinished run: the resume must read its rows
        for key in ("reason", "final_status", "final_evaluations", "final_nonfinite", "wall_time"):
            if key in f["runs/0000"].attrs:
                del f["runs/0000"].attrs[key]
    res = run("fit", path, "--out", tmp_path / "fit2.json", "--log", altered, "--resume", *FIT_ARGS, cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "row 1 does not match its checksum" in res.stderr
    assert not (tmp_path / "fit2.json").exists()


def _frames(path):
    with h5py.File(path, "r") as f:
        return {k: f["frames"][k][()] for k in f["frames"]}, f["times"][()], dict(f["params"].attrs)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_same_command_twice_is_bit_identical(tmp_path, dtype):
    outs = [tmp_path / f"run{k}.h5" for k in range(2)]
    for out in outs:
        res = run("simulate", HANGING, "--out", out, "--dtype", dtype, *TINY_SIM, cwd=tmp_path)
        assert res.returncode == 0, res.stderr
    (a, ta, pa), (b, tb, pb) = _frames(outs[0]), _frames(outs[1])
    assert sorted(a) == sorted(b) and pa == pb
    np.testing.assert_array_equal(ta, tb)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes(), k


@pytest.mark.slow
def test_two_concurrent_writers_leave_one_valid_file(tmp_path):
    """Two runs with different parameters write the same path at once: both succeed, and the file is one
    whole run (its frames are those of the run whose parameters it records), complete, with no leftovers."""
    out = tmp_path / "shared.h5"
    procs = [subprocess.Popen(jaxfoam_cmd("simulate", HANGING, "--out", out, "--mu", mu, *TINY_SIM),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=tmp_path)
             for mu in (200, 300)]
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
    traj = jaxfoam.load_trajectory(out)
    assert traj.complete and traj.num_frames == 5
    mu = traj.params.mu
    assert mu in (200.0, 300.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shared.h5"]  # no temporary file left
    ref = tmp_path / "ref.h5"
    res = run("simulate", HANGING, "--out", ref, "--mu", int(mu), *TINY_SIM, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    got, want = _frames(out)[0], _frames(ref)[0]
    for k in want:
        assert got[k].tobytes() == want[k].tobytes(), k


@pytest.mark.slow
def test_killed_simulate_leaves_the_previous_output_and_an_incomplete_partial(tmp_path):
    out = tmp_path / "run.h5"
    res = run("simulate", HANGING, "--out", out, *TINY_SIM, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    before = out.read_bytes()
    proc = subprocess.Popen(jaxfoam_cmd("simulate", HANGING, "--out", out, "--frames", "400", "--duration", "4"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV, cwd=tmp_path)
    try:
        for line in proc.stderr:  # a progress line past frame 0: blocks of frames are in the file
            if "/400" in line and "frame 0/400" not in line:
                break
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=600)
    assert out.read_bytes() == before  # the good file is untouched
    partial = [p for p in tmp_path.iterdir() if p.name.startswith(".run.partial-")]
    assert len(partial) == 1
    with h5py.File(partial[0], "r") as f:
        assert not f.attrs["complete"] and f["times"].shape[0] >= 1


@pytest.mark.slow
def test_sigterm_while_the_first_evaluation_compiles_exits_143_and_resumes(data, tmp_path):
    d, path, ref, _ = data
    out = tmp_path / "fit.json"
    proc = subprocess.Popen(jaxfoam_cmd("fit", path, "--out", out, *FIT_ARGS), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=ENV, cwd=tmp_path)
    try:
        for line in proc.stdout:  # the problem is bound; the first evaluation (and its compilation) follows
            if line.startswith("fit: "):
                break
        time.sleep(2.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, (proc.returncode, err[-2000:])
    assert "terminated" in err and "--resume" in err
    res = run("fit", path, "--out", out, "--resume", *FIT_ARGS, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    fit = json.loads(out.read_text())
    np.testing.assert_allclose(fit["loss_history"], ref["loss_history"], rtol=1e-10, atol=0)


@pytest.mark.slow
def test_fit_without_matplotlib_skips_its_pictures_and_succeeds(data, tmp_path, capsys, monkeypatch):
    """The optional dependency is checked before any work: a notice, then the fit runs to its result."""
    import fitting.cli  # the fit command checks its optional dependencies there
    from jaxfoam.cli import main

    d, path, ref, _ = data
    monkeypatch.setattr(fitting.cli, "missing_modules", lambda *mods: [m for m in mods if m == "matplotlib"])
    out = tmp_path / "fit.json"
    args = [a for a in FIT_ARGS if a != "--no-plots"] + ["--max-iter", "1"]
    assert main(["fit", str(path), "--out", str(out)] + args) == 0
    printed = capsys.readouterr().out
    assert printed.index("matplotlib is not installed, so the pictures are skipped") < printed.index("\nfit: ")
    assert json.loads(out.read_text())["iterations"] == 1
    assert not list(tmp_path.glob("*.png"))
