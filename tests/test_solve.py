"""Marginals of a nearly singular linear system: a ridge instead of a crash, and none when not needed; a pose
chain's spins unwound."""
import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from casm_graph.fit.solve import marginals
from casm_graph.fit.turns import spins, unwind


def chain(first_row):
    """Two 3-dof variables joined by a relative factor; ``first_row`` pins X(0) (None: not at all)."""
    g = gtsam.GaussianFactorGraph()
    unit = gtsam.noiseModel.Unit.Create(3)
    g.add(X(0), -np.eye(3), X(1), np.eye(3), np.zeros(3), unit)
    if first_row is not None:
        g.add(X(0), first_row, np.zeros(3), unit)
    return g


def test_well_posed_system_needs_no_ridge():
    m, ridge = marginals(chain(np.eye(3)), [(X(0), 3), (X(1), 3)])
    assert ridge == 0.0
    np.testing.assert_allclose(m.marginalCovariance(X(1)), 2 * np.eye(3), atol=1e-9)


def test_singular_system_gets_a_ridge_and_huge_std_where_undetermined():
    pin = np.diag([1.0, 1.0, 0.0])                     # heading of X(0) not observed at all
    try:
        gtsam.Marginals(chain(pin), gtsam.VectorValues())
        plain_fails = False
    except RuntimeError:
        plain_fails = True
    assert plain_fails
    m, ridge = marginals(chain(pin), [(X(0), 3), (X(1), 3)])
    assert ridge > 0
    cov = m.marginalCovariance(X(1))
    assert cov[0, 0] < 3 and cov[2, 2] > 1e5           # determined directions stay, the free one shows


def test_a_spin_is_found_and_unwound_to_the_model_turns():
    """Five segments each turning 2 pi / 5 beyond a model that says straight: one spin, re-drawn from its first
    knot with the model's turns; a lone large residual (a real sharp turn the model missed) is no spin."""
    th = np.array([1.9, 1.9 + 2 * np.pi / 5, 1.9 + 4 * np.pi / 5, 1.9 + 6 * np.pi / 5, 1.9 + 8 * np.pi / 5,
                   1.91, 1.92])
    poses = np.column_stack([np.arange(7.0), np.zeros(7), np.angle(np.exp(1j * th))])
    turn = np.angle(np.exp(1j * np.diff(th)))
    assert spins(turn) == [(0, 5)]
    out = unwind(poses, turn, spins(turn))
    assert np.allclose(out[:, 2], [1.9, 1.902, 1.904, 1.906, 1.908, 1.91, 1.92])
    assert np.allclose(out[:, :2], poses[:, :2])
    assert spins(np.array([0.0, 2.0, 0.0, 0.1])) == []
