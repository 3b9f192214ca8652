"""Named layouts of flat vectors: a pytree of arrays (a NamedTuple, nested) laid end to end in one vector.

Wherever a pytree must cross a boundary as one flat vector (a compiled call costs per argument; a 1 kHz loop writes
into preallocated buffers), :class:`FlatLayout` names its pieces once. ``ravel`` flattens a pytree (JAX or NumPy)
into the vector, ``unravel`` reads a vector back as the pytree, in JAX inside a compiled function or in NumPy, where
every leaf is a view into the vector (no copy): the loop writes a field by name, ``inputs.obs.gyro_rad_s[:] = …``,
and the compiled program reads it by the same name. The order of the leaves is ``jax.tree.flatten``'s, as in
``jax.flatten_util.ravel_pytree``, which does the same for JAX arrays only and gives no views.
"""

from __future__ import annotations

import math
from typing import Any, Generic, TypeVar

import jax
import jax.numpy as jnp
import numpy as np

T = TypeVar("T")


class FlatLayout(Generic[T]):
    """The layout of pytrees shaped like ``example`` (its leaves' shapes; their values are not kept) in a 1-D vector.

    Attributes:
      size: the vector's length.
      shapes: each leaf's shape, in flattening order.
      offsets: where each leaf starts in the vector.
      slices: for a NamedTuple ``example``, the same NamedTuple of each field's ``slice`` of the vector (a field's
        leaves are contiguous): ``x[layout.slices.state]`` is the state's part of ``x``, by name; None otherwise.
    """

    def __init__(self, example: T):
        leaves, self._treedef = jax.tree.flatten(example)
        self.shapes = tuple(tuple(np.shape(leaf)) for leaf in leaves)
        # Integer and boolean leaves travel as the vector's floats and are read back as their own dtype (a copy);
        # float leaves keep the vector's dtype, so in NumPy they stay views.
        dtypes = [np.asarray(leaf).dtype for leaf in leaves]
        self._casts = tuple(d if d.kind in "biu" else None for d in dtypes)
        sizes = [math.prod(shape) for shape in self.shapes]
        self.offsets = tuple(int(o) for o in np.cumsum([0, *sizes[:-1]]))
        self._sizes = tuple(sizes)
        self.size = int(sum(sizes))
        self.slices = None
        if hasattr(example, "_fields"):
            bounds = np.cumsum(
                [
                    0,
                    *(
                        sum(math.prod(np.shape(leaf)) for leaf in jax.tree.leaves(getattr(example, f)))
                        for f in example._fields
                    ),
                ]
            )
            self.slices = type(example)(*(slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)))

    def unravel(self, vector: Any) -> T:
        """The pytree read from ``vector`` (size,): JAX arrays in JAX; in NumPy, views into ``vector`` (integer and
        boolean leaves: copies in their own dtype)."""
        if vector.shape != (self.size,):
            raise ValueError(f"a vector of shape {vector.shape} for a layout of size {self.size}")
        leaves = [
            vector[o : o + n].reshape(shape) if cast is None else vector[o : o + n].reshape(shape).astype(cast)
            for o, n, shape, cast in zip(self.offsets, self._sizes, self.shapes, self._casts, strict=True)
        ]
        return jax.tree.unflatten(self._treedef, leaves)

    def ravel(self, tree: T, dtype=None) -> Any:
        """The vector (size,) of ``tree``: JAX if any leaf is a JAX array (or a tracer), else NumPy."""
        leaves = self._treedef.flatten_up_to(tree)
        xp = jnp if any(isinstance(leaf, jax.Array) for leaf in leaves) else np
        flat = [xp.ravel(xp.asarray(leaf)) for leaf in leaves]
        if dtype is None and flat:
            dtype = xp.result_type(*flat)
        flat = [leaf.astype(dtype) for leaf in flat]
        for leaf, shape in zip(flat, self.shapes, strict=True):
            if leaf.size != math.prod(shape):
                raise ValueError(f"a leaf of {leaf.size} values where the layout has shape {shape}")
        return xp.concatenate(flat) if flat else xp.zeros(0, dtype)

    def zeros(self, dtype=np.float32) -> np.ndarray:
        """A NumPy vector (size,) of zeros, for :meth:`unravel` to give named views into."""
        return np.zeros(self.size, dtype)
