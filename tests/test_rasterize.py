"""Tile rasterizer against the dense reference: values and gradients."""

from absl.testing import parameterized
import chex
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config
from clipgs_jax.render import project
from clipgs_jax.render import rasterize
import rasterize_ref
import synthetic

# Small budget/chunk keep compile times low; no test scene overflows them
# unless it says so.
CFG = config.RenderConfig(tile_budget=256, chunk_size=8)
BG = jnp.array([0.1, 0.2, 0.3])
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


def _loss_weights(h, w, seed=1):
  rng = np.random.default_rng(seed)
  return (jnp.asarray(rng.normal(size=(h, w, 3)), jnp.float32),
          jnp.asarray(rng.normal(size=(h, w)), jnp.float32),
          jnp.asarray(rng.normal(size=(h, w)), jnp.float32))


def _scalarize(image, alpha, depth, weights):
  wi, wa, wd = weights
  return (jnp.sum(image * wi) + jnp.sum(alpha * wa)
          + 0.1 * jnp.sum(depth * wd))


class ForwardTest(parameterized.TestCase):

  @parameterized.named_parameters(
      ("odd_size_deg0", (37, 29), 0, 0), ("one_tile_deg3", (16, 16), 3, 1),
      ("wide_deg1", (48, 20), 1, 2), ("odd_size_deg2", (37, 29), 2, 3))
  def test_matches_reference(self, size, degree, seed):
    cam = synthetic.front_camera(*size)
    params = synthetic.random_params(120, seed=seed, degree=degree)
    alive = jnp.asarray(np.random.default_rng(seed).uniform(size=120) < 0.9)
    out = jax.jit(lambda p, a: rasterize.render(p, a, cam, BG, CFG))(
        params, alive)
    ref = rasterize_ref.render_ref(params, alive, cam, BG)
    self.assertEqual(int(out.num_overflow), 0)
    chex.assert_shape(out.image, (size[1], size[0], 3))
    np.testing.assert_allclose(out.image, ref["image"], atol=1e-5)
    np.testing.assert_allclose(out.alpha, ref["alpha"], atol=1e-5)
    np.testing.assert_allclose(out.depth, ref["depth"], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(out.contribution, ref["contribution"],
                               rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(out.visible, ref["contribution"] > 0)

  def test_visibility_ignores_dead_and_offscreen(self):
    cam = synthetic.front_camera()
    params = synthetic.random_params(3, degree=0)
    # Slot 0 on screen, slot 1 far off screen, slot 2 dead.
    params = synthetic.with_rows(
        params, means=[[0, 0, 0], [50, 0, 0], [0, 0, 0]],
        log_scales=np.full((3, 3), -2.0), opacity_logits=[2.0, 2.0, 2.0])
    out = rasterize.render(params, jnp.array([True, True, False]), cam, BG,
                           CFG)
    np.testing.assert_array_equal(out.visible, [True, False, False])
    self.assertGreater(float(out.contribution[0]), 0.0)


class GradientTest(parameterized.TestCase):

  @parameterized.named_parameters(
      ("odd_size_deg1", (37, 29), 1, 0), ("one_tile_deg3", (16, 16), 3, 1),
      ("wide_deg2", (48, 20), 2, 2))
  def test_custom_vjp_matches_reference_autodiff(self, size, degree, seed):
    cam = synthetic.front_camera(*size)
    params = synthetic.random_params(80, seed=seed, degree=degree)
    alive = jnp.asarray(np.random.default_rng(seed).uniform(size=80) < 0.9)
    weights = _loss_weights(size[1], size[0], seed)

    def loss_fast(p, bg):
      out = rasterize.render(p, alive, cam, bg, CFG)
      return _scalarize(out.image, out.alpha, out.depth, weights)

    def loss_ref(p, bg):
      out = rasterize_ref.render_ref(p, alive, cam, bg)
      return _scalarize(out["image"], out["alpha"], out["depth"], weights)

    g_fast = jax.jit(jax.grad(loss_fast, argnums=(0, 1)))(params, BG)
    g_ref = jax.grad(loss_ref, argnums=(0, 1))(params, BG)
    for field in FIELDS:
      ref = getattr(g_ref[0], field)
      # rtol 1e-3 relative to the field's gradient scale.
      atol = 1e-3 * float(jnp.max(jnp.abs(ref)))
      np.testing.assert_allclose(getattr(g_fast[0], field), ref, rtol=1e-3,
                                 atol=atol, err_msg=field)
    np.testing.assert_allclose(g_fast[1], g_ref[1], rtol=1e-3)

  def test_custom_vjp_matches_autodiff_of_same_forward(self):
    cam = synthetic.front_camera(40, 24)
    params = synthetic.random_params(60, seed=3, degree=1)
    alive = jnp.ones(60, bool)
    weights = _loss_weights(24, 40)

    # A short budget keeps the unrolled autodiff scan small to compile.
    cfg = config.RenderConfig(tile_budget=64, chunk_size=8)

    def loss(p, custom):
      proj = project.project(p, alive, cam, near=cfg.near, sh_degree=1)
      out = rasterize.rasterize(proj, cam, BG, cfg, custom_vjp=custom)
      return _scalarize(out.image, out.alpha, out.depth, weights)

    g_custom = jax.jit(jax.grad(lambda p: loss(p, True)))(params)
    g_auto = jax.jit(jax.grad(lambda p: loss(p, False)))(params)
    for field in FIELDS:
      ref = getattr(g_auto, field)
      np.testing.assert_allclose(
          getattr(g_custom, field), ref, rtol=1e-4,
          atol=1e-4 * float(jnp.max(jnp.abs(ref))), err_msg=field)

  def test_check_grads_float64(self):
    with jax.enable_x64(True):
      cam = synthetic.front_camera(20, 18, dtype=np.float64)
      params = synthetic.random_params(4, seed=5, degree=1,
                                       dtype=jnp.float64,
                                       log_scale=(-1.5, -1.0), spread=0.4)
      alive = jnp.ones(4, bool)
      weights = tuple(w.astype(jnp.float64) for w in _loss_weights(18, 20))

      def loss(means, log_scales, quats, opacity_logits, sh_dc, sh_rest, bg):
        p = params.replace(means=means, log_scales=log_scales, quats=quats,
                           opacity_logits=opacity_logits, sh_dc=sh_dc,
                           sh_rest=sh_rest)
        out = rasterize.render(p, alive, cam, bg, CFG)
        return _scalarize(out.image, out.alpha, out.depth, weights)

      args = tuple(getattr(params, f) for f in FIELDS) + (
          jnp.array([0.1, 0.2, 0.3], jnp.float64),)
      jax.test_util.check_grads(jax.jit(loss), args, order=1, modes=["rev"],
                                eps=1e-6, atol=1e-4, rtol=1e-4)


class RetraceAndMemoryTest(parameterized.TestCase):

  def test_alive_changes_do_not_retrace(self):
    cam = synthetic.front_camera()
    params = synthetic.random_params(50, degree=1)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(p, alive):
      return jax.grad(
          lambda q: jnp.sum(rasterize.render(q, alive, cam, BG, CFG).image))(p)

    rng = np.random.default_rng(0)
    for fraction in (1.0, 0.5, 0.1, 0.0, 0.7):
      alive = jnp.asarray(rng.uniform(size=50) < fraction)
      jax.block_until_ready(step(params, alive))

  def test_peak_memory_does_not_scale_with_pixels_times_n(self):
    cam = synthetic.front_camera(64, 64, focal=60.0)
    cfg = config.RenderConfig(tile_budget=1024, chunk_size=8)

    def temp_bytes(n):
      params = synthetic.random_params(n, degree=0)
      alive = jnp.ones(n, bool)
      grad = jax.jit(jax.grad(lambda p: jnp.sum(
          rasterize.render(p, alive, cam, BG, cfg).image)))
      return grad.lower(params).compile().memory_analysis().temp_size_in_bytes

    small, large = temp_bytes(1000), temp_bytes(8000)
    # Per-Gaussian state is ~100s of bytes; a [pixels, N] float tensor would
    # add 4096 * 7000 * 4 = 115 MB.
    self.assertLess(large - small, 7000 * 2000)


class BadInputTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    self.cam = synthetic.front_camera()
    self.params = synthetic.random_params(5)
    self.alive = jnp.ones(5, bool)

  def test_wrong_param_shape(self):
    bad = self.params.replace(means=jnp.zeros((5, 2)))
    with self.assertRaisesRegex(ValueError, r"params.means has shape"):
      rasterize.render(bad, self.alive, self.cam, BG)

  def test_wrong_alive_dtype(self):
    with self.assertRaisesRegex(ValueError, r"alive must be bool \[5\]"):
      rasterize.render(self.params, jnp.ones(5), self.cam, BG)

  def test_integer_params(self):
    bad = self.params.replace(opacity_logits=jnp.zeros(5, jnp.int32))
    with self.assertRaisesRegex(ValueError, "floating point"):
      rasterize.render(bad, self.alive, self.cam, BG)

  def test_background_shape(self):
    with self.assertRaisesRegex(ValueError, "background"):
      rasterize.render(self.params, self.alive, self.cam, jnp.zeros(4))

  @parameterized.named_parameters(
      ("nan_rotation", dict(rotation=np.full((3, 3), np.nan)), "non-finite"),
      ("inf_translation", dict(translation=[0, np.inf, 0]), "non-finite"),
      ("zero_focal", dict(fx=0.0), "fx must be positive"),
      ("negative_focal", dict(fy=-3.0), "fy must be positive"),
      ("zero_width", dict(width=0), "image size"),
      ("negative_height", dict(height=-2), "image size"),
      ("not_rotation", dict(rotation=np.eye(3) * 2), "not a rotation"))
  def test_bad_camera(self, change, message):
    fields = dict(rotation=np.eye(3), translation=np.zeros(3), fx=10.0,
                  fy=10.0, cx=5.0, cy=5.0, width=10, height=10)
    fields.update(change)
    with self.assertRaisesRegex(ValueError, message):
      synthetic.camera.Camera.create(**fields)
    # A camera built around the validator is still caught at render time.
    cam = synthetic.camera.Camera(**{
        k: (np.asarray(v, np.float32) if k not in ("width", "height") else v)
        for k, v in fields.items()})
    with self.assertRaisesRegex(ValueError, message):
      rasterize.render(self.params, self.alive, cam, BG)
