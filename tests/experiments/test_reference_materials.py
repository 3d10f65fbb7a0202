"""The reference simulator's shared foams: every scene of a material carries the same truth, and a scene
file of one's own (a designed recording) runs with its duration and frame count."""
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # experiments/ is a folder of the repository
from experiments.reference.generate import RANGES, Case, generate, materials  # noqa: E402


def test_materials_lie_in_the_issue_ranges_and_differ():
    mats = materials()
    assert len(mats) == 3
    for name, (lo, hi) in RANGES.items():
        vals = [m[name] for m in mats]
        assert all(lo <= v <= hi for v in vals)
        assert len(set(vals)) == 3  # a Latin hypercube: one value per stratum


def test_scene_file_of_ones_own_runs_with_the_material_truth(tmp_path):
    spec = {"kind": "drop", "dim": 2, "gravity": [0.0, -9.81], "density": 80.0, "kappa": 3000.0,
            "domain": {"min": [-0.05, 0.0], "max": [0.05, 0.08]}, "floor": {"y": 0.0, "friction": 0.5},
            "initial_shape": {"type": "box", "min": [-0.02, 0.0], "max": [0.02, 0.03]}}
    scene = tmp_path / "mine.json"
    scene.write_text(json.dumps(spec))
    case = Case("mine", 0.02, 3, 4.0, 1, 0, path=str(scene))
    path, source = generate("mine", 0, tmp_path, refine=0.25, material=1, case=case, progress=lambda s: None)
    from fitting import read_silhouettes

    data = read_silhouettes(path)
    assert path.name == "mine_mat1.h5"
    assert {k: data.truth[k] for k in ("mu", "sigma_y", "eta", "m")} == materials()[1]
    np.testing.assert_allclose(data.times, [0.0, 0.01, 0.02])
    assert json.loads(data.scene_json)["domain"] == spec["domain"]
    assert abs(source["dx"] - 0.1 / 64 / 0.25) < 1e-12
