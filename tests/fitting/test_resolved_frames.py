"""Fits on the frames the grid resolves (`FitSettings.resolved_frames`, `fitting.horizon`).

Contracts: the window ends before the first frame whose silhouette moves more than FRAME_BOUNDARY_SPACINGS
particle spacings between the fit grid and DX_CHECK_RATIO dx (never shorter than RESOLVED_MIN_FRAMES); the
rounds refit until the window stays put; the result is the last window's optimum with its uncertainty;
a fit killed in a later round resumes to the uninterrupted result without rerunning finished rounds.
The scene is the calibrate tests' slump (sigma_y alone fitted, dx = 1 cm, 5 observed frames).
"""
import dataclasses

import numpy as np
import pytest

import fitting.horizon as horizon
from fitting import CalibrationError, FitSettings, build_problem, calibrate, read_silhouettes, synthesize
from fitting.check import finer_settings
from fitting.cli import add_fit_parser, settings_from_args
from fitting.horizon import RESOLVED_MIN_FRAMES, grid_displacement, resolved_count, round_log, window_of
from fitting.joint import build_joint, calibrate_joint
from fitting.settings import FRAME_BOUNDARY_SPACINGS

from helpers import edited, scene as zoo_scene

SLUMP = zoo_scene("slump", initial_shape={"type": "box", "min": [-0.04, 0.0], "max": [0.04, 0.1]})
TRUTH = {"mu": 150.0, "sigma_y": 25.0, "eta": 5.0, "m": 0.6}
SETTINGS = FitSettings(dx=0.01, fixed={"mu": 150.0, "eta": 5.0, "m": 0.6}, starts=1, max_iter=8, dx_refit=1,
                       resolved_frames=True)
TIMES = [0.06, 0.12, 0.18, 0.24, 0.3]  # the slump data's observed frames, s
DROP = edited(zoo_scene("drop"), ("kappa",), 3000.0)  # the joint tests' second recording of the same foam


def _recorded(tmp_path_factory, spec, name: str, frames: int, noise: float, seed: int):
    """The path of synthetic data of `spec` at TRUTH (dx 5 mm, 0.3 s)."""
    path = tmp_path_factory.mktemp(name) / f"{name}.h5"
    synthesize(spec, TRUTH, dx=0.005, frames=frames, duration=0.3, noise=noise, seed=seed).write(path)
    return path


@pytest.fixture(scope="module")
def slump(tmp_path_factory):
    return _recorded(tmp_path_factory, SLUMP, "slump", frames=6, noise=0.02, seed=1)


def test_resolved_count_stops_before_the_first_unresolved_frame_and_keeps_a_minimum():
    """The first frame above the limit ends the window; NaN counts as unresolved; a record unresolved from
    its first frame keeps RESOLVED_MIN_FRAMES; a resolved record keeps every frame."""
    assert resolved_count([0.2, 0.4, 0.9, 1.3, 0.5, 2.0]) == 3  # the 0.5 after the first miss does not count
    assert resolved_count([0.2, 0.3, 0.4, 0.5, np.nan]) == 4
    assert resolved_count([1.5, 0.2, 0.3, 0.2, 0.2]) == RESOLVED_MIN_FRAMES == 3
    assert resolved_count([0.1, 0.2]) == 2  # a record shorter than the minimum keeps what it has
    assert resolved_count([0.1] * 7) == 7
    # the limit itself is resolved
    assert resolved_count([0.2, FRAME_BOUNDARY_SPACINGS, 0.3, 1.01 * FRAME_BOUNDARY_SPACINGS, 0.1]) == 3


def test_window_of_ends_half_way_to_the_next_frame_and_keeps_the_users_start():
    assert window_of(TIMES, 3, None) == (0.0, pytest.approx(0.21))
    assert window_of(TIMES, 2, (0.1, 0.3)) == (0.1, pytest.approx(0.15))
    assert window_of(TIMES, 5, None) is None
    assert window_of(TIMES, 5, (0.05, 0.31)) == (0.05, 0.31)


def test_round_logs_sit_beside_the_final_log():
    assert round_log("/a/fit.fitlog.h5", 1).name == "fit.round1.fitlog.h5"
    assert round_log("/a/run.h5", 0).name == "run.round0.h5"
    assert round_log(None, 0) is None


def test_settings_and_cli_name_resolved_frames_and_a_fixed_joint_problem_refuses_it(slump):
    import argparse
    ap = argparse.ArgumentParser()
    add_fit_parser(ap.add_subparsers())
    args = ap.parse_args(["fit", "data.h5", "--out", "f.json", "--resolved-frames"])
    assert settings_from_args(args).resolved_frames is True
    assert settings_from_args(ap.parse_args(["fit", "data.h5", "--out", "f.json"])).resolved_frames is False
    with pytest.raises(CalibrationError, match="resolved_frames must be True or False, got 'yes'"):
        FitSettings(resolved_frames="yes").validate()
    # a joint fit measures its windows itself: a prebuilt joint problem (fixed windows) cannot take them
    with pytest.raises(CalibrationError, match="resolved_frames=True: the windows are measured by calibrate_joint"):
        build_joint([slump, slump], SETTINGS)
    joint = build_joint([slump, slump], dataclasses.replace(SETTINGS, resolved_frames=False))
    with pytest.raises(CalibrationError, match="pass the recordings, not a prebuilt joint"):
        calibrate_joint(None, SETTINGS, joint=joint)
    with pytest.raises(CalibrationError, match="windows: one time window per recording \\(2\\), got 1"):
        build_joint([slump, slump], dataclasses.replace(SETTINGS, resolved_frames=False), windows=[None])
    with pytest.raises(CalibrationError, match="start_z must be 1 finite joint fitted coordinates"):
        calibrate_joint(None, dataclasses.replace(SETTINGS, resolved_frames=False), joint=joint, start_z=[np.nan])


@pytest.mark.slow
def test_grid_displacement_measures_refinement_in_particle_spacings(slump):
    """At the truth the slump's silhouettes on dx = 1 cm and dx / sqrt 2 differ by a fraction of a particle
    spacing in every frame (measured 0.1-0.25) but not by nothing (two different grids); the same
    problem against itself gives exactly 0."""
    data = read_silhouettes(slump)
    plain = dataclasses.replace(SETTINGS, resolved_frames=False, dx_check=False)
    coarse = build_problem(data, plain)
    fine = build_problem(data, finer_settings(coarse, plain))
    theta = {"sigma_y": TRUTH["sigma_y"]}
    d = grid_displacement(coarse, fine, theta)
    assert d.shape == (5,)
    assert np.all(d < 0.5) and np.all(d > 0.02), d
    np.testing.assert_array_equal(grid_displacement(coarse, coarse, theta), 0.0)
    # an optimum on a bound (m = 1.5 from a fit) is measured just inside it, not refused
    lo, hi = coarse.transform.lower[0], coarse.transform.upper[0]
    assert np.all(np.isfinite(grid_displacement(coarse, fine, {"sigma_y": float(hi)})))
    assert np.all(np.isfinite(grid_displacement(coarse, fine, {"sigma_y": float(lo)})))


@pytest.fixture(scope="module")
def drop(tmp_path_factory):
    return _recorded(tmp_path_factory, DROP, "drop", frames=5, noise=0.01, seed=2)


class Interrupt(Exception):
    """Raised from the progress callback to kill a fit."""


def scripted(monkeypatch, answers):
    """Replace the grid measurement by `answers` (one displacement list per call, in order); returns the
    list of parameter points it was called at."""
    calls = []

    def fake(coarse, fine, theta):
        calls.append(dict(theta))
        return np.asarray(answers[min(len(calls), len(answers)) - 1], np.float64)

    monkeypatch.setattr(horizon, "grid_displacement", fake)
    return calls


@pytest.mark.slow
def test_rounds_shrink_the_window_refit_from_the_optimum_and_resume(slump, tmp_path, monkeypatch):
    """Scripted measurements: all 5 frames resolved at the start, then only the first 3 at each optimum.
    Round 0 fits 5 frames, round 1 refits 3 from round 0's optimum, the third measurement agrees, so the
    result is the 3-frame optimum (equal to a plain 3-frame fit started there) with the round record and
    a note naming t = 0.24 s; a fit killed in round 1 resumes to the same result, round 0 read back."""
    answers = [[0.2] * 5, [0.3, 0.4, 0.6, 1.4, 2.0], [0.3, 0.4, 0.7, 1.2, 1.9]]
    data = read_silhouettes(slump)
    calls = scripted(monkeypatch, answers)
    ref = calibrate(data, SETTINGS, log=tmp_path / "ref.fitlog.h5")
    assert len(calls) == 3
    rounds = ref.settings["resolved"]["rounds"]
    assert [r["resolved"] for r in rounds] == [5, 3, 3] and ref.settings["resolved"]["settled"] is True
    assert rounds[0]["window"] is None and rounds[1]["window"] == [0.0, pytest.approx(0.21)]
    assert ref.data["frames_used"] == [1, 2, 3] and list(ref.settings["time_window"]) == [0.0, pytest.approx(0.21)]
    assert ref.settings["resolved_frames"] is True and len(ref.frame_iou) == 3
    assert calls[1]["sigma_y"] == pytest.approx(rounds[0]["params"]["sigma_y"], rel=1e-12)
    assert ref.params["sigma_y"] == pytest.approx(rounds[1]["params"]["sigma_y"], rel=1e-12)
    assert "Fitted the first 3 of 5 frames (t <= 0.18 s)" in ref.notes[0] and "t = 0.24 s on" in ref.notes[0]
    assert ref.settings["dx_check"] is not None  # the final window's discretization check ran
    # ... at round 1's optimum itself (its fitted coordinates, not the parameters rounded inside bounds)
    np.testing.assert_array_equal(ref.z, rounds[1]["z"])
    with pytest.raises(CalibrationError, match="start_z must be 1 finite fitted coordinates"):
        calibrate(data, dataclasses.replace(SETTINGS, resolved_frames=False), start_z=[0.0, 1.0])
    for k in (0, 1):
        assert round_log(tmp_path / "ref.fitlog.h5", k).exists()

    # The same 3-frame fit made directly from round 0's optimum reaches the same point.
    direct = calibrate(data, dataclasses.replace(SETTINGS, resolved_frames=False, dx_check=False,
                                                 time_window=(0.0, 0.21),
                                                 initial={"sigma_y": rounds[0]["params"]["sigma_y"]}))
    assert ref.params["sigma_y"] == pytest.approx(direct.params["sigma_y"], rel=1e-9)
    assert ref.loss == pytest.approx(direct.loss, rel=1e-9)

    # Killed at round 1's second iteration, then resumed.
    calls.clear()
    log = tmp_path / "killed.fitlog.h5"
    seen = []

    def kill(info, theta):
        seen.append(info.iteration)
        if len(calls) == 2 and info.iteration == 1:
            raise Interrupt

    with pytest.raises(Interrupt):
        calibrate(data, SETTINGS, log=log, callback=kill)
    calls.clear()
    seen.clear()
    resumed = calibrate(data, SETTINGS, log=log, resume=True, callback=lambda info, theta: seen.append(info.iteration))
    assert resumed.params["sigma_y"] == pytest.approx(ref.params["sigma_y"], rel=1e-9)
    np.testing.assert_allclose(resumed.loss_history, ref.loss_history, rtol=1e-9)
    assert [r["resolved"] for r in resumed.settings["resolved"]["rounds"]] == [5, 3, 3]
    # Round 0 was read back from its log (no new iteration), round 1 continued after iteration 1.
    assert min(seen) >= 1, seen
    # The wall time counts the optimizer time the killed run spent (kept in the logs) too.
    assert resumed.wall_time >= sum(r["wall_time"] for r in resumed.settings["resolved"]["rounds"] if "wall_time" in r)


@pytest.mark.slow
def test_time_budget_covers_the_rounds_and_the_result_says_it_stopped_them(slump, monkeypatch):
    """A 1 us budget: round 0 stops at its start point (its first evaluation spends it), the measurement
    there would shrink the window to 3 frames, but no time is left for round 1, so the result is round 0's
    5-frame point with notes that the budget stopped both the start and the rounds."""
    scripted(monkeypatch, [[0.2] * 5, [0.3, 0.4, 0.6, 1.4, 2.0]])
    res = calibrate(read_silhouettes(slump), dataclasses.replace(SETTINGS, time_budget=1e-6))
    rounds = res.settings["resolved"]["rounds"]
    assert [r["resolved"] for r in rounds] == [5, 3] and rounds[-1]["stopped"] == "time budget"
    assert res.settings["resolved"]["settled"] is False and res.data["frames_used"] == [1, 2, 3, 4, 5]
    assert res.iterations == 0 and res.params["sigma_y"] == pytest.approx(rounds[0]["measured_at"]["sigma_y"])
    assert "the time budget ended the rounds" in res.notes[0]
    assert any(n.startswith("The time budget") for n in res.notes[1:])


@pytest.mark.slow
def test_command_line_fit_with_resolved_frames_writes_the_window_and_its_pictures(slump, tmp_path, monkeypatch):
    """`jaxfoam fit --resolved-frames` (scripted measurements: 3 of 5 frames resolved at the optimum) writes
    fit.json with the 3-frame window and round record, the round logs beside the fit log, and the overlay
    of the frames fitted; a fresh run replaces old round logs."""
    import json

    from jaxfoam.cli import main

    scripted(monkeypatch, [[0.2] * 5, [0.3, 0.4, 0.6, 1.4, 2.0]])
    out = tmp_path / "fit.json"
    stale = tmp_path / "fit.round2.fitlog.h5"
    stale.write_bytes(b"old")
    args = ["fit", str(slump), "--out", str(out), "--dx", "0.01", "--fix", "mu=150,eta=5,m=0.6", "--starts", "1",
            "--max-iter", "8", "--dx-refit", "1", "--resolved-frames"]
    assert main(args) == 0
    fit = json.loads(out.read_text())
    assert fit["settings"]["resolved_frames"] is True and fit["data"]["frames_used"] == [1, 2, 3]
    assert fit["settings"]["time_window"] == [0.0, pytest.approx(0.21)]
    assert [r["resolved"] for r in fit["settings"]["resolved"]["rounds"]] == [5, 3, 3]
    assert len(fit["z"]) == 1 and len(fit["frame_iou"]) == 3
    assert (tmp_path / "fit.round0.fitlog.h5").exists() and (tmp_path / "fit.round1.fitlog.h5").exists()
    assert not stale.exists()
    assert (tmp_path / "fit_overlay.png").stat().st_size > 1000


@pytest.mark.slow
def test_joint_fit_gets_a_window_per_recording_refits_and_resumes(slump, drop, tmp_path, monkeypatch):
    """A joint fit of the slump (5 frames) and a drop (4 frames) with scripted measurements: every frame of
    both resolved at the start, then 3 of the slump's and all of the drop's at each optimum. Round 0 fits
    all frames, round 1 refits the slump's first 3 with the drop's 4 from round 0's optimum, the third
    measurement agrees; the result is round 1's optimum (equal to a joint fit with those windows started
    there) with its discretization check, the windows and per-recording notes; a fit killed in round 1
    resumes to the same result; `jaxfoam fit a.h5 b.h5 --resolved-frames` writes the windows."""
    import json

    from jaxfoam.cli import main

    answers = [[0.2] * 5, [0.1] * 4, [0.3, 0.4, 0.6, 1.4, 2.0], [0.2, 0.3, 0.5, 0.9],
               [0.3, 0.4, 0.7, 1.2, 1.9], [0.2, 0.3, 0.5, 0.8]]
    calls = scripted(monkeypatch, answers)
    both = [slump, drop]
    ref = calibrate(both, SETTINGS, log=tmp_path / "ref.fitlog.h5")
    assert len(calls) == 6
    res = ref.settings["resolved"]
    assert [[r["resolved"] for r in k["recordings"]] for k in res["rounds"]] == [[5, 4], [3, 4], [3, 4]]
    assert res["settled"] is True and res["frames"] == [3, 4] and res["of"] == [5, 4]
    assert ref.settings["time_windows"] == [[0.0, pytest.approx(0.21)], None]
    # round 1 measured recording i at round 0's optimum
    assert calls[2]["sigma_y"] == pytest.approx(res["rounds"][0]["params"]["sigma_y"], rel=1e-12)
    np.testing.assert_array_equal(ref.z, res["rounds"][1]["z"])
    assert ref.notes[0].startswith("recording 0: Fitted the first 3 of 5 frames (t <= 0.18 s)")
    assert ref.notes[1].startswith("recording 1: Every frame is resolved") and "every window stays" in ref.notes[2]
    assert ref.numerical_error["sigma_y"] > 0  # the final stage's discretization check ran on both windows
    assert [len(r["frame_iou"]) for r in ref.recordings] == [3, 4]

    direct = calibrate_joint(None, dataclasses.replace(SETTINGS, resolved_frames=False, dx_check=False, starts=1),
                             joint=build_joint(both, dataclasses.replace(SETTINGS, resolved_frames=False),
                                               windows=[(0.0, 0.21), None]),
                             start_z=res["rounds"][0]["z"])
    assert ref.params["sigma_y"] == pytest.approx(direct.params["sigma_y"], rel=1e-9)

    calls.clear()
    log = tmp_path / "killed.fitlog.h5"

    def kill(msg):
        if len(calls) == 4 and "iter   1" in msg:
            raise Interrupt

    with pytest.raises(Interrupt):
        calibrate(both, SETTINGS, log=log, progress=kill)
    calls.clear()
    seen = []
    resumed = calibrate(both, SETTINGS, log=log, resume=True, progress=seen.append)
    assert resumed.params["sigma_y"] == pytest.approx(ref.params["sigma_y"], rel=1e-9)
    # round 0 was read back (no iteration reported before round 1's measurement)
    first_iter = next(i for i, m in enumerate(seen) if "] iter " in m)
    assert sum("resolved frames" in m for m in seen[:first_iter]) == 4, seen[:first_iter]

    calls.clear()
    out = tmp_path / "joint.json"
    assert main(["fit", str(slump), str(drop), "--out", str(out), "--dx", "0.01", "--fix", "mu=150,eta=5,m=0.6",
                 "--starts", "1", "--max-iter", "8", "--dx-refit", "1", "--resolved-frames"]) == 0
    fit = json.loads(out.read_text())
    assert fit["format"] == "jaxfoam-joint-fit" and fit["settings"]["resolved_frames"] is True
    assert fit["settings"]["time_windows"] == [[0.0, pytest.approx(0.21)], None]
    assert fit["params"]["sigma_y"] == pytest.approx(ref.params["sigma_y"], rel=1e-9) and len(fit["z"]) == 1
    assert (tmp_path / "joint.round0.fitlog.h5").exists() and (tmp_path / "joint.round1.fitlog.h5").exists()
