"""Tests for losses: L1, SSIM (valid/same) and the 3DGS photometric loss."""

import jax
import jax.test_util  # pylint: disable=unused-import
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from clipgs_jax import losses


def _ssim_numpy(a, b, padding):
  """Direct per-window SSIM: every window summed explicitly (float64)."""
  a = np.asarray(a, np.float64)
  b = np.asarray(b, np.float64)
  x = np.arange(11) - 5.0
  g = np.exp(-0.5 * (x / 1.5) ** 2)
  w = np.outer(g, g)
  w /= w.sum()
  if padding == "same":
    a = np.pad(a, ((5, 5), (5, 5), (0, 0)))
    b = np.pad(b, ((5, 5), (5, 5), (0, 0)))
  h, wd = a.shape[0] - 10, a.shape[1] - 10
  out = np.zeros((h, wd, a.shape[2]))
  for i in range(h):
    for j in range(wd):
      pa, pb = a[i:i + 11, j:j + 11], b[i:i + 11, j:j + 11]
      mu_a = np.einsum("ij,ijc->c", w, pa)
      mu_b = np.einsum("ij,ijc->c", w, pb)
      var_a = np.einsum("ij,ijc->c", w, (pa - mu_a) ** 2)
      var_b = np.einsum("ij,ijc->c", w, (pb - mu_b) ** 2)
      cov = np.einsum("ij,ijc->c", w, (pa - mu_a) * (pb - mu_b))
      out[i, j] = ((2 * mu_a * mu_b + 1e-4) * (2 * cov + 9e-4)
                   / ((mu_a ** 2 + mu_b ** 2 + 1e-4) * (var_a + var_b + 9e-4)))
  return out


class SsimTest(parameterized.TestCase):

  @parameterized.named_parameters(("valid", "valid"), ("same", "same"))
  def test_matches_direct_windows(self, padding):
    rng = np.random.default_rng(0)
    a = rng.random((16, 19, 3)).astype(np.float32)
    b = np.clip(a + 0.2 * rng.normal(size=a.shape), 0, 1).astype(np.float32)
    got = jax.jit(losses.ssim_map, static_argnums=2)(a, b, padding)
    want = _ssim_numpy(a, b, padding)
    self.assertEqual(got.shape, want.shape)
    np.testing.assert_allclose(got, want, atol=2e-5)
    np.testing.assert_allclose(losses.ssim(a, b, padding), want.mean(),
                               atol=2e-6)

  def test_identical_images_give_one(self):
    a = jax.random.uniform(jax.random.key(1), (2, 20, 24, 3))
    for padding in losses.PADDINGS:
      np.testing.assert_allclose(losses.ssim(a, a, padding), [1.0, 1.0],
                                 atol=1e-6)

  def test_constant_images_closed_form(self):
    # Constant images: variances and covariance are 0, so
    # SSIM = (2 m1 m2 + C1) / (m1^2 + m2^2 + C1) = (0.16 + 1e-4) / (0.2 + 1e-4)
    # for means 0.2 and 0.4 (valid windows, no border effect).
    a = jnp.full((12, 12, 3), 0.2)
    b = jnp.full((12, 12, 3), 0.4)
    want = (2 * 0.2 * 0.4 + 1e-4) / (0.2 ** 2 + 0.4 ** 2 + 1e-4)
    np.testing.assert_allclose(losses.ssim(a, b), want, rtol=1e-5)

  def test_same_padding_lowers_border(self):
    # Zero padding darkens border windows' means: "same" < "valid" for a
    # bright image pair.
    a = jnp.full((16, 16, 3), 0.8)
    b = jnp.full((16, 16, 3), 0.7)
    self.assertLess(float(losses.ssim(a, b, "same")),
                    float(losses.ssim(a, b, "valid")))

  def test_batch_dims(self):
    a = jax.random.uniform(jax.random.key(2), (2, 3, 12, 13, 3))
    b = jax.random.uniform(jax.random.key(3), (2, 3, 12, 13, 3))
    got = losses.ssim(a, b)
    self.assertEqual(got.shape, (2, 3))
    np.testing.assert_allclose(got[1, 2], losses.ssim(a[1, 2], b[1, 2]),
                               rtol=1e-6)

  def test_errors(self):
    a = jnp.zeros((8, 8, 3))
    with self.assertRaisesRegex(ValueError, "padding='same'"):
      losses.ssim(a, a, "valid")
    with self.assertRaisesRegex(ValueError, "padding must be"):
      losses.ssim(a, a, "full")
    with self.assertRaisesRegex(ValueError, "equal shapes"):
      losses.ssim(jnp.zeros((12, 12, 3)), jnp.zeros((12, 13, 3)))

  def test_finite_gradients_at_extremes(self):
    for lo, hi in ((0.0, 0.0), (1.0, 1.0), (0.0, 1.0), (-1e3, 1e3)):
      a = jnp.full((12, 12, 3), lo).at[::2].set(hi)
      b = jnp.full((12, 12, 3), hi)
      for padding in losses.PADDINGS:
        val, grad = jax.value_and_grad(
            lambda x: losses.ssim(x, b, padding))(a)
        self.assertTrue(np.isfinite(val))
        self.assertTrue(np.all(np.isfinite(grad)))

  def test_check_grads(self):
    rng = np.random.default_rng(5)
    a, b = rng.random((2, 11, 12, 2))
    with jax.enable_x64():
      a, b = jnp.asarray(a, jnp.float64), jnp.asarray(b, jnp.float64)
      jax.test_util.check_grads(lambda x: losses.ssim(x, b, "same"), (a,),
                                order=1, modes=("rev",))


class PhotometricTest(absltest.TestCase):

  def test_l1_value(self):
    a = jnp.array([[[0.0, 0.5, 1.0]]])
    b = jnp.array([[[0.5, 0.5, 0.0]]])
    np.testing.assert_allclose(losses.l1(a, b), 0.5)   # (0.5 + 0 + 1) / 3

  def test_mix(self):
    rng = np.random.default_rng(3)
    a = rng.random((16, 16, 3)).astype(np.float32)
    b = rng.random((16, 16, 3)).astype(np.float32)
    loss, terms = losses.photometric(a, b, 0.2)
    want = (0.8 * np.mean(np.abs(a - b))
            + 0.2 * (1 - _ssim_numpy(a, b, "same").mean()))
    np.testing.assert_allclose(loss, want, rtol=1e-5)
    np.testing.assert_allclose(terms["l1"], np.mean(np.abs(a - b)),
                               rtol=1e-6)
    loss_same, _ = losses.photometric(a, a, 0.2)
    np.testing.assert_allclose(loss_same, 0.0, atol=1e-6)


def test_weighted_photometric():
  rng = np.random.default_rng(0)
  pred = jnp.asarray(rng.uniform(size=(20, 24, 3)), jnp.float32)
  target = jnp.asarray(rng.uniform(size=(20, 24, 3)), jnp.float32)
  plain, _ = losses.photometric(pred, target, 0.2)
  ones, _ = losses.photometric(pred, target, 0.2, jnp.ones((20, 24)))
  np.testing.assert_allclose(ones, plain, rtol=1e-5)
  # Pixels with weight 0 do not matter: changing them leaves the loss.
  weight = jnp.ones((20, 24)).at[:, :12].set(0.0)
  a, _ = losses.photometric(pred, target, 0.2, weight)
  # Every masked pixel, the mask's border included (SSIM windows reach
  # 5 px across it): neither the photo there nor the render's gradient.
  b, _ = losses.photometric(pred, target.at[:, :12].set(0.0), 0.2, weight)
  np.testing.assert_allclose(a, b, rtol=1e-6)
  g = jax.grad(lambda p: losses.photometric(p, target, 0.2, weight)[0])(pred)
  assert float(jnp.abs(g[:, :12]).max()) == 0.0
  assert float(jnp.abs(g[:, 12:]).min()) > 0.0
  # Soft weights (dense CLIP maps) are continuous in the weight: a
  # near-zero weight is nearly the binary mask.
  c, _ = losses.photometric(pred, target, 0.2, weight.at[:, :12].set(1e-6))
  np.testing.assert_allclose(c, a, rtol=1e-4)


if __name__ == "__main__":
  absltest.main()
