import itertools
import warnings

import numpy as np
import pytest
import torch

from covers_dist.symmetry import (
    D4_ELEMENTS,
    GROUP_NAMES,
    GroupElement,
    escnn_gspace,
    escnn_planar_repr,
    get_group,
    to_escnn_element,
)

E = GroupElement(0, 0)


def test_d4_has_eight_distinct_elements():
    assert len(set(D4_ELEMENTS)) == 8
    assert len({tuple(g.matrix().ravel()) for g in D4_ELEMENTS}) == 8


def test_group_laws_exhaustive():
    for a in D4_ELEMENTS:
        assert a * E == a and E * a == a
        assert a * a.inverse() == E and a.inverse() * a == E
        for b in D4_ELEMENTS:
            assert a * b in D4_ELEMENTS
            # composition agrees with matrix multiplication
            np.testing.assert_array_equal((a * b).matrix(), a.matrix() @ b.matrix())
            for c in D4_ELEMENTS:
                assert (a * b) * c == a * (b * c)


def test_d4_is_not_abelian_and_reflections_are_involutions():
    r, f = GroupElement(1, 0), GroupElement(0, 1)
    assert r * f != f * r
    for g in D4_ELEMENTS:
        if g.m:
            assert g * g == E


@pytest.mark.parametrize("name", GROUP_NAMES)
def test_subgroups_closed_under_composition_and_inverse(name):
    grp = get_group(name)
    for a, b in itertools.product(grp, grp):
        assert a * b in grp
    for a in grp:
        assert a.inverse() in grp
    assert E in grp
    assert len(grp) == {"D4": 8, "C4": 4, "D2": 4, "C2": 2, "D1": 2, "trivial": 1}[name]


def test_bad_group_and_element_names():
    with pytest.raises(ValueError, match="unknown symmetry group 'D8'"):
        get_group("D8")
    with pytest.raises(ValueError, match="unknown D4 element name"):
        GroupElement.from_name("r5")
    with pytest.raises(ValueError):
        GroupElement(4, 0)
    assert get_group("flip").name == "D1"


def test_rotation_is_counter_clockwise_and_mirror_flips_x():
    np.testing.assert_array_equal(GroupElement(1, 0).apply_vectors(np.array([1.0, 0.0])), [0.0, 1.0])
    np.testing.assert_array_equal(GroupElement(0, 1).apply_vectors(np.array([1.0, 2.0])), [-1.0, 2.0])


@pytest.mark.parametrize("g", D4_ELEMENTS, ids=lambda g: g.name)
def test_vector_action_matches_matrix_and_planar_layout(g):
    rng = np.random.default_rng(0)
    v = rng.normal(size=(5, 2))
    np.testing.assert_array_equal(g.apply_vectors(v), v @ g.matrix().T)
    flat = rng.normal(size=(3, 7))  # two planar pairs + three scalars
    out = g.apply_planar(flat, 2)
    np.testing.assert_array_equal(out[:, 4:], flat[:, 4:])
    np.testing.assert_array_equal(out[:, :2], g.apply_vectors(flat[:, :2]))
    np.testing.assert_array_equal(out[:, 2:4], g.apply_vectors(flat[:, 2:4]))


def _draw_point(size, p):
    """A one-pixel image with the pixel at planar point p (pixel units from the centre) set."""
    c = (size - 1) / 2
    img = np.zeros((size, size, 3), dtype=np.uint8)
    j, i = int(round(p[0] + c)), int(round(c - p[1]))
    img[i, j] = (255, 128, 7)
    return img


@pytest.mark.parametrize("size", [7, 8])
@pytest.mark.parametrize("g", D4_ELEMENTS, ids=lambda g: g.name)
def test_image_action_agrees_with_vector_action(g, size):
    c = (size - 1) / 2
    for i in range(size):
        for j in range(size):
            p = np.array([j - c, c - i])
            assert np.array_equal(g.apply_image(_draw_point(size, p)), _draw_point(size, g.apply_vectors(p)))


@pytest.mark.parametrize("g", D4_ELEMENTS, ids=lambda g: g.name)
def test_image_action_is_a_group_action_and_batch_forms_agree(g):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 255, size=(6, 6, 3), dtype=np.uint8)
    batch = rng.integers(0, 255, size=(2, 6, 6, 3), dtype=np.uint8)
    for h in D4_ELEMENTS:
        assert np.array_equal(g.apply_image(h.apply_image(img)), (g * h).apply_image(img))
    assert np.array_equal(g.apply_images(batch)[1], g.apply_image(batch[1]))
    t = torch.from_numpy(batch).permute(0, 3, 1, 2)
    assert torch.equal(g.apply_tensor(t).permute(0, 2, 3, 1), torch.from_numpy(g.apply_images(batch)))


def test_image_action_rejects_non_square():
    with pytest.raises(ValueError, match="square"):
        GroupElement(1, 0).apply_image(np.zeros((4, 5, 3)))


@pytest.mark.parametrize("name", GROUP_NAMES)
def test_escnn_mapping_agrees_on_images_and_planar_vectors(name):
    warnings.simplefilter("ignore")
    from escnn import nn as enn

    gs = escnn_gspace(name)
    ft = enn.FieldType(gs, [gs.trivial_repr])
    img = torch.randn(2, 1, 9, 9)
    rho = escnn_planar_repr(gs)
    seen = set()
    for g in get_group(name):
        e = to_escnn_element(g, gs)
        seen.add(e)
        moved = enn.GeometricTensor(img, ft).transform(e).tensor
        assert torch.allclose(moved, g.apply_tensor(img)), g
        np.testing.assert_allclose(rho(e), g.matrix(), atol=1e-9)
    assert len(seen) == gs.fibergroup.order() == len(get_group(name))


def test_escnn_mapping_rejects_elements_outside_the_group():
    gs = escnn_gspace("C4")
    with pytest.raises(ValueError, match="not in the cyclic group"):
        to_escnn_element(GroupElement(0, 1), gs)
