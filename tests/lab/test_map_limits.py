"""Tests for clipgs_jax/lab/map_limits.py: the truth-fitted classifier,
the ranking's precision and multi-view photo consistency."""

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera as camera_lib
from clipgs_jax import guidance_config
from clipgs_jax.lab import map_limits

H, W, F = 24, 32, 20.0
PLANE_Z = 4.0
CENTRES = (-0.4, 0.0, 0.4, 0.8)


def test_precision_at_recall():
  score = np.array([0.9, 0.8, 0.7, 0.6, 0.5])
  truth = np.array([True, False, True, True, False])
  # Recall 2/3 needs the top three (two hits): precision 2/3.
  assert np.isclose(map_limits.precision_at_recall(score, truth, 0.6),
                    2 / 3)
  assert np.isclose(map_limits.precision_at_recall(score, truth, 1.0),
                    3 / 4)


def test_fit_classifier_separates_separable_features():
  rng = np.random.default_rng(0)
  truth = np.zeros((4, 12, 16), bool)
  truth[:, 3:8, 4:10] = True
  feats = rng.normal(0, 0.1, (4, 12, 16, 6)).astype(np.float32)
  feats[..., 0] += np.where(truth, 2.0, -2.0)
  lc = guidance_config.LearnedConfig(dims=3, frequencies=0)
  prob = map_limits.fit_classifier(feats, truth, lc, steps=300)
  s = map_limits.scores(prob > 0.5, truth)
  assert s["precision"] > 0.95 and s["recall"] > 0.95
  # Features that say nothing give no such map.
  noise = rng.normal(0, 1, feats.shape).astype(np.float32)
  s = map_limits.scores(
      map_limits.fit_classifier(noise, truth, lc, steps=300) > 0.5, truth)
  assert s["iou"] < 0.6


def _plane_views():
  """Four cameras side by side looking down +z at a textured plane z = 4:
  photos, depths, alphas, cameras; view 1 holds a flat grey patch."""
  cams, photos = [], []
  u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
  for c in CENTRES:
    cam = camera_lib.Camera.create(np.eye(3), np.array([-c, 0.0, 0.0]), F, F,
                                   W / 2, H / 2, W, H)
    x = (u - W / 2) / F * PLANE_Z + c
    y = (v - H / 2) / F * PLANE_Z
    photos.append(np.stack([0.5 + 0.4 * np.sin(3 * x),
                            0.5 + 0.4 * np.cos(2 * y),
                            0.5 + 0.2 * np.sin(x + y)], -1))
    cams.append(cam)
  photos = np.stack(photos).astype(np.float32)
  photos[1, 8:14, 12:20] = [0.0, 1.0, 0.0]
  stacked = jax.tree.map(lambda *x: jnp.asarray(np.stack(x), jnp.float32),
                         *cams)
  depths = np.full((len(CENTRES), H, W), PLANE_Z, np.float32)
  return photos, depths, np.ones_like(depths), stacked


def _counts(photos, depths, alphas, cams, i):
  seen, differs = map_limits.views_seeing(
      jnp.asarray(photos), jnp.asarray(depths), jnp.asarray(alphas), cams,
      i, (0.1,))
  return np.asarray(seen), np.asarray(differs[0])


def test_disagreement_finds_the_patch_only_where_it_is():
  photos, depths, alphas, cams = _plane_views()
  out = [map_limits.disagrees(*_counts(photos, depths, alphas, cams, i),
                               min_seen=2) for i in range(len(CENTRES))]
  patch = np.zeros((H, W), bool)
  patch[8:14, 12:20] = True
  # View 1's patch disagrees with every view that sees its wall.
  assert out[1][patch].all()
  assert not out[1][~patch].any()
  # In the others, the wall under view 1's patch disagrees with one view
  # in three: no majority, so nothing is called transient.
  for i in (0, 2, 3):
    assert not out[i].any(), i


def test_disagreement_needs_min_seen_views():
  photos, depths, alphas, cams = _plane_views()
  out = map_limits.disagrees(*_counts(photos, depths, alphas, cams, 1),
                             min_seen=4)
  assert not out.any()   # three other views at most


def test_summary_names_every_test():
  s = {"precision": 0.5, "recall": None, "iou": 0.25}
  out = {"residual": s, "features": {"scores": s, "precision_at_recall": 0.8},
         "multiview": {"0.1": {"alone": s, "with_residual": s}}}
  text = "\n".join(map_limits.summary(out))
  assert "0.50 / - / 0.25" in text
  assert "tolerance 0.1" in text and "P 0.80 at R 0.75" in text
  assert "memory" not in text
  out["memory"] = {"alone": s, "release": {"0.2": s}}
  text = "\n".join(map_limits.summary(out))
  assert "the map's memory: 0.50 / - / 0.25" in text
  assert "release, colour tolerance 0.2" in text


def test_release_lets_go_of_held_static_scene_only():
  photos, depths, alphas, cams = _plane_views()
  held = np.zeros((H, W), bool)
  held[8:14, 12:20] = True       # view 1's patch
  held[2:5, 2:6] = True          # and the wall, which the others agree on
  seen, differs = _counts(photos, depths, alphas, cams, 1)
  out = map_limits.released(held, seen, differs, min_seen=2)
  assert not out[8:14, 12:20].any()
  assert out[2:5, 2:6].any()
  # A pixel too few views see stays held; nothing unheld is released.
  assert not out[~held].any()
  assert not map_limits.released(held, seen, differs, min_seen=9).any()


def test_one_projection_counts_every_tolerance():
  photos, depths, alphas, cams = _plane_views()
  args = (jnp.asarray(photos), jnp.asarray(depths), jnp.asarray(alphas),
          cams, 1)
  seen, differs = map_limits.views_seeing(*args, (0.05, 0.1, 0.2))
  assert differs.shape == (3,) + seen.shape
  for t, tol in enumerate((0.05, 0.1, 0.2)):
    alone_seen, alone = map_limits.views_seeing(*args, (tol,))
    np.testing.assert_array_equal(alone_seen, seen)
    np.testing.assert_array_equal(alone[0], differs[t])
  # Counts fall as the tolerance grows; the patch differs at every one.
  assert (np.diff(np.asarray(differs), axis=0) <= 0).all()
  assert np.asarray(differs)[-1, 8:14, 12:20].any()
