"""Tests for optim: per-field Adam, the means LR schedule, row helpers."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
from absl.testing import absltest

from clipgs_jax import config
from clipgs_jax import gaussians
from clipgs_jax import optim
from clipgs_jax import state as state_lib


class MeansLrTest(absltest.TestCase):

  def test_log_linear_values(self):
    cfg = config.OptimConfig()
    lr = lambda s: float(optim.means_lr(s, cfg, 2.0, 1000))
    np.testing.assert_allclose(lr(0), 2 * 1.6e-4, rtol=1e-6)
    np.testing.assert_allclose(lr(1000), 2 * 1.6e-6, rtol=1e-5)
    # Halfway in log space: the geometric mean, 2 * 1.6e-5.
    np.testing.assert_allclose(lr(500), 2 * 1.6e-5, rtol=1e-5)
    np.testing.assert_allclose(lr(5000), lr(1000))      # constant afterwards

  def test_explicit_decay_length(self):
    cfg = config.OptimConfig(means_lr_steps=100)
    np.testing.assert_allclose(optim.means_lr(100, cfg, 1.0, 30_000), 1.6e-6,
                               rtol=1e-5)

  def test_pure_under_jit(self):
    cfg = config.OptimConfig()
    f = jax.jit(lambda s: optim.means_lr(s, cfg, 3.0, 300))
    np.testing.assert_allclose(f(jnp.int32(150)),
                               optim.means_lr(150, cfg, 3.0, 300), rtol=1e-6)


class PartitionTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    self.params, _ = gaussians.empty(5, 2)
    self.cfg = config.OptimConfig()
    self.tx = optim.make(self.cfg, 2.0, 100)

  def test_first_step_uses_field_learning_rates(self):
    # Adam's first update is -lr * g / (|g| + eps) = -lr for unit gradients.
    state = self.tx.init(self.params)
    grads = jax.tree.map(jnp.ones_like, self.params)
    updates, state = self.tx.update(grads, state, self.params)
    want = {"means": 2 * 1.6e-4, "log_scales": 5e-3, "quats": 1e-3,
            "opacity_logits": 0.05, "sh_dc": 2.5e-3, "sh_rest": 2.5e-3 / 20}
    for field, lr in want.items():
      np.testing.assert_allclose(getattr(updates, field), -lr, rtol=1e-5,
                                 err_msg=field)
    self.assertEqual(int(optim.count(state)), 1)

  def test_row_and_field_helpers(self):
    state = self.tx.init(self.params)
    grads = jax.tree.map(lambda x: jnp.arange(1, x.size + 1, dtype=x.dtype
                                              ).reshape(x.shape), self.params)
    _, state = self.tx.update(grads, state, self.params)
    idx = jnp.array([1, 3, 5])                                 # 5: dropped
    zeroed = state_lib.map_rows(state, 5,
                                lambda x: x.at[idx].set(0, mode="drop"))
    for field in optim.FIELDS:
      mu, nu = optim.moments(zeroed, field)
      mu0, nu0 = optim.moments(state, field)
      rows = np.array([0, 2, 4])
      self.assertTrue(np.all(mu[np.array([1, 3])] == 0), field)
      self.assertTrue(np.all(nu[np.array([1, 3])] == 0), field)
      np.testing.assert_array_equal(mu[rows], mu0[rows])
      np.testing.assert_array_equal(nu[rows], nu0[rows])
      self.assertTrue(np.all(mu0[rows] != 0), field)
    # Step counts are not rows and survive.
    self.assertEqual(int(optim.count(zeroed)), 1)

    only_opacity = optim.zero_field(state, "opacity_logits", 5)
    mu, nu = optim.moments(only_opacity, "opacity_logits")
    self.assertTrue(np.all(mu == 0) and np.all(nu == 0))
    np.testing.assert_array_equal(optim.moments(only_opacity, "means")[0],
                                  optim.moments(state, "means")[0])
    with self.assertRaisesRegex(ValueError, "unknown field"):
      optim.zero_field(state, "colors", 5)

  def test_needs_positive_extent(self):
    with self.assertRaisesRegex(ValueError, "extent must be positive"):
      optim.make(self.cfg, 0.0, 100)

  def test_apply_updates_moves_every_field(self):
    state = self.tx.init(self.params)
    grads = jax.tree.map(jnp.ones_like, self.params)
    updates, _ = self.tx.update(grads, state, self.params)
    new = optax.apply_updates(self.params, updates)
    for field in optim.FIELDS:
      self.assertTrue(np.all(getattr(new, field) < getattr(self.params, field)),
                      field)


if __name__ == "__main__":
  absltest.main()
