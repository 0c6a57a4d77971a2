"""Tests for state: the row operations keep every per-row array aligned."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from clipgs_jax import gaussians
from clipgs_jax import state as state_lib
from test_densify import _first, _make_state, _row_leaves, _tag_state  # pylint: disable=g-bad-import-order


class RowOperationsTest(absltest.TestCase):

  def test_write_rows(self):
    state = _make_state(6, 4, np.random.default_rng(2))
    state = _tag_state(state, np.arange(1, 7))
    values, _ = gaussians.empty(2, state.params.sh_degree)
    values = values.replace(means=jnp.full((2, 3), 7.0))
    # Index 6 is out of range (the fill value of a sized nonzero): dropped.
    out = state_lib.write_rows(state, jnp.array([4, 6]), values, alive=True)
    np.testing.assert_array_equal(out.alive, [1, 1, 1, 1, 1, 0])
    np.testing.assert_array_equal(out.params.means[4], [7.0, 7.0, 7.0])
    np.testing.assert_array_equal(out.params.means[5], state.params.means[5])
    tags = [1, 2, 3, 4, 0, 6]              # row 4 starts afresh
    for m in _row_leaves(out):
      np.testing.assert_array_equal(m[_first(m)], tags)
    np.testing.assert_array_equal(out.semantic.acc, tags)
    # values None keeps the parameters: a prune.
    pruned = state_lib.write_rows(state, jnp.array([0]), None, alive=False)
    np.testing.assert_array_equal(pruned.params.means, state.params.means)
    self.assertFalse(bool(pruned.alive[0]))
    np.testing.assert_array_equal(pruned.semantic.n[:2], [0.0, 2.0])

  def test_resize(self):
    state = _make_state(8, 5, np.random.default_rng(3))
    state = _tag_state(state, np.arange(1, 9))
    grown = state_lib.resize(state, 12)
    self.assertEqual(grown.capacity, 12)
    np.testing.assert_array_equal(grown.params.means[:8], state.params.means)
    np.testing.assert_array_equal(grown.params.quats[8:],
                                  np.tile([1.0, 0, 0, 0], (4, 1)))
    self.assertFalse(np.any(grown.alive[8:]))
    for m in _row_leaves(grown):
      self.assertEqual(m.shape[0], 12)
      np.testing.assert_array_equal(m[8:], 0)
      np.testing.assert_array_equal(m[_first(m)][:8], np.arange(1, 9))
    np.testing.assert_array_equal(grown.semantic.acc[8:], 0)
    shrunk = state_lib.resize(grown, 8)
    chex.assert_trees_all_equal(jax.device_get(shrunk.params),
                                jax.device_get(state.params))
    with self.assertRaisesRegex(ValueError, "alive rows would be lost"):
      state_lib.resize(state, 4)


if __name__ == "__main__":
  absltest.main()
