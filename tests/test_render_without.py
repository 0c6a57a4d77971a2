"""The render-without test that can spare rows of eq. 13's semantic clause."""

from absl.testing import absltest
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config as config_lib
from clipgs_jax import render_without
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.render import rasterize
import synthetic

CFG = config_lib.Config()


def _blobs():
  """Two opaque, bright Gaussians side by side, and a third behind."""
  return synthetic.with_rows(
      synthetic.random_params(3, degree=0),
      means=[[-0.6, 0.0, 0.0], [0.6, 0.0, 0.0], [0.0, 0.0, 1.5]],
      log_scales=np.full((3, 3), -1.2), quats=np.tile([1.0, 0, 0, 0], (3, 1)),
      opacity_logits=[5.0, 5.0, 5.0],
      sh_dc=[[2.0, 2.0, 2.0], [2.0, -1.0, -1.0], [-1.0, 2.0, -1.0]])


def _views(cam, photo):
  cams = jax.tree.map(lambda x: np.asarray(x)[None], cam)
  return scene_lib.Views(cameras=cams, images=np.asarray(photo)[None],
                         names=("a.png",), masks=None)


class HarmedShareTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    self.cam = synthetic.front_camera(40, 24)
    self.params = _blobs()
    self.bg = jnp.asarray(CFG.train.background, jnp.float32)

  def _photo(self, alive):
    return rasterize.render(self.params, jnp.asarray(alive), self.cam,
                            self.bg, CFG.render, 0).image

  def _share(self, photo, candidates):
    return render_without.harmed_share(
        self.params, jnp.ones(3, bool), np.asarray(candidates),
        _views(self.cam, photo), render_without.HARM_TOLERANCE,
        jnp.int32(0), CFG)

  def test_a_row_the_photo_shows_is_needed(self):
    share, pixels, _ = self._share(self._photo([True, True, True]),
                                [True, False, False])
    self.assertGreater(pixels, 10)
    self.assertGreater(share[0], 0.5)
    np.testing.assert_array_equal(share[1:], 0.0)   # not candidates

  def test_a_row_not_yet_fit_is_needed_too(self):
    # The photo's blob is darker than the render's (a residual above any
    # map threshold there), but the background without the row is worse.
    photo = self._photo([True, True, True])
    self.params = synthetic.with_rows(
        self.params, sh_dc=[[1.2, 1.2, 1.2], [2.0, -1.0, -1.0],
                            [-1.0, 2.0, -1.0]])
    share, _, _ = self._share(photo, [True, False, False])
    self.assertGreater(share[0], 0.5)

  def test_a_ghost_the_photo_lacks_is_not(self):
    # The photo has the first blob's place empty: the render misses it
    # there with the row and fits it without, so nothing is harmed.
    share, pixels, _ = self._share(self._photo([False, True, True]),
                                [True, False, False])
    self.assertEqual(pixels, 0)
    np.testing.assert_array_equal(share, 0.0)

  def test_two_candidates_are_judged_apart(self):
    # Both go together; only the one the photo shows is needed (the
    # ghost's tail reaches a few of the other's harmed pixels).
    share, _, _ = self._share(self._photo([False, True, True]),
                           [True, True, False])
    self.assertLess(share[0], 0.05)
    self.assertGreater(share[1], 0.5)

  def test_views_that_cannot_see_the_candidates_are_not_rendered(self):
    photo = self._photo([True, True, True])
    self.params = synthetic.with_rows(
        self.params, means=[[40.0, 0.0, 0.0], [0.6, 0.0, 0.0],
                            [0.0, 0.0, 1.5]])
    share, pixels, tested = self._share(photo, [True, False, False])
    self.assertEqual((pixels, tested), (0, 0))
    np.testing.assert_array_equal(share, 0.0)
    self.assertEqual(self._share(photo, [False, True, False])[2], 1)


if __name__ == "__main__":
  absltest.main()
