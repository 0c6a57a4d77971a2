"""Stiff and extreme cases: finite values and gradients, and agreement with
the dense reference wherever the reference is defined."""

import functools

from absl.testing import absltest
from absl.testing import parameterized
import chex
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config
from clipgs_jax.render import rasterize
import rasterize_ref
import synthetic

CFG = config.RenderConfig(tile_budget=256, chunk_size=8)
BG = jnp.array([0.1, 0.2, 0.3])
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


def _scene(n_extra=1, seed=0, dtype=jnp.float32):
  """Three ordinary Gaussians plus `n_extra` slots for the extreme case."""
  return synthetic.random_params(3 + n_extra, seed=seed, degree=1,
                                 dtype=dtype, spread=0.8)


def _set(params, row, **fields):
  """Sets row `row` of the given fields."""
  return params.replace(**{
      k: getattr(params, k).at[row].set(jnp.asarray(v, params.means.dtype))
      for k, v in fields.items()})


@functools.partial(jax.jit, static_argnames="cfg")
def _loss_and_grads(params, alive, cam, weights, cfg):
  def loss(p):
    out = rasterize.render(p, alive, cam, BG, cfg)
    return jnp.sum(out.image * weights) + jnp.sum(out.alpha) + 0.01 * jnp.sum(
        out.depth), out

  return jax.value_and_grad(loss, has_aux=True)(params)


def _render_and_grads(params, alive, cam, cfg=CFG):
  """Render and gradients of a fixed random linear loss, jit-cached by shape."""
  weights = jnp.asarray(np.random.default_rng(0).normal(
      size=(cam.height, cam.width, 3)), params.means.dtype)
  (_, out), grads = _loss_and_grads(params, alive, cam, weights, cfg=cfg)
  return out, grads


class ExtremeTest(parameterized.TestCase):

  def check(self, params, alive, cam=None, cfg=CFG, compare=True, atol=1e-5):
    cam = cam or synthetic.front_camera()
    out, grads = _render_and_grads(params, alive, cam, cfg)
    chex.assert_tree_all_finite((out.image, out.alpha, out.depth,
                                 out.contribution))
    chex.assert_tree_all_finite(grads)
    if compare:
      ref = rasterize_ref.render_ref(params, alive, cam, BG, near=cfg.near)
      np.testing.assert_allclose(out.image, ref["image"], atol=atol)
      np.testing.assert_allclose(out.alpha, ref["alpha"], atol=atol)
    return out, grads

  def test_scale_1e_minus_6(self):
    p = _set(_scene(), 3, log_scales=np.full(3, np.log(1e-6)),
             means=[0.0, 0.0, -1.0], opacity_logits=3.0)
    out, _ = self.check(p, jnp.ones(4, bool))
    # The 0.3 px^2 low-pass keeps a sub-pixel Gaussian visible.
    self.assertTrue(bool(out.visible[3]))

  def test_scale_1e4(self):
    p = _set(_scene(), 3, log_scales=np.full(3, np.log(1e4)))
    out, _ = self.check(p, jnp.ones(4, bool), atol=1e-4)
    self.assertTrue(bool(out.visible[3]))

  def test_behind_camera(self):
    p = _set(_scene(), 3, means=[0.0, 0.0, -6.0], opacity_logits=5.0)
    out, grads = self.check(p, jnp.ones(4, bool))
    self.assertFalse(bool(out.visible[3]))
    np.testing.assert_array_equal(grads.means[3], 0.0)

  @parameterized.named_parameters(("on_near_plane", 0.0),
                                  ("just_in_front", 1e-3))
  def test_near_plane(self, offset):
    # Camera at world z = -4 looking along +z; near = 0.25 is exact in
    # binary, so world z = -3.75 lies exactly on the near plane.
    cfg = config.RenderConfig(near=0.25, tile_budget=256, chunk_size=8)
    p = _set(_scene(), 3, means=[0.0, 0.0, -3.75 + offset],
             opacity_logits=5.0, log_scales=np.full(3, -3.0))
    out, _ = self.check(p, jnp.ones(4, bool), cfg=cfg, atol=1e-4)
    self.assertEqual(bool(out.visible[3]), offset > 0)

  def test_at_camera_centre(self):
    p = _set(_scene(), 3, means=[0.0, 0.0, -4.0], opacity_logits=5.0)
    out, grads = self.check(p, jnp.ones(4, bool))
    self.assertFalse(bool(out.visible[3]))
    np.testing.assert_array_equal(grads.log_scales[3], 0.0)

  @parameterized.named_parameters(
      # Long axis (local x) in the image plane, turned 45 degrees about the
      # view axis: the 2D covariance is ill-conditioned and off-diagonal.
      ("edge_on_diagonal", [np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)]),
      # Long axis turned onto the view direction: seen end-on as a point.
      ("end_on", [np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0]))
  def test_needle(self, quat):
    p = _set(_scene(), 3, means=[0.0, 0.0, 0.0], quats=quat,
             log_scales=np.log([1.0, 1e-4, 1e-4]), opacity_logits=4.0)
    out, _ = self.check(p, jnp.ones(4, bool), compare=False)
    self.assertTrue(bool(out.visible[3]))
    # The float32 naive ac - b^2 of the reference cancels catastrophically
    # here, so compare against it in float64.
    with jax.enable_x64(True):
      p64 = jax.tree.map(lambda x: x.astype(jnp.float64), p)
      cam64 = synthetic.front_camera(dtype=np.float64)
      ref = rasterize_ref.render_ref(p64, jnp.ones(4, bool), cam64,
                                     BG.astype(jnp.float64))
    np.testing.assert_allclose(out.image, ref["image"], atol=1e-4)

  @parameterized.named_parameters(("logit_minus_60", -60.0),
                                  ("logit_plus_60", 60.0))
  def test_extreme_opacity(self, logit):
    p = _set(_scene(), 3, means=[0.0, 0.0, -1.0], opacity_logits=logit,
             log_scales=np.full(3, -1.0))
    out, grads = self.check(p, jnp.ones(4, bool))
    self.assertEqual(bool(out.visible[3]), logit > 0)
    if logit > 0:
      # Opacity saturates at the 0.99 cap: the centre pixel is 99% covered.
      self.assertGreaterEqual(float(out.alpha[14, 18]), 0.99 - 1e-6)

  def test_zero_quaternion(self):
    p = _set(_scene(), 3, quats=[0.0, 0.0, 0.0, 0.0], opacity_logits=3.0)
    _, grads = self.check(p, jnp.ones(4, bool))
    # Zero quaternion means identity rotation with a zero gradient.
    np.testing.assert_array_equal(grads.quats[3], 0.0)

  def test_10000_stacked_on_one_pixel(self):
    n = 10_000
    cam = synthetic.front_camera(16, 16, focal=20.0)
    depths = np.linspace(-1.0, 1.0, n)
    p = synthetic.random_params(n, degree=0)
    p = synthetic.with_rows(
        p, means=np.stack([np.zeros(n), np.zeros(n), depths], -1),
        log_scales=np.full((n, 3), -2.0), opacity_logits=np.full(n, 4.0),
        quats=np.tile([1.0, 0, 0, 0], (n, 1)))
    cfg = config.RenderConfig(tile_budget=16384, chunk_size=32)
    out, _ = self.check(p, jnp.ones(n, bool), cam=cam, cfg=cfg)
    self.assertEqual(int(out.num_overflow), 0)
    # The centre pixel saturates within a few Gaussians; the far half of the
    # stack never blends anywhere.
    self.assertLess(float(1.0 - out.alpha[8, 8]), 1e-3)
    self.assertLess(int(jnp.sum(out.visible)), n // 2)

  def test_tile_budget_overflow(self):
    n = 40
    cam = synthetic.front_camera(16, 16, focal=20.0)
    p = synthetic.random_params(n, degree=0, spread=0.3,
                                log_scale=(-2.5, -2.0))
    cfg = config.RenderConfig(tile_budget=8, chunk_size=8, tile_size=16)
    out, _ = self.check(p, jnp.ones(n, bool), cam=cam, cfg=cfg,
                        compare=False)
    # One 16x16 tile: every valid Gaussian beyond the 8 nearest is dropped.
    self.assertGreater(int(out.max_tile_count), 8)
    self.assertEqual(int(out.num_overflow), int(out.max_tile_count) - 8)
    # The kept ones are the 8 nearest, so the result equals the reference
    # render of those 8 alone.
    from clipgs_jax.render import project  # pylint: disable=g-import-not-at-top
    proj = project.project(p, jnp.ones(n, bool), cam, near=cfg.near,
                           sh_degree=0)
    depth = np.where(np.asarray(proj.valid), np.asarray(proj.depths), np.inf)
    nearest = np.zeros(n, bool)
    nearest[np.argsort(depth, kind="stable")[:8]] = True
    ref = rasterize_ref.render_ref(p, jnp.asarray(nearest), cam, BG)
    np.testing.assert_allclose(out.image, ref["image"], atol=1e-5)

  def test_no_alive_gaussian(self):
    out, grads = self.check(_scene(), jnp.zeros(4, bool))
    np.testing.assert_allclose(out.image, jnp.broadcast_to(BG, (29, 37, 3)))
    np.testing.assert_array_equal(out.alpha, 0.0)
    for field in FIELDS:
      np.testing.assert_array_equal(getattr(grads, field), 0.0)

  @parameterized.named_parameters(("17x33", 17, 33), ("31x5", 31, 5),
                                  ("1x1", 1, 1))
  def test_image_sizes(self, width, height):
    cam = synthetic.front_camera(width, height, focal=float(max(width, 8)))
    p = _set(_scene(), 3, means=[0.0, 0.0, 0.0], opacity_logits=2.0,
             log_scales=np.full(3, -0.5))
    out, _ = self.check(p, jnp.ones(4, bool), cam=cam)
    chex.assert_shape(out.image, (height, width, 3))
    self.assertTrue(bool(out.visible[3]))

  def test_float32_against_float64(self):
    p32 = synthetic.random_params(100, seed=7, degree=2)
    alive = jnp.ones(100, bool)
    out32, _ = _render_and_grads(p32, alive, synthetic.front_camera())
    with jax.enable_x64(True):
      p64 = jax.tree.map(lambda x: x.astype(jnp.float64), p32)
      cam64 = synthetic.front_camera(dtype=np.float64)
      out64 = jax.jit(lambda p: rasterize.render(
          p, alive, cam64, BG.astype(jnp.float64), CFG))(p64)
      self.assertEqual(out64.image.dtype, jnp.float64)
      err = float(jnp.max(jnp.abs(out32.image - out64.image)))
    print(f"float32 vs float64 max abs image error: {err:.3g}")
    self.assertLess(err, 1e-5)


if __name__ == "__main__":
  absltest.main()
