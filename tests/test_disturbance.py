"""Disturbance processes: the paper recipe bit for bit, seeded boxes, hold semantics."""

import numpy as np
import pytest

from hmpc_cli.sim.disturbance import make_disturbance, paper_fig3_sequence


def test_paper_recipe_first_values():
    w = paper_fig3_sequence(1, magnitude=10.0)
    # MT19937(5489): 0.8147, 0.9058, 0.1270 ... -> w = 20 (U - 0.5)
    np.testing.assert_allclose(w[:3, 0], 20 * (np.array([0.8147, 0.9058, 0.1270]) - 0.5),
                               atol=2e-3)
    assert w.shape == (61, 2)
    stream = np.random.RandomState(5489).random_sample(1220)
    np.testing.assert_array_equal(w[:, 0], 20 * (stream[:61] - 0.5))
    np.testing.assert_array_equal(w[:, 1], 20 * (stream[61:122] - 0.5))
    w10 = paper_fig3_sequence(10, magnitude=10.0)
    np.testing.assert_array_equal(w10[:, 1], 20 * (stream[1159:1220] - 0.5))


def test_held_piecewise_constant_on_the_knot_grid():
    d = make_disturbance("paper_fig3", n_w=2, duration=3.0, magnitude=10.0, trial=3)
    seq = paper_fig3_sequence(3)
    assert np.array_equal(d(0.0), seq[0]) and np.array_equal(d(0.0499), seq[0])
    assert np.array_equal(d(0.05), seq[1]) and np.array_equal(d(0.15), seq[3])
    assert np.array_equal(d(3.0), seq[60]) and np.array_equal(d(5.0), seq[60])


def test_box_process_is_seeded_and_bounded():
    a = make_disturbance("box", n_w=2, duration=3.0, magnitude=5.0, hold=0.1, seed=7)
    b = make_disturbance("box", n_w=2, duration=3.0, magnitude=5.0, hold=0.1, seed=7)
    c = make_disturbance("box", n_w=2, duration=3.0, magnitude=5.0, hold=0.1, seed=8)
    assert np.array_equal(a.values, b.values) and not np.array_equal(a.values, c.values)
    assert a.values.shape == (31, 2) and np.all(np.abs(a.values) <= 5.0)
    assert np.all(make_disturbance("none", n_w=2, duration=1.0)(0.7) == 0.0)
    with pytest.raises(ValueError):
        paper_fig3_sequence(11)
