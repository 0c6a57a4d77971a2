"""The residual map: running quantile, neighbourhood rules, warm-up, sources."""

import dataclasses

from absl.testing import absltest
from absl.testing import parameterized
import chex
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config_file
from clipgs_jax import guidance
from clipgs_jax import guidance_config
from clipgs_jax import step as step_lib
from clipgs_jax import train
from clipgs_jax.maps import residual
from clipgs_jax.maps import sources
from test_checkpoint import _assert_states_equal  # pylint: disable=g-bad-import-order
from test_train import synthetic_scene  # pylint: disable=g-bad-import-order


class QuantileTest(parameterized.TestCase):

  @parameterized.parameters(0.5, 0.7, 0.9)
  def test_threshold_is_the_quantile(self, q):
    res = np.random.default_rng(0).uniform(0, 0.5, size=(40, 30))
    state = residual.update(residual.ResidualState.initial(),
                            jnp.asarray(res, jnp.float32), quantile=q,
                            decay=0.95)
    # The threshold is a bin edge: within one bin of numpy's quantile.
    self.assertAlmostEqual(float(state.threshold), np.quantile(res, q),
                           delta=2.0 / residual.HISTOGRAM_BINS)
    self.assertEqual(float(jnp.sum(state.histogram)), res.size)

  def test_decay_weights_the_past(self):
    low = jnp.full((10, 10), 0.1)
    high = jnp.full((10, 10), 0.9)
    state = residual.ResidualState.initial()
    for _ in range(20):
      state = residual.update(state, low, quantile=0.7, decay=0.5)
    # One step of high residuals against a decayed past of 1.0 x 100
    # (sum of 0.5^k) low ones: 100 high vs ~100 low, the quantile is high.
    after = residual.update(state, high, quantile=0.7, decay=0.5)
    self.assertAlmostEqual(float(after.threshold), 0.9, delta=1e-3)
    # With decay 0 only the last step counts.
    fresh = residual.update(state, low, quantile=0.7, decay=0.0)
    self.assertAlmostEqual(float(fresh.threshold), 0.1, delta=1e-3)
    np.testing.assert_array_equal(np.nonzero(np.asarray(fresh.histogram))[0],
                                  [1000])

  def test_median_floor(self):
    # Residuals 0.01..0.10 evenly: the 0.7 quantile is ~0.07, the median
    # ~0.05; a floor of 3 x median lifts the threshold to ~0.15.
    res = jnp.asarray(np.linspace(0.01, 0.10, 100).reshape(10, 10),
                      jnp.float32)
    plain = residual.update(residual.ResidualState.initial(), res,
                            quantile=0.7, decay=0.9)
    floored = residual.update(residual.ResidualState.initial(), res,
                              quantile=0.7, decay=0.9, median_factor=3.0)
    self.assertAlmostEqual(float(plain.threshold), 0.073, delta=2e-3)
    self.assertAlmostEqual(float(floored.threshold), 3 * 0.055, delta=5e-3)
    # A floor under the quantile changes nothing.
    low = residual.update(residual.ResidualState.initial(), res,
                          quantile=0.7, decay=0.9, median_factor=1.0)
    self.assertEqual(float(low.threshold), float(plain.threshold))

  def test_absolute_floor(self):
    res = jnp.asarray(np.linspace(0.01, 0.10, 100).reshape(10, 10),
                      jnp.float32)
    floored = residual.update(residual.ResidualState.initial(), res,
                              quantile=0.7, decay=0.9, minimum=0.25)
    self.assertAlmostEqual(float(floored.threshold), 0.25, delta=1e-6)
    under = residual.update(residual.ResidualState.initial(), res,
                            quantile=0.7, decay=0.9, minimum=0.01)
    self.assertAlmostEqual(float(under.threshold), 0.073, delta=2e-3)

  def test_initial_threshold_keeps_every_pixel(self):
    state = residual.ResidualState.initial()
    res = jnp.full((8, 8), 0.99)
    np.testing.assert_array_equal(
        residual.inliers(res, state.threshold, "sls"), 1.0)

  def test_extreme_residuals_stay_finite(self):
    state = residual.ResidualState.initial()
    res = jnp.array([[0.0, 1.0], [5.0, -1.0]])   # outside [0, 1]: clipped
    state = residual.update(state, res, quantile=0.7, decay=0.95)
    chex.assert_tree_all_finite(state)
    self.assertEqual(float(jnp.sum(state.histogram)), 4.0)


class RuleTest(absltest.TestCase):

  def test_sls_isolated_outlier_is_rescued_by_neighbours(self):
    res = np.zeros((7, 7), np.float32)
    res[3, 3] = 1.0                           # one outlier, 8 inliers around
    res[0:3, 0:3] = 1.0                       # a 3x3 block of outliers
    inl = np.asarray(residual.inliers(jnp.asarray(res), 0.5, "sls"))
    self.assertEqual(inl[3, 3], 1.0)
    # The block's centre has no inlier neighbour: it stays an outlier; its
    # corner pixel at (0, 0) sees 0 of 9 inliers (zero padding).
    self.assertEqual(inl[1, 1], 0.0)
    self.assertEqual(inl[0, 0], 0.0)
    # (2, 2) sees 4 inliers of 9 (its block, and (3, 3)): not rescued.
    self.assertEqual(inl[2, 2], 0.0)
    # (3, 3)'s rescue needs more than half: 8 of 9 around it are inliers.
    res[4, 4] = res[4, 3] = res[3, 4] = res[2, 4] = 1.0
    inl = np.asarray(residual.inliers(jnp.asarray(res), 0.5, "sls"))
    self.assertEqual(inl[3, 3], 0.0)

  def test_robustnerf_blocks_take_the_window_verdict(self):
    res = np.zeros((32, 32), np.float32)
    res[8:16, 8:16] = 1.0                # one 8x8 block of outliers
    inl = np.asarray(residual.inliers(jnp.asarray(res), 0.5, "robustnerf"))
    # The block's 16x16 window holds 64 - (box-filter erosion) outliers of
    # 256 pixels: well under 40 %, so the whole block is an inlier.
    np.testing.assert_array_equal(inl, 1.0)
    res[4:20, 4:20] = 1.0                # a 16x16 region of outliers
    inl = np.asarray(residual.inliers(jnp.asarray(res), 0.5, "robustnerf"))
    np.testing.assert_array_equal(inl[8:16, 8:16], 0.0)
    self.assertEqual(inl[28, 28], 1.0)

  def test_robustnerf_odd_sizes(self):
    res = jnp.zeros((13, 21))
    inl = residual.inliers(res, 0.5, "robustnerf")
    self.assertEqual(inl.shape, (13, 21))
    np.testing.assert_array_equal(inl, 1.0)

  def test_unknown_rule(self):
    with self.assertRaisesRegex(ValueError, "not one of sls, robustnerf"):
      residual.inliers(jnp.zeros((4, 4)), 0.5, "median")


class WarmupTest(absltest.TestCase):

  def test_share_closed_form(self):
    # a = exp(-3e-3 floor((s + 1) / 1.5)): s = 0 -> 1; s = 999 -> exp(-2).
    self.assertAlmostEqual(float(residual.warmup_share(jnp.int32(0), 3e-3)),
                           1.0)
    self.assertAlmostEqual(
        float(residual.warmup_share(jnp.int32(999), 3e-3)),
        np.exp(-3e-3 * np.floor(1000 / 1.5)), places=6)

  def test_sampling(self):
    inlier = jnp.asarray(np.random.default_rng(1).uniform(size=(64, 64))
                         > 0.5, jnp.float32)
    key = jax.random.key(0)
    # No warm-up: the map itself.
    np.testing.assert_array_equal(
        residual.sample_inliers(inlier, jnp.int32(10), key, 0.0), inlier)
    # At step 0 every pixel is kept; late, only the inliers.
    np.testing.assert_array_equal(
        residual.sample_inliers(inlier, jnp.int32(0), key, 3e-3), 1.0)
    late = residual.sample_inliers(inlier, jnp.int32(100_000), key, 3e-3)
    np.testing.assert_array_equal(late, inlier)
    # Inliers are always kept.
    mid = residual.sample_inliers(inlier, jnp.int32(300), key, 3e-3)
    self.assertTrue(bool(jnp.all(mid >= inlier)))
    share = float(jnp.sum(mid - inlier) / jnp.sum(1 - inlier))
    self.assertAlmostEqual(share, float(residual.warmup_share(
        jnp.int32(300), 3e-3)), delta=0.05)


class SourceTest(absltest.TestCase):

  def _rc(self, **kw):
    kw = {"min_alpha": 0.0, **kw}   # no render alpha here
    return guidance_config.ResidualConfig(warmup=0.0, **kw)

  def test_residual_map_and_gate(self):
    photo = jnp.zeros((16, 16, 3))
    render = photo.at[4:12, 4:12].set(1.0)       # an 8x8 miss
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.5))
    view = jnp.int32(0)
    plain = sources.residual_map(
        sources.ResidualSource(), stats, view, render, photo,
        jnp.int32(5), jax.random.key(0), self._rc())
    np.testing.assert_array_equal(plain.transient[5:11, 5:11], 1.0)
    self.assertEqual(float(jnp.sum(plain.transient[:3])), 0.0)
    np.testing.assert_array_equal(plain.loss_weight, 1.0 - plain.transient)
    # The gate keeps the residual test only where p(transient) > 0.5.
    semantic = jnp.zeros((1, 16, 16)).at[0, :, :8].set(0.9)
    gated = sources.residual_map(
        sources.ResidualSource(semantic=semantic), stats, view, render,
        photo, jnp.int32(5), jax.random.key(0), self._rc())
    np.testing.assert_array_equal(gated.transient[:, 8:], 0.0)
    np.testing.assert_array_equal(gated.transient[:, :8],
                                  plain.transient[:, :8])

  def test_a_map_under_the_share_floor_is_empty(self):
    photo = jnp.zeros((20, 20, 3))
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.5))
    rc = self._rc(min_share=0.05)   # 20 of 400 pixels
    for size, kept in ((4, False), (6, True)):
      render = photo.at[:size, :size].set(1.0)
      rmap = sources.residual_map(
          sources.ResidualSource(), stats, jnp.int32(0), render, photo,
          jnp.int32(5), jax.random.key(0), self._rc())
      self.assertEqual(float(jnp.sum(rmap.transient)) >= 20, kept)
      floored = sources.residual_map(
          sources.ResidualSource(), stats, jnp.int32(0), render, photo,
          jnp.int32(5), jax.random.key(0), rc)
      np.testing.assert_array_equal(floored.transient,
                                    rmap.transient if kept else 0.0)
      np.testing.assert_array_equal(floored.loss_weight,
                                    rmap.loss_weight if kept else 1.0)
      stages = sources.residual_stages(
          sources.ResidualSource(), stats, jnp.int32(0), render,
          jnp.ones((20, 20)), photo, rc)
      np.testing.assert_array_equal(stages["share"], floored.transient)
    # On a larger canvas the share counts the photo's pixels only: the
    # 4x4 miss is under 5 % of the canvas, over 5 % of a 10x10 photo.
    valid = jnp.zeros((20, 20)).at[:10, :10].set(1.0)
    floored = sources.residual_map(
        sources.ResidualSource(), stats, jnp.int32(0),
        photo.at[:4, :4].set(1.0), photo, jnp.int32(5), jax.random.key(0),
        rc, valid=valid)
    self.assertGreater(float(jnp.sum(floored.transient)), 5.0)

  def test_start_leaves_the_map_empty_before_it(self):
    photo = jnp.zeros((16, 16, 3))
    render = photo.at[4:12, 4:12].set(1.0)       # an 8x8 miss
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.5))
    rc = self._rc(start=100)
    rmap = sources.residual_map(
        sources.ResidualSource(), stats, jnp.int32(0), render, photo,
        jnp.int32(99), jax.random.key(0), rc)
    maps = [sources.held_back(rmap, sources.ResidualSource(),
                              jnp.int32(0), jnp.int32(step), rc)
            for step in (99, 100)]
    np.testing.assert_array_equal(maps[0].transient, 0.0)
    np.testing.assert_array_equal(maps[0].loss_weight, 1.0)
    np.testing.assert_array_equal(maps[1].transient[5:11, 5:11], 1.0)
    np.testing.assert_array_equal(maps[1].loss_weight,
                                  1.0 - maps[1].transient)

  def test_uneven_regions_wait_until_the_uniformity_gate_ends(self):
    photo = jnp.zeros((16, 16, 3))
    # Region 0 (left) misses evenly; region 1 (right) misses by 0.6 to 1.0
    # in stripes, std / mean 0.25; both fail the test whole.
    render = photo.at[:, :8].set(0.8).at[:, 8:].set(1.0).at[::2, 8:].set(0.6)
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.5))
    source = sources.ResidualSource(
        labels=jnp.zeros((1, 16, 16), jnp.int32).at[0, :, 8:].set(1),
        num_regions=2)
    rc = self._rc(uniformity=0.2, uniform_until=100)
    rmap = sources.residual_map(source, stats, jnp.int32(0), render,
                                photo, jnp.int32(99), jax.random.key(0),
                                rc)
    np.testing.assert_array_equal(rmap.transient, 1.0)
    early, late = [sources.held_back(rmap, source, jnp.int32(0),
                                     jnp.int32(step), rc)
                   for step in (99, 100)]
    np.testing.assert_array_equal(early.transient[:, :8], 1.0)
    np.testing.assert_array_equal(early.transient[:, 8:], 0.0)
    np.testing.assert_array_equal(early.loss_weight, 1.0 - early.transient)
    np.testing.assert_array_equal(late.transient, rmap.transient)
    np.testing.assert_array_equal(late.loss_weight, rmap.loss_weight)
    # A looser gate passes the striped region too; without regions (the
    # per-pixel map) there is nothing to gate.
    loose = sources.held_back(
        rmap, source, jnp.int32(0), jnp.int32(99),
        self._rc(uniformity=0.3, uniform_until=100))
    np.testing.assert_array_equal(loose.transient, 1.0)
    per_pixel = sources.held_back(rmap, sources.ResidualSource(),
                                  jnp.int32(0), jnp.int32(99), rc)
    self.assertIs(per_pixel, rmap)

  def test_alpha_gate_keeps_transients_only_on_rendered_surface(self):
    photo = jnp.zeros((16, 16, 3))
    render = photo.at[4:12, 4:12].set(1.0)       # an 8x8 miss
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.5))
    alpha = jnp.ones((16, 16)).at[:, 8:].set(0.3)  # no surface on the right
    args = (sources.ResidualSource(), stats, jnp.int32(0), render, photo,
            jnp.int32(5), jax.random.key(0))
    plain = sources.residual_map(*args, self._rc(), alpha=alpha)
    gated = sources.residual_map(
        *args, self._rc(min_alpha=0.5), alpha=alpha)
    np.testing.assert_array_equal(gated.transient[:, :8],
                                  plain.transient[:, :8])
    np.testing.assert_array_equal(gated.transient[:, 8:], 0.0)
    self.assertGreater(float(jnp.sum(plain.transient[:, 8:])), 0.0)
    # The unmasked pixels are trained: the loss weight follows the map.
    np.testing.assert_array_equal(gated.loss_weight, 1.0 - gated.transient)
    with self.assertRaisesRegex(ValueError, "needs the render's alpha"):
      sources.residual_map(*args, self._rc(min_alpha=0.5))

  def test_alpha_gate_follows_feature_regions(self):
    photo = jnp.zeros((16, 16, 3))
    render = photo + 1.0                           # every pixel fails
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.5))
    labels = jnp.zeros((1, 16, 16), jnp.int32).at[0, :, 8:].set(1)
    # Region 0 is mostly rendered surface, region 1 mostly empty.
    alpha = (jnp.ones((16, 16)).at[:, :2].set(0.3)
             .at[:, 8:14].set(0.3))
    args = (stats, jnp.int32(0), render, photo, jnp.int32(5),
            jax.random.key(0))
    rc = self._rc(min_alpha=0.5)
    pixels = sources.residual_map(
        sources.ResidualSource(), *args, rc, alpha=alpha)
    np.testing.assert_array_equal(pixels.transient, alpha > 0.5)
    regions = sources.residual_map(
        sources.ResidualSource(labels=labels, num_regions=2), *args,
        rc, alpha=alpha)
    # Each region gets its majority's verdict, its empty pixels and its
    # rendered ones alike.
    np.testing.assert_array_equal(regions.transient[:, :8], 1.0)
    np.testing.assert_array_equal(regions.transient[:, 8:], 0.0)
    np.testing.assert_array_equal(regions.loss_weight,
                                  1.0 - regions.transient)

  def test_vote_fraction_decides_a_region(self):
    photo = jnp.zeros((16, 16, 3))
    render = photo.at[:10].set(1.0)        # rows 0-9 miss
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.5))
    source = sources.ResidualSource(
        labels=jnp.zeros((1, 16, 16), jnp.int32).at[0, :, 8:].set(1)
        .at[0, 12:].set(1), num_regions=2)
    # After the 3x3 rule region 0 (left, rows 0-11) fails the test on 80
    # of its 96 pixels, region 1 (the rest) on 80 of its 160.
    maps = {v: sources.residual_map(
        source, stats, jnp.int32(0), render, photo, jnp.int32(5),
        jax.random.key(0), self._rc(vote=v)).transient
            for v in (0.5, 0.7, 0.9)}
    left, right = (0, 0), (0, 15)
    self.assertEqual([float(maps[v][left]) for v in (0.5, 0.7, 0.9)],
                     [1.0, 1.0, 0.0])
    self.assertEqual([float(maps[v][right]) for v in (0.5, 0.7, 0.9)],
                     [1.0, 0.0, 0.0])

  def test_stages_end_in_the_map(self):
    photo = jnp.zeros((16, 16, 3))
    render = photo.at[2:14, 2:14].set(1.0).at[6:10, 6:10].set(0.2)
    stats = residual.ResidualState.initial().replace(
        threshold=jnp.float32(0.5))
    source = sources.ResidualSource(
        semantic=jnp.zeros((1, 16, 16)).at[0, :, :12].set(0.9),
        labels=jnp.zeros((1, 16, 16), jnp.int32).at[0, 8:].set(1),
        num_regions=2)
    alpha = jnp.ones((16, 16)).at[:, :3].set(0.3)
    rc = self._rc(min_alpha=0.5)
    stages = sources.residual_stages(source, stats, jnp.int32(0),
                                     render, alpha, photo, rc)
    self.assertEqual(list(stages), ["threshold", "rule", "vote",
                                    "semantic", "alpha", "share"])
    self.assertEqual(tuple(k for k in sources.STAGES if k in stages),
                     tuple(stages))
    # The low residual in the middle fails the threshold; the 3x3 rule
    # calls its interior static.
    np.testing.assert_array_equal(stages["threshold"][6:10, 6:10], 0.0)
    np.testing.assert_array_equal(stages["rule"][7:9, 7:9], 0.0)
    transient = sources.residual_map(
        source, stats, jnp.int32(0), render, photo, jnp.int32(5),
        jax.random.key(0), rc, alpha=alpha).transient
    np.testing.assert_array_equal(stages["share"], transient)
    np.testing.assert_array_equal(stages["semantic"][:, 12:], 0.0)

  def test_memory_holds_what_the_map_marked(self):
    photo = jnp.zeros((8, 8, 3))
    stats = residual.ResidualState.initial(memory_shape=(2, 8, 8)).replace(
        threshold=jnp.float32(0.5))
    rc = self._rc(remember=True, uniform_until=5)
    source = sources.ResidualSource()
    miss = photo.at[:4, :4].set(1.0)       # a 4x4 transient at first

    def visit(render, memory, step):
      rmap = sources.residual_map(source, stats, jnp.int32(1), render,
                                  photo, jnp.int32(step), jax.random.key(0),
                                  rc)
      return sources.remember(rmap, memory, jnp.int32(step), rc)

    # Before uniform_until the map is used, not remembered.
    early, memory = visit(miss, stats.memory[1], 4)
    self.assertEqual(float(early.transient[0, 0]), 1.0)
    self.assertEqual(memory.dtype, jnp.bool_)
    np.testing.assert_array_equal(memory, False)
    first, memory = visit(miss, memory, 5)
    np.testing.assert_array_equal(memory, first.transient > 0)
    # The model then fits the miss: the test passes it, the memory holds it
    # out of the loss.
    for step in (6, 7):
      later, memory = visit(photo, memory, step)
      np.testing.assert_array_equal(later.transient, first.transient)
      np.testing.assert_array_equal(later.loss_weight,
                                    1.0 - first.transient)
    np.testing.assert_array_equal(memory, first.transient > 0)
    # The evaluation map and the stages read the memory as the step does.
    held = stats.replace(memory=stats.memory.at[1].set(memory))
    m = sources.view_map(source, held, jnp.int32(1), photo, jnp.ones((8, 8)),
                         photo, rc)
    np.testing.assert_array_equal(m, first.transient)
    stages = sources.residual_stages(source, held, jnp.int32(1), photo,
                                     jnp.ones((8, 8)), photo, rc)
    self.assertEqual(list(sources.in_stage_order(stages))[-1], "memory")
    np.testing.assert_array_equal(stages["memory"], m)
    np.testing.assert_array_equal(stages["share"], 0.0)

  def test_oracle_patch_pools_to_the_grid(self):
    masks = np.zeros((2, 28, 42), bool)
    masks[0, :14, :21] = True         # one quadrant: 7 x 7 cells of 14 x 14
    maps = np.asarray(sources.oracle_patch_maps(masks, 14))
    self.assertEqual(maps.shape, (2, 28, 42))
    self.assertAlmostEqual(maps[0, 2, 2], 1.0, places=5)
    self.assertAlmostEqual(maps[0, 25, 38], 0.0, places=5)
    np.testing.assert_allclose(maps[1], 0.0, atol=1e-6)
    # Pooling keeps the transient area (bilinear upsampling, half-pixel
    # centres, spreads it a little at the edge).
    self.assertAlmostEqual(maps[0].mean(), masks[0].mean(), delta=0.02)



def _memory_config(steps: int, batch: int = 1):
  """The smoke preset with the residual map, its memory on and no gate
  that needs a fitted model."""
  cfg = config_file.named("smoke")
  return dataclasses.replace(
      cfg,
      semantic=dataclasses.replace(cfg.semantic, scorer="residual",
                                   evidence="pixel", accumulate_start=0,
                                   reg_start=10, prune_start=1000),
      pixel=guidance_config.PixelConfig(loss_masking=True),
      residual=dataclasses.replace(cfg.residual, min_threshold=0.0,
                                   min_alpha=0.0, min_share=0.0,
                                   uniform_until=0, remember=True),
      train=dataclasses.replace(cfg.train, steps=steps, batch_size=batch,
                                eval_every=0, log_every=10,
                                checkpoint_every=0))


class MemoryRunTest(absltest.TestCase):

  def test_a_step_writes_its_views_memory(self):
    # Threshold 0: every pixel of the step's two views is transient, so
    # their rows (the metric "view") are marked, no other.
    scene = synthetic_scene()
    cfg = train.resolve(_memory_config(1, batch=2), scene)
    state = train.initial_state(cfg, scene)
    num_views, size = scene.train.images.shape[:2]
    self.assertEqual(state.maps.memory.shape, (num_views, size, size))
    state = state.replace(maps=state.maps.replace(threshold=jnp.float32(0)))
    step, lanes, state, scorer = step_lib.for_scene(
        cfg, scene, state, guidance.make_scorer(cfg, scene))
    state, metrics = step(state, lanes, scorer)
    views = sorted(int(v) for v in metrics["view"])
    memory = np.asarray(state.maps.memory)
    for v in range(num_views):
      np.testing.assert_array_equal(memory[v], v in views,
                                    err_msg=f"view {v} (stepped: {views})")

  def test_without_the_memory_size_init_refuses(self):
    scene = synthetic_scene()
    cfg = train.resolve(_memory_config(1), scene)
    plain = train.initial_state(dataclasses.replace(
        cfg, residual=dataclasses.replace(cfg.residual, remember=False)),
        scene)
    self.assertIsNone(plain.maps.memory)
    with self.assertRaisesRegex(ValueError, "residual.remember=True"):
      train.init_state(cfg, plain.params, plain.alive)

  def test_resume_is_bit_identical(self):
    scene = synthetic_scene()
    cfg = train.resolve(_memory_config(20), scene)
    scorer = guidance.make_scorer(cfg, scene)
    fit = lambda workdir, **kw: train.fit(cfg, scene, workdir,
                                          scorer=scorer, progress=False,
                                          **kw)
    straight = fit(self.create_tempdir().full_path)
    workdir = self.create_tempdir().full_path
    fit(workdir, stop_after=10)
    resumed = fit(workdir, resume=True)
    _assert_states_equal(resumed.state, straight.state)
    self.assertTrue(np.any(straight.state.maps.memory))


if __name__ == "__main__":
  absltest.main()
