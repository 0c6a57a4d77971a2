"""Tests for initialize: kNN scales, packing into capacity, random init."""

import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from clipgs_jax import config
from clipgs_jax import gaussians
from clipgs_jax import initialize
from clipgs_jax import sh


class KnnTest(absltest.TestCase):

  def test_matches_brute_force(self):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3)) * 5 + 100.0     # far from the origin
    got = initialize.knn_mean_distance(pts, k=3, chunk=64)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    want = np.sort(d, axis=1)[:, :3].mean(axis=1)
    np.testing.assert_allclose(got, want, rtol=1e-9)

  def test_closed_form_grid(self):
    # On a unit-spacing line, inner points have neighbours at 1, 1, 2:
    # mean 4/3; an end point has 1, 2, 3: mean 2.
    pts = np.stack([np.arange(6.0), np.zeros(6), np.zeros(6)], -1)
    got = initialize.knn_mean_distance(pts)
    np.testing.assert_allclose(got[[0, 2, 5]], [2.0, 4 / 3, 2.0])

  def test_few_points(self):
    pts = np.array([[0.0, 0, 0], [0, 3, 4]])
    np.testing.assert_allclose(initialize.knn_mean_distance(pts), [5.0, 5.0])
    self.assertTrue(np.isnan(initialize.knn_mean_distance(pts[:1]))[0])


class FromPointsTest(absltest.TestCase):

  def test_packing_and_values(self):
    cfg = config.GaussiansConfig(sh_degree=2)
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1],
                    [0, 0, 1]], np.float32)     # the last one duplicated
    colors = np.tile([[0.2, 0.5, 0.9]], (5, 1)).astype(np.float32)
    params, alive = initialize.from_points(pts, colors, 8, cfg)
    gaussians.validate(params, jnp.asarray(alive))
    self.assertEqual(params.capacity, 8)
    self.assertEqual(params.sh_degree, 2)
    np.testing.assert_array_equal(alive, [True] * 5 + [False] * 3)
    np.testing.assert_array_equal(params.means[:5], pts)
    np.testing.assert_allclose(
        jnp.asarray(params.sh_dc[:5]) * 0.28209479177387814 + 0.5, colors,
        rtol=1e-5)
    np.testing.assert_allclose(params.sh_dc[:5], sh.rgb_to_dc(colors))
    np.testing.assert_allclose(1 / (1 + np.exp(-params.opacity_logits[:5])),
                               0.1, rtol=1e-5)
    np.testing.assert_array_equal(params.quats[:5],
                                  np.tile([1.0, 0, 0, 0], (5, 1)))
    np.testing.assert_array_equal(params.sh_rest, 0)
    # Isotropic scales = log of the mean 3-NN distance; the origin has
    # neighbours at 1, 1, 1 -> log 1 = 0.
    np.testing.assert_allclose(params.log_scales[0], 0.0, atol=1e-6)
    want = initialize.knn_mean_distance(pts)
    np.testing.assert_allclose(params.log_scales[:5, 1], np.log(want),
                               rtol=1e-6)

  def test_min_scale_floor(self):
    cfg = config.GaussiansConfig(init_min_scale=1e-3)
    pts = np.zeros((4, 3), np.float32)         # all coincide: distance 0
    params, _ = initialize.from_points(pts, np.zeros((4, 3)), 4, cfg)
    np.testing.assert_allclose(params.log_scales[:4], np.log(1e-3),
                               rtol=1e-6)

  def test_capacity_error(self):
    with self.assertRaisesRegex(ValueError, "exceed capacity 2.*capacity"):
      initialize.from_points(np.zeros((3, 3)), np.zeros((3, 3)), 2,
                             config.GaussiansConfig())

  def test_bad_points(self):
    with self.assertRaisesRegex(ValueError, r"\[P, 3\]"):
      initialize.from_points(np.zeros((3, 2)), np.zeros((3, 2)), 4,
                             config.GaussiansConfig())
    with self.assertRaisesRegex(ValueError, "non-finite"):
      initialize.from_points(np.full((3, 3), np.nan), np.zeros((3, 3)), 4,
                             config.GaussiansConfig())

  def test_auto_capacity(self):
    cfg = config.GaussiansConfig(min_capacity=16, max_capacity=1024)
    self.assertEqual(initialize.auto_capacity(3, cfg), 16)
    self.assertEqual(initialize.auto_capacity(100, cfg), 256)
    self.assertEqual(initialize.auto_capacity(900, cfg), 1024)
    self.assertEqual(initialize.auto_capacity(2000, cfg), 2000)
    self.assertEqual(initialize.auto_capacity(
        5, config.GaussiansConfig(capacity=7)), 7)


class RandomInitTest(absltest.TestCase):

  def test_inside_camera_box(self):
    centers = np.array([[-2.0, 0, 1], [2, 0.5, -1], [0, 0.5, 3]])
    cfg = config.GaussiansConfig(random_init_points=500, min_capacity=8)
    params, alive = initialize.initialize(None, None, centers, cfg, seed=3)
    self.assertEqual(int(alive.sum()), 500)
    self.assertEqual(params.capacity, 1024)
    means = np.asarray(params.means[:500])
    self.assertTrue(np.all(means >= [-2, 0, -1]) and
                    np.all(means <= [2, 0.5, 3]))
    # Spread over the box, not collapsed.
    self.assertGreater(means[:, 0].std(), 0.8)
    colors = np.asarray(params.sh_dc[:500]) * 0.28209479177387814 + 0.5
    self.assertTrue(np.all((colors >= 0) & (colors <= 1 + 1e-6)))

  def test_flat_camera_box_gets_volume(self):
    lo, hi = initialize.camera_box(np.array([[0.0, 0, 0], [2, 2, 0]]))
    np.testing.assert_allclose(lo, [0, 0, -1])
    np.testing.assert_allclose(hi, [2, 2, 1])

  def test_uses_points_when_given(self):
    pts = np.random.default_rng(1).normal(size=(40, 3)).astype(np.float32)
    params, alive = initialize.initialize(
        pts, np.full((40, 3), 0.5, np.float32), np.zeros((2, 3)),
        config.GaussiansConfig(min_capacity=64))
    self.assertEqual(params.capacity, 128)
    self.assertEqual(int(alive.sum()), 40)
    np.testing.assert_array_equal(params.means[:40], pts)


if __name__ == "__main__":
  absltest.main()
