"""The showcase measurements (experiments/showcase/measure.py) on point sets whose answer is known:
a gap between a cap and a falling body, a decaying wobble of known decay time, a column with a gap above
it, the mass fraction near a sphere; and the errors of a bad `measure` list."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "experiments" / "showcase"))
import measure as M  # noqa: E402

H = 0.005  # slab height, m (the grid's dx)


def _column(lo, hi, n, rng):
    return rng.uniform(lo, hi, n)


def test_gap_between_cap_and_body_and_strays_do_not_close_it():
    rng = np.random.default_rng(0)
    body, cap = _column(0.10, 0.14, 400, rng), _column(0.16, 0.19, 300, rng)
    strays = np.array([0.151, 0.152])  # two loose points in the gap
    g = M.gap_height(np.concatenate([body, cap, strays]), top=0.19, h=H, min_count=5)
    assert g is not None and 0.14 - H <= g <= 0.16
    assert M.gap_height(_column(0.10, 0.19, 700, rng), top=0.19, h=H, min_count=5) is None


def test_detachment_is_the_first_frame_with_a_gap():
    rng = np.random.default_rng(1)
    times = np.array([0.1, 0.2, 0.3, 0.4])
    xs = []
    for k in range(4):
        y = _column(0.10, 0.19, 700, rng) if k < 2 else np.concatenate([_column(0.05, 0.12, 400, rng),
                                                                          _column(0.16, 0.19, 300, rng)])
        xs.append(np.stack([np.zeros_like(y), y, np.zeros_like(y)], -1))
    frames = {"x": np.array(xs), "active": np.ones((4, 700), bool), "mass": np.ones((4, 700))}
    det = M.detachment(frames, times, top=0.19, h=H, min_count=5)
    assert det["time"] == 0.3 and det["after"] == 0.2
    assert det["gaps"][0] is None and det["gaps"][3] is not None


def test_wobble_decay_time_of_a_damped_oscillation():
    """COM height floor + 3 cm + A exp(-t / tau) sin(2 pi f t) sampled every 0.01 s: the log-linear fit
    of the windows' peak-to-peak amplitudes returns tau within 15%."""
    tau, f, amp = 0.4, 4.0, 0.01
    times = np.arange(1.0, 2.0, 0.01)
    n = 50
    xs = []
    for t in times:
        c = 0.03 + amp * np.exp(-(t - 1.0) / tau) * np.sin(2 * np.pi * f * t)
        y = np.linspace(-0.005, 0.005, n) + c
        y[0] = 0.004  # the lowest point touches the floor's slab: landed
        y = y - y.mean() + c
        xs.append(np.stack([np.zeros(n), y, np.zeros(n)], -1))
    frames = {"x": np.array(xs), "active": np.ones((len(times), n), bool), "mass": np.ones((len(times), n))}
    w = M.wobble(frames, times, [0.2] * len(times), floor_y=0.0, h=H, window=0.25)
    assert w["landing"] == pytest.approx(1.0)
    assert len(w["amplitudes"]) == 4 and w["amplitudes"][0] > w["amplitudes"][-1]
    assert abs(w["decay_time"] / tau - 1) < 0.15, w["decay_time"]


def test_column_height_stops_at_the_first_gap():
    rng = np.random.default_rng(2)
    base = 0.035
    y = np.concatenate([_column(base, base + 0.05, 2000, rng), _column(base + 0.07, base + 0.09, 500, rng)])
    x = np.stack([rng.uniform(-0.03, 0.03, len(y)), y, rng.uniform(-0.03, 0.03, len(y))], -1)
    outside = np.array([[0.06, base + 0.2, 0.0]] * 50)  # off the footprint: not counted
    frames = {"x": np.concatenate([x, outside])[None], "active": np.ones((1, len(y) + 50), bool)}
    out = M.column_height(frames, np.array([1.0]), base, [[-0.04, 0.04], [-0.04, 0.04]], H, 5, [1.0])
    assert out["1.000"] == pytest.approx(0.05, abs=H)


def test_fraction_near_a_sphere_counts_mass_not_points():
    from jaxfoam.sdf import collider_from_spec
    sphere = collider_from_spec({"shape": {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 0.1}})
    x = np.array([[0.105, 0, 0], [0.0, 0.108, 0], [0.3, 0, 0], [0, 0, 0.5]])  # two within 1 cm of the surface
    frames = {"x": x[None], "active": np.ones((1, 4), bool), "mass": np.array([[1.0, 3.0, 2.0, 2.0]])}
    out = M.fraction_near(frames, np.array([0.4]), sphere, 0.01, [0.4])
    assert out == {"0.400": pytest.approx(0.5)}


def test_a_bad_measure_list_is_refused_naming_the_problem():
    frames = {"x": np.zeros((1, 3, 3)), "active": np.ones((1, 3), bool), "mass": np.ones((1, 3))}
    with pytest.raises(ValueError, match="type 'peaks' unknown"):
        M.measure_all([{"type": "peaks"}], frames, np.array([0.0]), None, (), 0.01)
    with pytest.raises(ValueError, match="'wobble' needs a 'detachment' entry before it"):
        M.measure_all([{"type": "wobble", "window": 0.2}], frames, np.array([0.0]), None, (), 0.01)


def test_pieces_counts_separate_clumps_by_mass_and_ignores_specks():
    rng = np.random.default_rng(3)
    a = rng.uniform(0.0, 0.05, (600, 3))
    b = rng.uniform(0.0, 0.03, (200, 3)) + [0.1, 0.0, 0.0]  # 3 cm from the first clump
    speck = np.array([[0.2, 0.0, 0.0]])
    x = np.concatenate([a, b, speck])
    frames = {"x": x[None], "active": np.ones((1, len(x)), bool), "mass": np.ones((1, len(x)))}
    out = M.pieces(frames, np.array([0.5]), H, 0.01, [0.5])["0.500"]
    assert out["count"] == 2
    assert out["fractions"] == [pytest.approx(600 / 801, abs=1e-4), pytest.approx(200 / 801, abs=1e-4)]


def test_mass_in_box():
    x = np.array([[0.0, 0.06, 0.0], [0.0, 0.01, 0.0], [0.05, 0.07, 0.0]])
    frames = {"x": x[None], "active": np.ones((1, 3), bool), "mass": np.array([[2.0, 1.0, 1.0]])}
    out = M.mass_in_box(frames, np.array([0.4]), [[-0.04, 0.04], [0.055, 0.2], [-0.04, 0.04]], [0.4])
    assert out == {"0.400": pytest.approx(0.5)}
