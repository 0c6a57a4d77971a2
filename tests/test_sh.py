"""Spherical harmonics: closed forms, band masking, extremes, gradients."""

from absl.testing import parameterized
import chex
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import sh


class ShTest(parameterized.TestCase):

  def test_dc_only_is_constant_plus_offset(self):
    # Y_0^0 = 1 / (2 sqrt(pi)); colour = C0 * dc + 0.5.
    dc = jnp.array([[1.0, -1.0, 0.0]])
    dirs = jnp.array([[0.0, 0.0, 1.0]])
    out = sh.to_color(dc, jnp.zeros((1, 0, 3)), dirs, 0)
    c0 = 1 / (2 * np.sqrt(np.pi))
    np.testing.assert_allclose(out, [[c0 + 0.5, max(0.5 - c0, 0.0), 0.5]],
                               rtol=1e-6)

  def test_clamped_at_zero(self):
    out = sh.to_color(jnp.full((1, 3), -10.0), jnp.zeros((1, 0, 3)),
                      jnp.array([[1.0, 0, 0]]), 0)
    np.testing.assert_array_equal(out, 0.0)

  def test_rgb_to_dc_round_trip(self):
    rgb = jnp.array([[0.2, 0.5, 0.9]])
    out = sh.to_color(sh.rgb_to_dc(rgb), jnp.zeros((1, 0, 3)),
                      jnp.array([[0.0, 1.0, 0.0]]), 0)
    np.testing.assert_allclose(out, rgb, rtol=1e-6)

  def test_basis_is_orthonormal(self):
    # Monte Carlo over the sphere: integral of Y_i Y_j = delta_ij.
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200_000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    b = np.asarray(sh.basis(jnp.asarray(d), 3), np.float64)
    gram = 4 * np.pi * b.T @ b / len(d)
    np.testing.assert_allclose(gram, np.eye(16), atol=0.02)

  def test_degree_one_closed_form(self):
    # Y_1: -C1 y, C1 z, -C1 x with C1 = sqrt(3 / (4 pi)).
    c1 = np.sqrt(3 / (4 * np.pi))
    d = jnp.array([[0.6, 0.0, 0.8]])
    np.testing.assert_allclose(sh.basis(d, 1)[0, 1:],
                               [0.0, c1 * 0.8, -c1 * 0.6], rtol=1e-6)

  @parameterized.parameters(0, 1, 2, 3)
  def test_band_mask_ignores_higher_bands(self, active):
    rng = np.random.default_rng(active)
    rest = jnp.asarray(rng.normal(size=(5, 15, 3)), jnp.float32)
    dc = jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)
    d = jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)
    d = d / jnp.linalg.norm(d, axis=1, keepdims=True)
    keep = sh.num_rest_coeffs(active)
    full = sh.to_color(dc, rest, d, active)
    zeroed = sh.to_color(dc, rest.at[:, keep:].set(0.0), d, 3)
    np.testing.assert_allclose(full, zeroed, rtol=1e-5, atol=1e-6)

  def test_finite_output_and_gradient(self):
    rest = jnp.full((2, 15, 3), 1e4)
    dc = jnp.full((2, 3), -1e4)
    d = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])   # zero dir included
    f = lambda dc, rest: jnp.sum(sh.to_color(dc, rest, d, 3))
    chex.assert_tree_all_finite(jax.grad(f, argnums=(0, 1))(dc, rest))

  def test_check_grads(self):
    with jax.enable_x64(True):
      rng = np.random.default_rng(1)
      rest = jnp.asarray(rng.normal(size=(3, 8, 3)) * 0.1)
      dc = jnp.asarray(rng.normal(size=(3, 3)) + 2.0)   # away from the clamp
      d = jnp.asarray(rng.normal(size=(3, 3)))
      d = d / jnp.linalg.norm(d, axis=1, keepdims=True)
      jax.test_util.check_grads(lambda a, b: sh.to_color(a, b, d, 2),
                                (dc, rest), order=1)

  def test_bad_degree(self):
    with self.assertRaisesRegex(ValueError, "SH degree"):
      sh.num_rest_coeffs(4)
    with self.assertRaisesRegex(ValueError, "rest SH"):
      sh.degree_of(5)
