"""Tests for metrics: PSNR, SSIM and LPIPS (AlexNet / VGG)."""

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from clipgs_jax import losses
from clipgs_jax import metrics


class PsnrSsimTest(absltest.TestCase):

  def test_psnr_known_value(self):
    a = jnp.zeros((2, 8, 8, 3))
    b = a.at[0].set(0.1).at[1].set(0.5)
    # MSE 0.01 -> 20 dB; MSE 0.25 -> -10 log10(0.25) = 6.0206 dB.
    np.testing.assert_allclose(metrics.psnr(b, a), [20.0, 6.0206], rtol=1e-4)

  def test_psnr_identical_is_capped(self):
    a = jnp.full((4, 4, 3), 0.3)
    # -10 log10(1e-10) = 100 dB: finite, so step metrics and means stay so.
    self.assertAlmostEqual(float(metrics.psnr(a, a)), 100.0, places=4)

  def test_ssim_is_valid_windows(self):
    a = jax.random.uniform(jax.random.key(0), (20, 20, 3))
    b = jax.random.uniform(jax.random.key(1), (20, 20, 3))
    np.testing.assert_allclose(metrics.ssim(a, b),
                               losses.ssim(a, b, "valid"), rtol=1e-6)
    np.testing.assert_allclose(metrics.ssim(a, a), 1.0, atol=1e-6)

  def test_image_metrics_clips_prediction(self):
    target = jnp.ones((16, 16, 3))
    pred = jnp.full((16, 16, 3), 1.7)       # clipped to 1: a perfect match
    out = metrics.image_metrics(pred, target)
    self.assertEqual(sorted(out), ["psnr", "ssim"])
    self.assertAlmostEqual(float(out["psnr"]), 100.0, places=4)


class LpipsTest(parameterized.TestCase):

  def test_not_built_until_asked(self):
    metrics._lpips_fn.cache_clear()
    metrics.image_metrics(jnp.zeros((16, 16, 3)), jnp.zeros((16, 16, 3)))
    self.assertEqual(metrics._lpips_fn.cache_info().currsize, 0)

  @parameterized.named_parameters(("alex", "alex"), ("vgg", "vgg"))
  def test_orders_distortions(self, net):
    rng = np.random.default_rng(0)
    x = np.linspace(0, 1, 64)
    clean = np.stack(list(np.meshgrid(x, x[::-1])) + [np.outer(x, x)], -1)
    clean = clean.astype(np.float32)
    mild = np.clip(clean + 0.03 * rng.normal(size=clean.shape), 0, 1)
    strong = np.clip(clean + 0.3 * rng.normal(size=clean.shape), 0, 1)
    batch_pred = jnp.asarray(np.stack([clean, mild, strong]), jnp.float32)
    batch_ref = jnp.asarray(np.stack([clean] * 3))
    d = np.asarray(metrics.lpips(batch_pred, batch_ref, net))
    self.assertEqual(d.shape, (3,))
    self.assertLess(d[0], 1e-6)           # identical images
    self.assertLess(d[0], d[1])
    self.assertLess(d[1], d[2])
    self.assertGreater(d[2], 0.1)         # heavy noise is far, perceptually
    # Symmetric in its arguments.
    np.testing.assert_allclose(
        metrics.lpips(batch_ref[2], batch_pred[2], net), d[2], rtol=1e-4)

  def test_backbones_differ_and_named(self):
    a = jax.random.uniform(jax.random.key(2), (64, 64, 3))
    b = jax.random.uniform(jax.random.key(3), (64, 64, 3))
    alex = metrics.image_metrics(a, b, "alex")["lpips"]
    vgg = metrics.image_metrics(a, b, "vgg")["lpips"]
    self.assertNotAlmostEqual(float(alex), float(vgg), places=3)
    self.assertEqual(sorted(metrics.LPIPS_NETS), ["alex", "vgg"])

  def test_bad_net(self):
    with self.assertRaisesRegex(ValueError, "net must be one of"):
      metrics.lpips(jnp.zeros((32, 32, 3)), jnp.zeros((32, 32, 3)), "squeeze")


if __name__ == "__main__":
  absltest.main()
