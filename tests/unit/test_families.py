"""The model families of the core (``magkf.families``): nested subspaces of ``(R, b)``."""

import numpy as np
import pytest

from magkf.families import FAMILIES, MODEL_CHOICES, family


@pytest.mark.parametrize("name", FAMILIES)
def test_basis_is_orthonormal_and_frees_the_offsets(name):
    T = family(name).basis
    np.testing.assert_allclose(T.T @ T, np.eye(T.shape[1]), atol=1e-15)
    assert np.all(np.abs(T[9:12]).sum(axis=1) > 0)  # every family estimates b


def test_families_are_nested_and_sized():
    sizes = [family(name).size for name in FAMILIES]
    assert sizes == [3, 6, 9, 12]
    for poor, rich in zip(FAMILIES, FAMILIES[1:]):
        P, Q = family(poor).basis, family(rich).basis
        # each poorer family's directions lie in the richer one's span
        np.testing.assert_allclose(Q @ (Q.T @ P), P, atol=1e-15)


def test_soft_iron_keeps_r_symmetric_and_holds_the_rest():
    rng = np.random.default_rng(3)
    reference = np.concatenate([(np.eye(3) + 0.05 * rng.normal(size=(3, 3))).ravel(), rng.normal(size=3) * 100])
    core = np.concatenate([(np.eye(3) + 0.05 * rng.normal(size=(3, 3))).ravel(), rng.normal(size=3) * 100])
    soft = family("soft-iron").project(core, reference)
    R = soft[:9].reshape(3, 3)
    np.testing.assert_allclose(R, R.T, atol=1e-15)
    np.testing.assert_allclose(soft[9:], core[9:])
    offsets = family("offsets").project(core, reference)
    np.testing.assert_array_equal(offsets[:9], reference[:9])  # R held at the reference exactly
    scale = family("scale").project(core, reference)
    assert np.all(scale[[1, 2, 3, 5, 6, 7]] == reference[[1, 2, 3, 5, 6, 7]])
    np.testing.assert_allclose(scale[[0, 4, 8]], core[[0, 4, 8]])


def test_restricted_drops_the_columns_of_a_component_that_did_not_vary():
    full = family("full").restricted([True, True, False])  # a level drive: the vertical barely changes
    assert full.size == 12 - 3
    R_free = np.abs(full.basis[:9]).sum(axis=1).reshape(3, 3) > 0
    assert not R_free[:, 2].any() and R_free[:, :2].all()
    soft = family("soft-iron").restricted([True, True, False])
    assert soft.size == 3 + 2 + 1  # b, R11 and R22, the symmetric pair (1, 2)
    assert family("offsets").restricted([False] * 3) is not None
    assert family("offsets").restricted([False] * 3).size == 3
    assert "hardly varied" in full.estimates


def test_unknown_family_is_refused():
    with pytest.raises(ValueError, match="soft-iron"):
        family("diagonal")
    assert MODEL_CHOICES[0] == "auto"
