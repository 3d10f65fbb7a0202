"""The fit-fidelity goal table counts what the issue's goals count: truth inside the interval, intervals
that are only the bounds, identifiable-but-wrong, parameters within 10% in 2D, and the loss ratio."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # experiments/ is a folder of the repository
from experiments.reference_fits import report  # noqa: E402


def _record(name, fit, interval, identifiable, loss, loss_truth):
    truth = {"mu": 100.0, "sigma_y": 20.0, "eta": 5.0, "m": 0.5}
    return dict(file=name, truth=truth, params=dict(zip(truth, fit)), interval=dict(zip(truth, interval)),
                identifiable=dict(zip(truth, identifiable)), loss=loss, loss_truth=loss_truth, dx=0.005, wall=60.0)


def test_goal_counts():
    bounds = [[5.0, 2000.0], [0.5, 500.0], [0.05, 500.0], [0.2, 1.5]]
    good = _record("drop_2d_set0.h5", [105.0, 21.0, 4.0, 0.6], [[90, 120], [18, 24], [2, 8], [0.4, 0.7]],
                   [True] * 4, loss=1.0, loss_truth=1.1)
    wrong = _record("squeeze_2d_set0.h5", [150.0, 30.0, 4.0, 0.6], [[140, 160], bounds[1], bounds[2], bounds[3]],
                    [True, False, False, False], loss=1.0, loss_truth=3.0)
    text = report([good, wrong])
    assert "Truth inside the reported interval: 7 of 8 parameter-cases" in text
    assert "3 of them with the interval equal to the default bounds" in text
    assert "reported identifiable with the truth outside: 1 (goal: 0)" in text
    assert "mu within 10% in 1 of 2" in text and "sigma_y in 1 of 2" in text
    assert "at most 1.2 in 1 of 2 (goal: 8 of 9)" in text


GPU_FIT = Path(__file__).resolve().parents[2] / "experiments" / "results" / "bench_gpu" / "fit_plate_2d.json"


def test_from_fit_refuses_a_fit_with_other_settings(tmp_path):
    """Contract of --from-fit: only a default `jaxfoam fit` of the file is recorded; any other setting is
    refused naming the field and both values, before the loss at the truth is computed."""
    import json

    import pytest

    from experiments.reference_fits import DATA, record_from_fit
    fit = json.loads(GPU_FIT.read_text())
    for field, value in (("starts", 2), ("dx", 0.004), ("time_window", [0.0, 0.5]), ("floor_phase", 0.5)):
        changed = json.loads(json.dumps(fit))
        changed["settings"][field] = value
        path = tmp_path / f"{field}.json"
        path.write_text(json.dumps(changed))
        with pytest.raises(ValueError, match=rf"settings\.{field} = .* is not the default fit's"):
            record_from_fit(DATA / "hanging_plate_2d_set0.h5", path)
    with pytest.raises(ValueError, match=r"settings\.data\.scene_kind|settings\.dx"):
        record_from_fit(DATA / "drop_2d_set0.h5", GPU_FIT)  # another file's problem


@__import__("pytest").mark.slow
def test_from_fit_records_the_fit_and_the_loss_at_truth():
    """--from-fit copies the fit's numbers and computes the loss at the truth on the fit's grid; the GPU
    fit's record reproduces: same parameters, and a loss at truth equal to the committed record's."""
    import json

    from experiments.reference_fits import DATA, RECORDS, record_from_fit
    rec = record_from_fit(DATA / "hanging_plate_2d_set0.h5", GPU_FIT)
    fit = json.loads(GPU_FIT.read_text())
    committed = json.loads((RECORDS / "hanging_plate_2d_set0.json").read_text())
    assert rec["params"] == {n: fit["params"][n] for n in fit["fitted"]}
    assert abs(rec["loss_truth"] / committed["loss_truth"] - 1) < 1e-9
    assert rec["loss_truth"] > 10 * rec["loss"]  # the truth misfits the default grid (ratio 114.7 recorded)
