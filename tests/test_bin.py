"""Binning against a NumPy reference, past one block of sort keys."""

from absl.testing import absltest
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax.render import blend
from clipgs_jax.render import project
from clipgs_jax.render import rasterize

# 512 x 256 pixels in 16 x 16 tiles: 512 tiles.
WIDTH, HEIGHT, TILE = 512, 256, 16
# Whole-image splats: ~90 % valid x 160 x 512 tiles exceed two key blocks.
NUM_BIG = 160
NUM_SMALL = 400


def _splats(seed=0):
  """Projected splats with exactly representable, in-image rectangles."""
  rng = np.random.default_rng(seed)
  n = NUM_BIG + NUM_SMALL
  means = np.stack([rng.integers(0, WIDTH, n), rng.integers(0, HEIGHT, n)],
                   -1) + 0.5
  ext = rng.integers(1, 40, (n, 2)).astype(np.float64)
  ext[:NUM_BIG] = [2 * WIDTH, 2 * HEIGHT]
  depths = rng.integers(1, 50, n).astype(np.float64)   # ties on purpose
  valid = rng.random(n) > 0.1
  return project.Projected(
      means2d=jnp.asarray(means, jnp.float32),
      conics=jnp.ones((n, 3), jnp.float32),
      depths=jnp.asarray(depths, jnp.float32),
      colors=jnp.ones((n, 3), jnp.float32),
      opacities=jnp.ones(n, jnp.float32),
      extents=jnp.asarray(ext, jnp.float32),
      valid=jnp.asarray(valid))


def _reference(proj, grid):
  """Per tile, the ids of the valid splats covering it, near to far."""
  means, ext = np.asarray(proj.means2d), np.asarray(proj.extents)
  lo = np.clip(np.floor((means - ext) / TILE), 0,
               [grid.tiles_x - 1, grid.tiles_y - 1]).astype(int)
  hi = np.clip(np.floor((means + ext) / TILE), 0,
               [grid.tiles_x - 1, grid.tiles_y - 1]).astype(int)
  order = np.argsort(np.asarray(proj.depths), kind="stable")
  lists = [[] for _ in range(grid.num_tiles)]
  for g in order:
    if not np.asarray(proj.valid)[g]:
      continue
    for ty in range(lo[g, 1], hi[g, 1] + 1):
      for tx in range(lo[g, 0], hi[g, 0] + 1):
        lists[ty * grid.tiles_x + tx].append(g)
  return lists


class BinTest(absltest.TestCase):

  def test_lists_match_reference_over_several_key_blocks(self):
    proj = _splats()
    grid = blend.Grid(WIDTH, HEIGHT, tile_budget=256, chunk_size=8,
                      tile=TILE)
    # pylint: disable=protected-access
    gauss, start, count, overflow, max_count = jax.jit(
        lambda q: rasterize._bin(q, grid))(proj)
    ref = _reference(proj, grid)
    self.assertGreater(sum(map(len, ref)), 2 * rasterize._KEY_BLOCK)
    # pylint: enable=protected-access
    gauss, start, count = (np.asarray(x) for x in (gauss, start, count))
    self.assertEqual(int(overflow), 0)
    self.assertEqual(int(max_count), max(map(len, ref)))
    for t in range(grid.num_tiles):
      np.testing.assert_array_equal(
          gauss[start[t]:start[t] + count[t]], ref[t], err_msg=f"tile {t}")

  def test_depth_order_is_the_stable_argsort(self):
    """Distinct depths, pairs, runs up to and past _MAX_TIE, +-0, culled."""
    rng = np.random.default_rng(1)
    # pylint: disable=protected-access
    longest = rasterize._MAX_TIE
    order = jax.jit(rasterize._depth_order)
    # pylint: enable=protected-access
    cases = {
        "distinct": rng.uniform(0.2, 10.0, 3000),
        "pairs": np.repeat(rng.uniform(0.2, 10.0, 1500), 2),
        "runs at the limit": np.repeat(rng.uniform(1.0, 2.0, 100), longest),
        "runs past the limit": np.repeat(rng.uniform(1.0, 2.0, 100),
                                         longest + 1),
        "signed zeros": rng.choice([0.0, -0.0, 1.0, -1.0], 1000),
    }
    for name, depths in cases.items():
      depths = jnp.asarray(rng.permutation(depths), jnp.float32)
      for culled in (0.0, 0.4):
        valid = jnp.asarray(rng.random(depths.shape[0]) >= culled)
        want = np.argsort(np.where(valid, depths, np.inf), kind="stable")
        np.testing.assert_array_equal(order(depths, valid), want,
                                      err_msg=f"{name}, {culled} culled")


if __name__ == "__main__":
  absltest.main()
