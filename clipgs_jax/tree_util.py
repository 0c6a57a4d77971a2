"""Row-wise helpers for pytrees whose leaves share a leading capacity axis."""

import jax
import jax.numpy as jnp


def tree_select(cond: jax.Array, a, b):
  """Per-leaf jnp.where(cond, a, b); `cond` broadcasts from the leading axis."""
  def select(x, y):
    c = jnp.reshape(cond, cond.shape + (1,) * (x.ndim - cond.ndim))
    return jnp.where(c, x, y)
  return jax.tree.map(select, a, b)


def tree_index_set(tree, idx: jax.Array, values):
  """Writes rows `values` at `idx` in every leaf; out-of-range idx are dropped.

  Out-of-range indices (e.g. the fill value of `jnp.nonzero(..., size=k,
  fill_value=capacity)`) write nothing, which is how a partial write into
  free slots stays shape-static.
  """
  return jax.tree.map(lambda x, v: x.at[idx].set(v, mode="drop"), tree,
                      values)
