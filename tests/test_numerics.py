"""numerics: values, finiteness at extremes, and numerical gradients."""

from absl.testing import parameterized
import chex
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import numerics

EXTREMES = jnp.array([-1e30, -1e4, -88.0, -1.0, 0.0, 1e-30, 1.0, 88.0, 89.0,
                      1e4, 1e30], jnp.float32)


class SafeExpTest(parameterized.TestCase):

  def test_values(self):
    x = jnp.array([-2.0, 0.0, 3.0, 88.0, 100.0])
    np.testing.assert_allclose(numerics.safe_exp(x),
                               np.exp(np.minimum(x, 88.0)), rtol=1e-6)

  def test_finite_output_and_gradient(self):
    chex.assert_tree_all_finite(numerics.safe_exp(EXTREMES))
    chex.assert_tree_all_finite(jax.vmap(jax.grad(numerics.safe_exp))(
        EXTREMES))

  def test_check_grads(self):
    with jax.enable_x64(True):
      jax.test_util.check_grads(numerics.safe_exp,
                                (jnp.array([-1.0, 0.5, 2.0]),), order=2)


class SafeSqrtNormalizeTest(parameterized.TestCase):

  def test_values(self):
    x = jnp.array([-4.0, 0.0, 4.0, 9.0])
    np.testing.assert_allclose(numerics.safe_sqrt(x), [0.0, 0.0, 2.0, 3.0])
    v = jnp.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(numerics.safe_normalize(v),
                               [[0.6, 0.8, 0.0], [0.0, 0.0, 0.0]])

  @parameterized.named_parameters(
      ("sqrt", lambda x: numerics.safe_sqrt(x)),
      ("normalize", lambda x: numerics.safe_normalize(
          jnp.stack([x, 2 * x], -1))[..., 0]))
  def test_finite_output_and_gradient(self, fn):
    # Squares of |x| > ~1e19 overflow float32; norms are only asked to be
    # safe where the squared norm is representable.
    x = jnp.clip(EXTREMES, -1e18, 1e18)
    chex.assert_tree_all_finite(fn(x))
    grads = jax.vmap(jax.grad(fn))(x)
    chex.assert_tree_all_finite(grads)

  def test_zero_gradients_at_zero(self):
    self.assertEqual(float(jax.grad(numerics.safe_sqrt)(0.0)), 0.0)
    np.testing.assert_array_equal(
        jax.jacobian(numerics.safe_normalize)(jnp.zeros(3)), 0.0)

  def test_check_grads(self):
    with jax.enable_x64(True):
      v = jnp.array([[0.3, -1.2, 2.0], [1.0, 0.5, -0.1]])
      jax.test_util.check_grads(numerics.safe_normalize, (v,), order=1)
      jax.test_util.check_grads(numerics.safe_sqrt, (jnp.array([0.5, 3.]),),
                                order=1)
