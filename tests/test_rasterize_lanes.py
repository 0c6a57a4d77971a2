"""The lane-scheduled blend: exact for any lane count, tile size and list."""

from absl.testing import parameterized
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config
from clipgs_jax.render import project
from clipgs_jax.render import rasterize
import rasterize_ref
import synthetic

BG = jnp.array([0.1, 0.2, 0.3])
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


class LaneTest(parameterized.TestCase):

  # An odd chunk leaves a remainder after the blend's two-entry unroll.
  @parameterized.named_parameters(
      ("one_lane", 1, 16, 8), ("three_lanes", 3, 16, 8),
      ("all_tiles", 64, 16, 8), ("tile8_auto", 0, 8, 8),
      ("odd_chunk", 3, 16, 5))
  def test_matches_reference_with_gradients(self, lanes, tile, chunk):
    cam = synthetic.front_camera(37, 29)
    params = synthetic.random_params(80, seed=2, degree=1)
    alive = jnp.ones(80, bool)
    cfg = config.RenderConfig(tile_budget=256, chunk_size=chunk, lanes=lanes,
                              tile_size=tile)
    emap = jnp.asarray(np.random.default_rng(0).uniform(size=(29, 37)),
                       jnp.float32)
    weights = jnp.asarray(np.random.default_rng(1).normal(size=(29, 37, 3)),
                          jnp.float32)

    def loss(p, render_fn):
      out = render_fn(p)
      return jnp.sum(out["image"] * weights) + jnp.sum(out["alpha"]), out

    def fast(p):
      out = rasterize.render(p, alive, cam, BG, cfg, evidence_map=emap)
      return dict(image=out.image, alpha=out.alpha, depth=out.depth,
                  contribution=out.contribution, evidence=out.evidence,
                  num_overflow=out.num_overflow)

    def ref(p):
      return rasterize_ref.render_ref(p, alive, cam, BG, evidence_map=emap)

    g_fast, out = jax.jit(jax.grad(lambda p: loss(p, fast), has_aux=True))(
        params)
    g_ref, out_ref = jax.grad(lambda p: loss(p, ref), has_aux=True)(params)
    self.assertEqual(int(out["num_overflow"]), 0)
    np.testing.assert_allclose(out["image"], out_ref["image"], atol=1e-5)
    np.testing.assert_allclose(out["alpha"], out_ref["alpha"], atol=1e-5)
    np.testing.assert_allclose(out["depth"], out_ref["depth"], rtol=1e-5,
                               atol=1e-4)
    for key in ("contribution", "evidence"):
      np.testing.assert_allclose(out[key], out_ref[key], rtol=1e-4, atol=1e-4,
                                 err_msg=key)
    for field in FIELDS:
      r = getattr(g_ref, field)
      np.testing.assert_allclose(getattr(g_fast, field), r, rtol=1e-3,
                                 atol=1e-3 * float(jnp.max(jnp.abs(r))),
                                 err_msg=field)

  def test_one_tile_longer_than_budget_is_exact(self):
    # Three tiles, buffer 3 x 16 = 48 entries: all 30 Gaussians sit in the
    # middle tile, so its list (30) is past K = 16 but the view fits.
    n = 30
    cam = synthetic.front_camera(48, 16, focal=20.0)
    p = synthetic.random_params(n, degree=0, spread=0.05,
                                log_scale=(-3.0, -2.5))
    alive = jnp.ones(n, bool)
    cfg = config.RenderConfig(tile_budget=16, chunk_size=8)
    out = jax.jit(lambda q: rasterize.render(q, alive, cam, BG, cfg))(p)
    ref = rasterize_ref.render_ref(p, alive, cam, BG)
    self.assertGreater(int(out.max_tile_count), 16)
    self.assertEqual(int(out.num_overflow), 0)
    np.testing.assert_allclose(out.image, ref["image"], atol=1e-5)

  def test_bad_tile_size(self):
    params = synthetic.random_params(5)
    with self.assertRaisesRegex(ValueError, "tile_size"):
      rasterize.render(params, jnp.ones(5, bool), synthetic.front_camera(),
                       BG, config.RenderConfig(tile_size=0))

  def test_blend_stats(self):
    cam = synthetic.front_camera(37, 29)
    params = synthetic.random_params(60, seed=4, degree=0)
    alive = jnp.ones(60, bool)
    cfg = config.RenderConfig(tile_budget=64, chunk_size=8, lanes=2,
                              tile_size=16)
    proj = project.project(params, alive, cam, near=cfg.near, sh_degree=0)
    stats = rasterize.blend_stats(proj, cam, cfg)
    self.assertEqual(stats["lanes"], 2)
    self.assertEqual(stats["num_tiles"], 6)
    for key in ("efficiency_fwd", "efficiency_bwd", "lockstep_efficiency_fwd"):
      self.assertGreater(stats[key], 0.0, key)
      self.assertLessEqual(stats[key], 1.0, key)
    self.assertLessEqual(stats["nonzero_alpha_share_fwd"],
                         stats["efficiency_fwd"])
    # The tile that needs the most chunks bounds the rounds from below.
    self.assertGreaterEqual(stats["rounds_fwd"], stats["lockstep_rounds"])
