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
  """Projected ellipses: exactly representable means, ~45 % of them thin
  and tilted (whose tile rectangles hold many tiles they miss)."""
  rng = np.random.default_rng(seed)
  n = NUM_BIG + NUM_SMALL
  means = np.stack([rng.integers(0, WIDTH, n), rng.integers(0, HEIGHT, n)],
                   -1) + 0.5
  sigma = rng.uniform(1.0, 12.0, (n, 2))
  sigma[rng.random(n) < 0.45, 1] = 0.6                  # thin
  sigma[:NUM_BIG] = 4 * WIDTH                           # cover the image
  angle = rng.uniform(0, np.pi, n)
  rot = np.stack([np.cos(angle), -np.sin(angle), np.sin(angle),
                  np.cos(angle)], -1).reshape(n, 2, 2)
  cov = rot @ (sigma[:, :, None] ** 2 * np.eye(2)) @ np.swapaxes(rot, 1, 2)
  inv = np.linalg.inv(cov)
  opacity = rng.uniform(0.05, 1.0, n)
  level = np.log(opacity * 255)
  ext = np.sqrt(2 * level[:, None] * cov[:, [0, 1], [0, 1]]) * 1.001 + 0.01
  depths = rng.integers(1, 50, n).astype(np.float64)   # ties on purpose
  valid = rng.random(n) > 0.1
  return project.Projected(
      means2d=jnp.asarray(means, jnp.float32),
      conics=jnp.asarray(inv[:, [0, 0, 1], [0, 1, 1]], jnp.float32),
      depths=jnp.asarray(depths, jnp.float32),
      colors=jnp.ones((n, 3), jnp.float32),
      opacities=jnp.asarray(opacity, jnp.float32),
      extents=jnp.asarray(ext, jnp.float32),
      valid=jnp.asarray(valid))


def _tile_powers(proj, g, tx, ty, samples):
  """Power of splat g on a samples x samples grid spanning the box of tile
  (tx, ty)'s pixel centres (samples = TILE: the centres), float64."""
  a, b, c = np.asarray(proj.conics, np.float64)[g]
  mean = np.asarray(proj.means2d, np.float64)[g]
  s = np.linspace(0.5, TILE - 0.5, samples)
  x = tx * TILE + s[None, :] - mean[0]
  y = ty * TILE + s[:, None] - mean[1]
  return 0.5 * (a * x * x + c * y * y) + b * x * y


def _box_least_power(proj, g, tx, ty):
  """Least power over the box, float64: a 2x2 quadratic program solved by
  its KKT cases (the interior minimum, each edge's clamped minimum)."""
  a, b, c = np.asarray(proj.conics, np.float64)[g]
  mean = np.asarray(proj.means2d, np.float64)[g]
  x0, y0 = tx * TILE + 0.5 - mean[0], ty * TILE + 0.5 - mean[1]
  x1, y1 = x0 + TILE - 1, y0 + TILE - 1
  if x0 <= 0 <= x1 and y0 <= 0 <= y1:
    return 0.0
  power = lambda x, y: 0.5 * (a * x * x + c * y * y) + b * x * y
  candidates = [power(np.clip(-b * y / a, x0, x1), y) for y in (y0, y1)]
  candidates += [power(x, np.clip(-b * x / c, y0, y1)) for x in (x0, x1)]
  return min(candidates)


def _reference(proj, grid):
  """Per tile, the valid splats whose rectangle covers it, near to far,
  each with whether the blend needs it (alpha >= 1/255 at a pixel centre)
  and whether it must go (its least power over the box of pixel centres
  over 1.01 x the level)."""
  means, ext = np.asarray(proj.means2d), np.asarray(proj.extents)
  level = np.log(np.asarray(proj.opacities, np.float64) * 255)
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
        pixels = _tile_powers(proj, g, tx, ty, TILE)
        least = _box_least_power(proj, g, tx, ty)
        # The box's least is at most the pixel centres' (the QP is right).
        assert least <= pixels.min() + 1e-9, (g, tx, ty)
        lists[ty * grid.tiles_x + tx].append(
            (g, pixels.min() <= level[g], least > 1.01 * level[g]))
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
    self.assertGreater(int(np.sum(count)), 2 * rasterize._KEY_BLOCK)
    # pylint: enable=protected-access
    gauss, start, count = (np.asarray(x) for x in (gauss, start, count))
    self.assertEqual(int(overflow), 0)
    self.assertEqual(int(max_count), int(count.max()))
    # The test culls: a quarter of the small splats' rectangle tiles go.
    small = sum(g >= NUM_BIG for entries in ref for g, _, _ in entries)
    kept = int(np.sum(gauss[:count.sum()] >= NUM_BIG))
    self.assertLess(kept, 0.85 * small)
    for t in range(grid.num_tiles):
      got = list(gauss[start[t]:start[t] + count[t]])
      # Near to far, a subsequence of the rectangles' list that holds
      # every splat the blend needs and none that must go.
      self.assertEqual([g for g, _, _ in ref[t] if g in got], got,
                       f"tile {t}")
      self.assertContainsSubset([g for g, need, _ in ref[t] if need], got,
                                f"tile {t}")
      self.assertNoCommonElements([g for g, _, out in ref[t] if out], got,
                                  f"tile {t}")

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
