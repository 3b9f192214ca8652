"""cpgjax.layout.FlatLayout against hand-written offsets: a pytree's leaves laid end to end in flattening order, the
same vector as ``jax.flatten_util.ravel_pytree``, read back by name in JAX and as NumPy views."""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from cpgjax.layout import FlatLayout


class Inner(NamedTuple):
    a: np.ndarray
    b: np.ndarray


class Outer(NamedTuple):
    first: np.ndarray
    inner: Inner
    last: np.ndarray


EXAMPLE = Outer(
    np.zeros(3, np.float32), Inner(np.zeros((2, 2), np.float32), np.zeros((), np.float32)), np.zeros(4, np.float32)
)


def test_offsets_sizes_and_field_slices():
    layout = FlatLayout(EXAMPLE)
    assert layout.size == 3 + 4 + 1 + 4 and layout.offsets == (0, 3, 7, 8)
    assert layout.shapes == ((3,), (2, 2), (), (4,))
    assert layout.slices == Outer(slice(0, 3), slice(3, 8), slice(8, 12))


def test_ravel_is_ravel_pytree_and_unravel_reads_it_back():
    layout = FlatLayout(EXAMPLE)
    tree = Outer(jnp.arange(3.0), Inner(jnp.arange(4.0).reshape(2, 2) + 10, jnp.float32(20)), jnp.arange(4.0) + 30)
    flat = layout.ravel(tree)
    np.testing.assert_array_equal(flat, ravel_pytree(tree)[0])
    back = jax.jit(layout.unravel)(flat)
    for x, y in zip(jax.tree.leaves(back), jax.tree.leaves(tree), strict=True):
        np.testing.assert_array_equal(x, y)


def test_numpy_unravel_gives_views_that_write_the_vector():
    layout = FlatLayout(EXAMPLE)
    x = layout.zeros()
    views = layout.unravel(x)
    views.inner.a[1, 0] = 5.0
    views.inner.b[...] = 7.0
    views.last[:] = 1.0
    expected = np.zeros(12, np.float32)
    expected[3 + 2], expected[7], expected[8:] = 5.0, 7.0, 1.0
    np.testing.assert_array_equal(x, expected)


def test_a_wrong_size_is_named():
    layout = FlatLayout(EXAMPLE)
    with pytest.raises(ValueError, match="shape \\(11,\\) for a layout of size 12"):
        layout.unravel(np.zeros(11, np.float32))
    with pytest.raises(ValueError, match="5 values where the layout has shape \\(4,\\)"):
        layout.ravel(EXAMPLE._replace(last=np.zeros(5, np.float32)))


def test_integer_leaves_come_back_in_their_dtype():
    class State(NamedTuple):
        force: np.ndarray
        tick: np.ndarray

    layout = FlatLayout(State(np.zeros(2, np.float32), np.zeros((), np.int32)))
    flat = jax.jit(layout.ravel)(State(jnp.array([1.5, 2.5]), jnp.int32(7)))
    assert flat.dtype == jnp.float32
    back = jax.jit(layout.unravel)(flat)
    assert back.tick.dtype == jnp.int32 and int(back.tick) == 7
    np.testing.assert_array_equal(back.force, [1.5, 2.5])
