"""Tests for learned: the learned map's classifier, labels and features."""

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from clipgs_jax import config
from clipgs_jax import config_file
from clipgs_jax import guidance
from clipgs_jax import guidance_config
from clipgs_jax import train
from clipgs_jax.maps import features
from clipgs_jax.maps import learned
from clipgs_jax.maps import residual
from clipgs_jax.maps import sources
from test_checkpoint import _assert_states_equal  # pylint: disable=g-bad-import-order
from test_train import synthetic_scene  # pylint: disable=g-bad-import-order

LC = guidance_config.LearnedConfig()
RC = guidance_config.ResidualConfig()


def _stats(residuals) -> residual.ResidualState:
  """Statistics whose histogram holds `residuals` (threshold: its 0.7
  quantile, floored as RC says)."""
  return residual.update(
      residual.ResidualState.initial(), jnp.asarray(residuals, jnp.float32),
      quantile=RC.quantile, decay=RC.decay, median_factor=RC.median_factor,
      minimum=RC.min_threshold)


class ClassifierTest(absltest.TestCase):

  def test_shapes_and_the_positional_encoding(self):
    clf = learned.init(LC, jax.random.key(0))
    dims = features.pixel_dims(LC.dims) + 4 * LC.frequencies
    self.assertEqual(clf.params["w1"].shape, (dims, LC.hidden))
    feats = jnp.zeros((5, 7, features.pixel_dims(LC.dims)))
    p = learned.predict(clf.params, feats)
    self.assertEqual(p.shape, (5, 7))
    self.assertTrue(np.all((np.asarray(p) > 0) & (np.asarray(p) < 1)))
    enc = np.asarray(learned.positional(2, 4, 3))
    # Pixel (row 1, col 2): x = 2.5 / 4, y = 1.5 / 2; band k = 2^k pi.
    x, y = 2.5 / 4, 1.5 / 2
    bands = np.pi * np.array([1.0, 2.0, 4.0])
    np.testing.assert_allclose(
        enc[1, 2], np.concatenate([np.sin(x * bands), np.cos(x * bands),
                                   np.sin(y * bands), np.cos(y * bands)]),
        atol=1e-6)

  def test_no_labels_before_any_residual(self):
    res = jnp.asarray(np.random.default_rng(0).random((6, 6)), jnp.float32)
    lower, upper = learned.confident(res, residual.ResidualState.initial(),
                                     RC, LC)
    np.testing.assert_array_equal(lower, 0.0)
    np.testing.assert_array_equal(upper, 1.0)

  def test_confident_pixels(self):
    # Histogram: 20 residuals of 0.02, 10 of 0.1, 6 of 0.5. Its 0.5
    # quantile is 0.02, its 0.9 quantile 0.5; the threshold is the 0.7
    # quantile 0.1 floored to 0.15 (RC.min_threshold).
    stats = _stats(np.repeat([0.02, 0.1, 0.5], [20, 10, 6]).reshape(6, 6))
    self.assertAlmostEqual(float(stats.threshold), 0.15, places=6)
    # The view: 0.01 on its border, 0.1 inside, 0.5 in its 4x4 centre.
    res = np.full((8, 8), 0.01, np.float32)
    res[1:7, 1:7] = 0.1
    res[2:6, 2:6] = 0.5
    lower, upper = learned.confident(jnp.asarray(res), stats, RC, LC)
    lower, outlier = np.asarray(lower), 1.0 - np.asarray(upper)
    # Inliers under 0.02: the 28 border pixels and, by the 3x3 rule (5 of
    # 9 neighbours inliers), the ring's 4 corners.
    self.assertEqual(lower.sum(), 32)
    self.assertEqual(lower[1, 1], 1.0)
    self.assertEqual(lower[1, 2], 0.0)
    # Outliers at 0.5 and above: the centre but its corners (the rule).
    self.assertEqual(outlier.sum(), 12)
    self.assertEqual(outlier[2:6, 2:6].sum(), 12)
    # The ring between the quantiles gets no label.
    self.assertEqual(float(np.sum(lower * outlier)), 0.0)

  def test_training_on_labels_learns_them(self):
    # Features that tell the labelled pixels apart: Adam on the loss makes
    # p follow the labels, and an unlabelled pixel with an outlier's
    # features follows the outliers.
    rng = np.random.default_rng(1)
    h, w, f = 8, 8, features.pixel_dims(LC.dims)
    transient = np.zeros((h, w), bool)
    transient[2:6, 2:6] = True
    feats = rng.normal(0, 0.05, (h, w, f)).astype(np.float32)
    feats[..., 0] += np.where(transient, 1.0, -1.0)
    lower = jnp.asarray(~transient, jnp.float32)
    upper = jnp.asarray(~transient, jnp.float32)
    upper = upper.at[3, 3].set(1.0)            # no label at (3, 3)
    lc = dataclasses.replace(LC, frequencies=0, lr=1e-2)
    clf = learned.init(lc, jax.random.key(2))
    feats = jnp.asarray(feats)
    grad = jax.jit(jax.grad(learned.loss), static_argnums=4)
    for _ in range(300):
      clf = learned.apply(clf, grad(clf.params, feats, lower, upper, lc),
                          lc, 1)
    p = np.asarray(learned.predict(clf.params, feats))
    self.assertTrue(np.all(p[~transient] > 0.8), p)
    self.assertTrue(np.all(p[transient] < 0.2), p)

  def test_the_map_is_the_verdict_and_the_loss_weight_is_p(self):
    # A classifier that says p = q everywhere: the map is 1 where q < 0.5,
    # and the loss weighs a pixel by q where the map is 0, by 0 where 1.
    feats = jnp.zeros((1, 4, 5, features.pixel_dims(LC.dims)))
    source = sources.ResidualSource(pixel_features=feats)
    photo = jnp.zeros((4, 5, 3))
    rc = dataclasses.replace(RC, warmup=0.0, min_alpha=0.0, min_share=0.0)
    for q, transient, weight in ((0.8, 0.0, 0.8), (0.3, 1.0, 0.0)):
      clf = learned.init(LC, jax.random.key(0))
      params = jax.tree.map(jnp.zeros_like, clf.params)
      params["b2"] = jnp.full((1,), np.log(q / (1 - q)), jnp.float32)
      stats = residual.ResidualState.initial(clf.replace(params=params))
      m = sources.residual_map(source, stats, jnp.int32(0), photo,
                               photo, jnp.int32(0), jax.random.key(0),
                               rc)
      np.testing.assert_allclose(m.transient, transient)
      np.testing.assert_allclose(m.loss_weight, weight, rtol=1e-5)

  def test_pixel_features_share_one_basis(self):
    rng = np.random.default_rng(3)
    photos = [rng.random((24, 40, 3)).astype(np.float32) for _ in range(2)]
    photos.append(photos[0])
    feats = features.pixel_features(photos, LC.net, LC.dims)
    self.assertEqual(feats[0].shape, (24, 40, features.pixel_dims(LC.dims)))
    self.assertTrue(np.all(np.isfinite(feats[0])))
    np.testing.assert_array_equal(feats[0], feats[2])
    # On a canvas: each photo alone, zero around it.
    canvas = np.zeros((2, 30, 40, 3), np.float32)
    canvas[0, :24], canvas[1, :20, :32] = photos[0], photos[1][:20, :32]
    placed = np.asarray(sources.learned_features(
        canvas, LC, np.array([[40, 24], [32, 20]])))
    self.assertEqual(placed.shape, (2, 30, 40, features.pixel_dims(LC.dims)))
    np.testing.assert_array_equal(placed[0, 24:], 0.0)
    np.testing.assert_array_equal(placed[1, :, 32:], 0.0)

  def test_bad_config_names_the_field(self):
    bad = dataclasses.replace(LC, inlier_quantile=0.95)
    self.assertLen(bad.problems(), 1)
    self.assertIn("inlier_quantile", bad.problems()[0])
    cfg = config.Config(
        learned=bad, semantic=guidance_config.SemanticConfig(scorer="learned"))
    problems = cfg.problems()
    self.assertTrue(any(p.startswith("--config.learned.inlier_quantile")
                        for p in problems), problems)
    self.assertTrue(any("evidence='pixel'" in p for p in problems), problems)


def _learned_config(steps: int):
  cfg = config_file.named("smoke")
  sem = dataclasses.replace(cfg.semantic, scorer="learned", evidence="pixel",
                            accumulate_start=0, reg_start=10,
                            prune_start=1000)
  return dataclasses.replace(
      cfg,
      semantic=sem,
      pixel=guidance_config.PixelConfig(loss_masking=True),
      residual=dataclasses.replace(cfg.residual, min_threshold=0.0),
      train=dataclasses.replace(cfg.train,
                                steps=steps,
                                eval_every=0,
                                log_every=10,
                                checkpoint_every=0))


class LearnedRunTest(absltest.TestCase):

  def test_resume_is_bit_identical(self):
    # The classifier trains (its weights move) and a killed run resumes to
    # the uninterrupted one's state, classifier and Adam state included.
    scene = synthetic_scene()
    cfg = train.resolve(_learned_config(30), scene)
    scorer = guidance.make_scorer(cfg, scene)
    fit = lambda workdir, **kw: train.fit(
        cfg, scene, workdir, scorer=scorer, progress=False,
        summary_dir=os.path.join(workdir, "tb"), **kw)
    straight = fit(self.create_tempdir().full_path)
    workdir = self.create_tempdir().full_path
    fit(workdir, stop_after=15)
    resumed = fit(workdir, resume=True)
    _assert_states_equal(resumed.state, straight.state)
    start = train.initial_state(cfg, scene).maps.classifier.params
    final = straight.state.maps.classifier.params
    self.assertFalse(np.array_equal(start["w1"], final["w1"]))
    self.assertEqual(int(straight.state.maps.classifier.opt_state[0].count),
                     30)


if __name__ == "__main__":
  absltest.main()
