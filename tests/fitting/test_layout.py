"""The package contract: `jaxfoam` (the simulator) never imports `fitting` (the calibration package);
`fitting` uses only jaxfoam's public API; `fitting.optim` knows no simulator; the old import paths
still work for one release, with a DeprecationWarning."""
import ast
import importlib
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

import fitting
import jaxfoam

ROOT = Path(__file__).resolve().parents[2]
# Modules of jaxfoam that may name fitting: the deprecation aliases, and the CLI's lazy dispatch.
ALIASES = ("calibrate", "io", "silhouette", "synth", "track")


def _imports(path: Path):
    """(module, names) for every import statement of a file; relative imports resolved to absolute."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, ()
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            yield base, tuple(a.name for a in node.names)


def test_jaxfoam_modules_do_not_import_fitting():
    offenders = []
    for path in sorted((ROOT / "jaxfoam").rglob("*.py")):
        if path.parent.name == "jaxfoam" and path.stem in ALIASES + ("cli",):
            continue
        offenders += [f"{path.name}: {m}" for m, _ in _imports(path) if m.split(".")[0] == "fitting"]
    assert offenders == []


@pytest.mark.slow
def test_simulating_never_loads_the_calibration_package():
    code = ("import sys, jax.numpy as jnp, jaxfoam, jaxfoam.cli\n"
            "s = jaxfoam.load_scene('experiments/scenes/drop_2d.json')\n"
            "p = jaxfoam.Params(mu=100.0, sigma_y=20.0, eta=2.0, m=0.5, kappa=s.kappa, rho=s.density)\n"
            "model = jaxfoam.make_model(s, 0.01, params_ref=p, dtype=jnp.float32)\n"
            "jaxfoam.step(model, model.sample(), p)\n"
            "jaxfoam.cli.build_parser(['simulate', 'x.json'])\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'fitting'))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_fitting_uses_only_the_public_api_of_jaxfoam():
    offenders = []
    for path in sorted((ROOT / "fitting").rglob("*.py")):
        for module, names in _imports(path):
            parts = module.split(".")
            if parts[0] != "jaxfoam":
                continue
            if any(p.startswith("_") for p in parts[1:]) or any(n.startswith("_") for n in names):
                offenders.append(f"{path.relative_to(ROOT)}: from {module} import {', '.join(names)}")
            if len(parts) == 1:
                offenders += [f"{path.name}: {n}" for n in names if n not in jaxfoam.__all__]
    assert offenders == []


def test_optimizers_know_no_simulator():
    found = [f"{p.name}: {m}" for p in sorted((ROOT / "fitting" / "optim").glob("*.py"))
             for m, _ in _imports(p) if m.split(".")[0] == "jaxfoam" or m.startswith("fitting.") and
             not m.startswith("fitting.optim")]
    assert found == []


@pytest.mark.parametrize("old,new,name", [
    ("jaxfoam.calibrate", "fitting", "calibrate"), ("jaxfoam.calibrate", "fitting.problem", "build_problem"),
    ("jaxfoam.calibrate", "fitting.cli", "add_fit_parser"), ("jaxfoam.io", "fitting.io", "read_silhouettes"),
    ("jaxfoam.silhouette", "fitting.silhouette", "render"), ("jaxfoam.synth", "fitting.synth", "synthesize"),
    ("jaxfoam.track", "fitting.track", "track_video"), ("jaxfoam.track", "fitting.video", "read_frames")])
def test_old_import_paths_warn_and_give_the_same_objects(old, new, name):
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=f"{old} is deprecated: import {new.split('.')[0]}"):
        module = importlib.import_module(old)
    assert getattr(module, name) is getattr(importlib.import_module(new), name)
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        module.not_a_name


def test_optimizers_at_the_old_top_level_warn_and_give_the_same_objects():
    with pytest.warns(DeprecationWarning, match="fitting.LevenbergMarquardt is deprecated: use fitting.optim"):
        assert fitting.LevenbergMarquardt is fitting.optim.LevenbergMarquardt
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fitting.calibrate is fitting.driver.calibrate  # the package's own names do not warn
    with pytest.raises(AttributeError):
        fitting.not_a_name
