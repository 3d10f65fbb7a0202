"""The recovery study resumes: re-running it over its finished (committed) records fits nothing and writes
nothing, and a record is written whole or not at all, so a killed study leaves no truncated file."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # experiments/ is a folder of the repository
from experiments.recovery import cases, runs


@pytest.mark.parametrize("quick", [True, False])
def test_rerunning_the_finished_study_fits_nothing(quick, monkeypatch, tmp_path, capsys):
    def no_fit(*args, **kwargs):
        raise AssertionError("a finished case was fitted again")

    monkeypatch.setattr(runs, "WORK", tmp_path)  # no fit logs: finished records are final
    monkeypatch.setattr(runs, "calibrate", no_fit)
    monkeypatch.setattr(runs, "make_data", no_fit)
    before = sorted(p.name for p in cases.CASES.iterdir())
    runs.run_study(quick)
    out = capsys.readouterr().out
    assert "FAILED" not in out and "== " not in out, out
    assert sorted(p.name for p in cases.CASES.iterdir()) == before


def test_a_record_is_written_whole(tmp_path):
    path = tmp_path / "sub" / "case_lm.json"
    cases.write_atomic(path, "{}\n")
    cases.write_cache(path, {"a": 1})
    assert path.read_text() == '{"a": 1}\n'
    assert [p.name for p in path.parent.iterdir()] == ["case_lm.json"]
