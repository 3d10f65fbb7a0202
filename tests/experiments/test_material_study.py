"""The material study's page judges the issue's goals from its records: the joint interval's narrowing
is the best single half-width over the joint one (relative, per parameter), a designed fit counts only
with every parameter within tolerance and its truth inside, and predicted against achieved is a ratio."""
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # experiments/ is a folder of the repository
from experiments import _common as C  # noqa: E402
from experiments import material_study as S  # noqa: E402
from experiments.reference import generate as G  # noqa: E402


def _fit(truth, scale, shift=1.0, stat=None):
    """A record whose value is truth*shift (m + shift - 1), its intervals value */ exp(scale) (m +- scale)."""
    params = {n: (truth[n] + shift - 1.0 if n == "m" else truth[n] * shift) for n in S.NAMES}
    def iv(s):
        return {n: ([params[n] - s, params[n] + s] if n == "m" else [params[n] / math.exp(s), params[n] * math.exp(s)])
                for n in S.NAMES}
    return dict(params=params, interval=iv(scale), interval_statistical=iv(stat or scale / 2), wall=60.0,
                information_share={n: [0.5, 0.3, 0.2] for n in S.NAMES},
                recordings=[dict(name=f"r{i}", scale=1.0, loss=0.1, reproduced=True) for i in range(3)])


def test_report_judges_the_goals_from_the_records(tmp_path, monkeypatch):
    monkeypatch.setattr(S, "RECORDS", tmp_path / "records")
    monkeypatch.setattr(C, "RESULTS", tmp_path)
    truth = G.materials()[0]
    for kind, hw in zip(S.KINDS, (0.9, 0.6, 1.2)):
        S._save(S.record_path(0, "single", kind), _fit(truth, hw))
    S._save(S.record_path(0, "joint"), _fit(truth, 0.25))       # log widths: best single 0.6 / 0.25 = 2.4x
    S._save(S.record_path(0, "designed_joint"), _fit(truth, 0.2, shift=1.05, stat=0.04))
    S._save(S.record_path(0, "design"), dict(candidates=20, wall=100.0, values={"plate.motion.amplitude": 0.02},
                                             advice="Film 1 s.", predicted_guess={n: 0.05 for n in S.NAMES},
                                             predicted_worst={n: 0.06 for n in S.NAMES},
                                             predicted_truth={n: 0.1 for n in S.NAMES}))
    page = S.report([0]).read_text()
    assert "sigma_y and eta reported intervals at least 2x narrower than the best single recording's: 1 of 1" in page
    assert "sigma_y 2.40 (statistical 2.40); eta 2.40" in page
    # +5% on mu, sigma_y (tolerance 10%), eta (25%) and +0.05 on m (0.1): within, truth inside
    assert "all four parameters within tolerance with the truth inside: 1 of 1" in page
    # achieved statistical half-width sinh(0.04) against 0.1 predicted at the truth: 0.4, outside [0.5, 2]
    assert "within 2x of the predicted (at the truth): 0 of 4" in page
    S._save(S.record_path(0, "designed_joint"), _fit(truth, 0.2, shift=1.15, stat=0.1))
    page = S.report([0]).read_text()
    assert "truth inside: 0 of 1" in page and "(at the truth): 4 of 4" in page


def test_half_width_and_error_follow_the_design_tolerance_convention():
    assert S.half_width("mu", (90.0, 130.0), 100.0) == pytest.approx(0.2)
    assert S.half_width("m", (0.4, 0.6), 0.5) == pytest.approx(0.1)
    assert S.within("eta", 1.24, 1.0) and not S.within("sigma_y", 1.11, 1.0)
    assert S.log_width("eta", (0.5, 2.0)) == pytest.approx(math.log(4.0)) and S.log_width("m", (0.2, 0.5)) == pytest.approx(0.3)
    assert S.covers_bounds("m", (0.2, 1.5), S.SETTINGS) and not S.covers_bounds("m", (0.3, 1.2), S.SETTINGS)
    lo, hi = S.SETTINGS.bounds_of("eta")
    assert S.covers_bounds("eta", (lo * 1.5, hi), S.SETTINGS) and not S.covers_bounds("eta", (1.0, 10.0), S.SETTINGS)
    assert S.error("m", 0.7, 0.6) == pytest.approx(0.1)


def test_a_fit_on_a_bound_becomes_a_guess_inside_it():
    """The design refuses a guess on a bound (its transform is open there): the study moves such a value
    GUESS_MARGIN of the span inside (log span for positive parameters) and leaves interior values alone."""
    lo, hi = S.SETTINGS.bounds_of("m")
    g = S.inside_bounds({"mu": 210.0, "sigma_y": 43.7, "eta": 15.2, "m": lo})
    assert g["m"] == pytest.approx(lo + S.GUESS_MARGIN * (hi - lo)) and g["mu"] == 210.0 and g["eta"] == 15.2
    mlo, mhi = S.SETTINGS.bounds_of("mu")
    assert S.inside_bounds({"mu": mhi})["mu"] == pytest.approx(mhi * (mlo / mhi) ** S.GUESS_MARGIN)


def test_a_grid_fits_another_grids_design_under_its_own_record(tmp_path, monkeypatch):
    """--design-grid: the default grid's designed joint fit reads the 1 cm grid's design records and writes
    its own record (mat<K>_designed_joint_default_design1cm); the page says where the design was ranked."""
    import dataclasses
    monkeypatch.setattr(S, "RECORDS", tmp_path / "records")
    monkeypatch.setattr(C, "RESULTS", tmp_path)
    grid = dataclasses.replace(S.GRIDS["default"], design_from="1cm")
    assert grid.design is S.GRIDS["1cm"] and grid.designed_tag == "_default_design1cm"
    assert S.GRIDS["default"].design is S.GRIDS["default"] and S.GRIDS["default"].designed_tag == "_default"
    check = dataclasses.replace(S.GRIDS["default"], design_from="1cm_check")
    assert check.design.design_check and check.design.guess_tag == "" and check.designed_tag == "_default_design1cm_check"
    truth = G.materials()[0]
    for kind in S.KINDS:
        S._save(S.record_path(0, "single", kind, grid=grid), _fit(truth, 0.9))
    S._save(S.record_path(0, "joint", grid=grid), _fit(truth, 0.25))
    with pytest.raises(SystemExit, match="the design's guess needs the joint fit mat0_joint.json"):
        S.run_material(0, "designed_joint", grid, say=lambda m: None)
    S._save(S.record_path(0, "design", grid=S.GRIDS["1cm"]),
            dict(candidates=20, wall=100.0, values={"plate.motion.amplitude": 0.02}, advice="Film 1 s.",
                 predicted_guess={n: 0.05 for n in S.NAMES}, predicted_worst={n: 0.06 for n in S.NAMES},
                 predicted_truth={n: 0.1 for n in S.NAMES}))
    S._save(S.RECORDS / "mat0_designed_joint_default_design1cm.json", _fit(truth, 0.2, shift=1.05, stat=0.04))
    page = S.report([0], grid).read_text()
    assert "on the 1cm grid" in page and "all four parameters within tolerance with the truth inside: 1 of 1" in page
    assert "--design-grid 1cm" in page


def test_resolved_grid_page_lists_the_frames_fitted_and_its_command(tmp_path, monkeypatch):
    """On the resolved-frames grids each column says how many of its frames the fit used (joint: per
    recording), and the page's command names its grid."""
    monkeypatch.setattr(S, "RECORDS", tmp_path / "records")
    monkeypatch.setattr(C, "RESULTS", tmp_path)
    grid = S.GRIDS["1cm_resolved"]
    truth = G.materials()[0]
    for kind, n in zip(S.KINDS, (16, 12, 14)):
        S._save(S.record_path(0, "single", kind, grid=grid), dict(_fit(truth, 0.5), resolved_frames=n - 2, of=n))
    S._save(S.record_path(0, "joint", grid=grid), dict(_fit(truth, 0.25), resolved_frames=[13, 12, 14], of=[16, 12, 14]))
    page = S.report([0], grid).read_text()
    assert ("Frames fitted (resolved of observed): hanging_plate alone 14 of 16; drop alone 10 of 12; squeeze alone "
            "12 of 14; joint (h + d + s) [13, 12, 14] of [16, 12, 14].") in page
    assert "material_study --grid 1cm_resolved" in page and "every fit on the frames its grid resolves" in page
