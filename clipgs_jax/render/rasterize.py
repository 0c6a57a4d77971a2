"""Tile rasterizer: bin splats into square tiles, depth-sort, alpha-blend.

Binning and sorting live here; the blend (`blend.py`) is a `jax.custom_vjp`
whose work follows each tile's own list. Projection (`project.py`) is plain
JAX and differentiated by autodiff; it is O(N) and cheap.
"""

import functools
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera as camera_lib
from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax.render import blend as blend_lib
from clipgs_jax.render import project as project_lib

MAX_ALPHA = blend_lib.MAX_ALPHA
TRANSMITTANCE_THRESHOLD = blend_lib.TRANSMITTANCE_THRESHOLD
# Smallest intersection buffer tried before sorting; below this, sorting is
# cheap enough that more lax.switch branches would only add compile time.
_MIN_SORT_BUFFER = 1 << 15
# Intersections whose sort keys one loop trip builds: the smallest rung, so
# a light view takes one trip.
_KEY_BLOCK = _MIN_SORT_BUFFER
_NO_KEY = np.uint32(0xFFFFFFFF)   # sorts after every real (tile, rank) key
# Depth keys of culled rows: above the total-order key of +inf (0xFF800000),
# plus the row index (so up to _MAX_KEYED_ROWS rows before they wrap).
_INVALID_KEY = np.uint32(0xFF800001)
_MAX_KEYED_ROWS = 0xFFFFFFFF - 0xFF800001
# Longest run of equal depths placed by scatter-min rounds (one round per
# rank within the run); a longer one takes the argsort.
_MAX_TIE = 16


@flax.struct.dataclass
class RenderOutput:
  """What one render returns.

  Attributes:
    image: float [H, W, 3], blended colour over the background.
    alpha: float [H, W], accumulated opacity, 1 - final transmittance.
    depth: float [H, W], expected depth sum(w z) / alpha (0 where alpha = 0).
    visible: bool [C], the slot gave a non-zero blending weight to a pixel.
    contribution: float [C], sum over pixels of its blending weights.
    evidence: float [C], sum over pixels of its blending weights times the
      evidence map, from the same pass; None when no map was given.
    probe_image: float [H, W], the evidence probe blended as a fourth
      colour channel over a zero background; None without a probe.
    num_overflow: int32 [], tile-list entries dropped because the view's
      intersections exceeded the buffer, num_tiles x `tile_budget` (0 means
      the render is exact; one tile may hold any number of them).
    max_tile_count: int32 [], the longest tile list.
  """
  image: Any
  alpha: Any
  depth: Any
  visible: Any
  contribution: Any
  evidence: Any
  probe_image: Any
  num_overflow: Any
  max_tile_count: Any


def _pixel_centers(grid: blend_lib.Grid, dtype):
  """float [T, P, 2] pixel centres per tile and bool [T, P] inside-image."""
  ty, tx, py, px = np.meshgrid(np.arange(grid.tiles_y), np.arange(grid.tiles_x),
                               np.arange(grid.tile), np.arange(grid.tile),
                               indexing="ij")
  x = (tx * grid.tile + px).reshape(grid.num_tiles, grid.pixels_per_tile)
  y = (ty * grid.tile + py).reshape(grid.num_tiles, grid.pixels_per_tile)
  inside = (x < grid.width) & (y < grid.height)
  centers = np.stack([x + 0.5, y + 0.5], -1).astype(dtype)
  return jnp.asarray(centers), jnp.asarray(inside)


def _tile(x: jax.Array, grid: blend_lib.Grid) -> jax.Array:
  """[H, W] image to the [T, P] tile layout (padding pixels get 0)."""
  x = jnp.pad(x, ((0, grid.tiles_y * grid.tile - grid.height),
                  (0, grid.tiles_x * grid.tile - grid.width)))
  x = x.reshape(grid.tiles_y, grid.tile, grid.tiles_x, grid.tile)
  return jnp.swapaxes(x, 1, 2).reshape(grid.num_tiles, grid.pixels_per_tile)


def _untile(x: jax.Array, grid: blend_lib.Grid) -> jax.Array:
  """[T, P, ...] tile layout to a cropped [H, W, ...] image."""
  rest = x.shape[2:]
  x = x.reshape((grid.tiles_y, grid.tiles_x, grid.tile, grid.tile) + rest)
  x = jnp.swapaxes(x, 1, 2).reshape(
      (grid.tiles_y * grid.tile, grid.tiles_x * grid.tile) + rest)
  return x[:grid.height, :grid.width]


def _depth_order(depths: jax.Array, valid: jax.Array) -> jax.Array:
  """int32 [N]: jnp.argsort(where(valid, depths, inf), stable=True).

  XLA:CPU sorts one integer array several times faster than it sorts keys
  with a payload, as an argsort does (220k rows: ~20 against ~150 ms;
  BUILD_NOTES.md, "Rasterizer"). So every row gets a uint32 key that orders as
  the argsort does: the depth's bits mapped to total order for valid rows,
  and _INVALID_KEY + index (above every finite depth) for the rest. One
  plain sort and a binary search give each row the first position of its
  key; rows that share a key (equal float32 depths: thousands at 200k
  rows) take the next positions in index order, one scatter-min per rank
  within the tie. A tie longer than _MAX_TIE (e.g. a fronto-parallel
  plane) takes the argsort itself (lax.cond), so the result is the
  argsort's in every case.
  """
  n = depths.shape[0]
  index = jnp.arange(n, dtype=jnp.int32)

  def argsort():
    return jnp.argsort(jnp.where(valid, depths, jnp.inf),
                       stable=True).astype(jnp.int32)
  if n > _MAX_KEYED_ROWS:
    return argsort()
  # -0.0 and 0.0 are equal depths (and NaN is never valid).
  depths = jnp.where(depths == 0, 0.0, depths).astype(jnp.float32)
  bits = jax.lax.bitcast_convert_type(depths, jnp.uint32)
  ordered = jnp.where(bits >> 31 != 0, ~bits, bits | jnp.uint32(1 << 31))
  key = jnp.where(valid, ordered, _INVALID_KEY + index.astype(jnp.uint32))
  first = jnp.searchsorted(jnp.sort(key), key).astype(jnp.int32)
  tie = jnp.zeros(n, jnp.int32).at[first].add(1)[first]   # rows per key
  longest = jnp.max(tie)

  def by_key():
    def place(carry):
      k, offset, left = carry
      # The lowest index still unplaced of each key takes its next slot.
      low = jnp.full(n, n, jnp.int32).at[first].min(
          jnp.where(left, index, n))
      now = left & (low[first] == index)
      return k + 1, jnp.where(now, k, offset), left & ~now
    _, offset, _ = jax.lax.while_loop(
        lambda carry: carry[0] < longest, place,
        (jnp.int32(0), jnp.zeros(n, jnp.int32), tie > 1))
    return jnp.zeros(n, jnp.int32).at[first + offset].set(
        index, unique_indices=True)
  return jax.lax.cond(longest <= _MAX_TIE, by_key, argsort)


def _reaches(tx, ty, ellipse, size: int):
  """Whether a splat's alpha can reach the blend's threshold in a tile.

  True where the least power 0.5 (a x^2 + c y^2) + b x y over the box of
  the tile's pixel centres (x, y relative to the splat's mean) is at most
  `level` = log(opacity / ALPHA_THRESHOLD): 0 if the box holds the mean,
  else the least over its four edges, each a clamped 1D minimum. The box
  holds every pixel centre, and the slack covers float rounding (terms of
  size s round by ~1e-7 s), so a tile where the blend finds alpha above the
  threshold is never dropped. tx, ty: int [B]; ellipse: float [B, 6],
  the mean (2), conic (3) and level of each splat.
  """
  mean_x, mean_y, a, b, c, level = jnp.moveaxis(ellipse, -1, 0)
  x0 = (tx * size).astype(ellipse.dtype) + 0.5 - mean_x
  y0 = (ty * size).astype(ellipse.dtype) + 0.5 - mean_y
  x1, y1 = x0 + (size - 1), y0 + (size - 1)
  a, c = jnp.maximum(a, 1e-30), jnp.maximum(c, 1e-30)

  def on_row(y):      # least over x in [x0, x1] at this y
    return blend_lib.power(jnp.clip(-b * y / a, x0, x1), y, a, b, c)

  def on_column(x):   # least over y in [y0, y1] at this x
    return blend_lib.power(x, jnp.clip(-b * x / c, y0, y1), a, b, c)

  least = jnp.minimum(jnp.minimum(on_row(y0), on_row(y1)),
                      jnp.minimum(on_column(x0), on_column(x1)))
  holds_mean = (x0 <= 0) & (x1 >= 0) & (y0 <= 0) & (y1 >= 0)
  least = jnp.where(holds_mean, 0.0, least)
  far_x = jnp.maximum(jnp.abs(x0), jnp.abs(x1))
  far_y = jnp.maximum(jnp.abs(y0), jnp.abs(y1))
  size_of_terms = 0.5 * (a * far_x * far_x + c * far_y * far_y) + jnp.abs(
      b * far_x * far_y)
  return least <= level * (1 + 1e-3) + 1e-5 * size_of_terms


def _bin(proj: project_lib.Projected, grid: blend_lib.Grid):
  """Depth-sorted per-tile lists as one sorted array plus tile ranges.

  Returns:
    gauss: int32 [T * K], Gaussian ids grouped by tile, near to far.
    start: int32 [T], first entry of each tile in `gauss`.
    count: int32 [T], entries of each tile.
    num_overflow: int32 [], intersections the buffer could not hold (the
      farthest; once the buffer is full, counted by tile rectangle).
    max_count: int32 [], longest tile list; on overflow, the most tile
      rectangles over one tile (an upper bound).
  """
  n = proj.depths.shape[0]
  t = grid.num_tiles
  capacity = t * grid.tile_budget
  rank_bits = max(1, int(np.ceil(np.log2(n))))
  tile_bits = int(np.ceil(np.log2(t + 1)))
  if rank_bits + tile_bits > 32:
    raise ValueError(
        f"{n} Gaussian slots and {t} tiles do not fit a 32-bit sort key; "
        "lower the capacity or render at a lower resolution.")
  lo = jnp.floor((proj.means2d - proj.extents) / grid.tile)
  hi = jnp.floor((proj.means2d + proj.extents) / grid.tile)
  limit = jnp.array([grid.tiles_x - 1, grid.tiles_y - 1], lo.dtype)
  # Clip in float before the int cast, so huge splats cannot overflow int32.
  lo_i = jnp.clip(lo, 0, limit).astype(jnp.int32)
  hi_i = jnp.clip(hi, -1, limit).astype(jnp.int32)
  span = jnp.maximum(hi_i - lo_i + 1, 0) * (hi >= 0) * (lo <= limit)
  n_tiles = jnp.where(proj.valid, span[:, 0] * span[:, 1], 0)     # [N]
  # Per-tile counts of the tile rectangles from a 2D difference array:
  # O(N + T), and independent of how many intersections the buffer holds.
  hit = (n_tiles > 0).astype(jnp.int32)
  x0, y0 = lo_i[:, 0], lo_i[:, 1]
  x1, y1 = hi_i[:, 0] + 1, hi_i[:, 1] + 1
  diff = jnp.zeros((grid.tiles_y + 1, grid.tiles_x + 1), jnp.int32)
  diff = (diff.at[y0, x0].add(hit).at[y0, x1].add(-hit)
          .at[y1, x0].add(-hit).at[y1, x1].add(hit))
  true_count = jnp.cumsum(jnp.cumsum(diff, 0), 1)[:-1, :-1].reshape(-1)

  order = _depth_order(proj.depths, proj.valid)
  counts = n_tiles[order]
  # The rows that emit intersections, compacted in depth order: each has
  # at least one, so a block of `block` intersections is emitted by at most
  # `block` consecutive emitters, and a block finds each intersection's
  # emitter by a running count over that window instead of a binary search
  # over all rows (at 1e5 splats and 1.8M intersections: ~25 against ~85 ms).
  emits = counts > 0
  slot = jnp.cumsum(emits, dtype=jnp.int32) - 1
  rank = jnp.zeros(n, jnp.int32).at[jnp.where(emits, slot, n)].set(
      jnp.arange(n, dtype=jnp.int32), mode="drop", unique_indices=True)
  emitted = jnp.where(jnp.arange(n) <= slot[-1], counts[rank], 0)
  emitter = order[rank]                        # Gaussian id of each emitter
  # jnp.cumsum, not lax.associative_scan: 3.5x slower to run at 1M ints
  # (7.5 vs 2.1 ms) but 0.5-0.7 s less to compile per call site.
  ends = jnp.cumsum(emitted)
  starts = ends - emitted
  total = ends[-1]

  # Keys are built block by block in a while loop (one compiled body, as
  # many trips as the view's intersections need), then only the sort runs
  # on a ladder of buffer sizes: building them inside each rung cost ~0.45 s
  # of XLA:CPU compile per rung. A rectangle's tile that the splat's
  # ellipse misses gets no key (_reaches), so neither the sort nor the
  # blend sees it; the kept keys are packed in emission order.
  block = min(_KEY_BLOCK, capacity)
  # starts, then past the last emitter a value above every intersection.
  starts_p = jnp.concatenate([starts, jnp.full(block + 1, total + block,
                                               starts.dtype)])
  # What a block reads of an emitter, gathered once in emission order and
  # packed in rows (one gather each a block instead of one per field):
  # its first intersection and tile rectangle, and its ellipse.
  rect = jnp.stack([starts, lo_i[emitter, 0], lo_i[emitter, 1],
                    jnp.maximum(span[emitter, 0], 1)], -1)
  level = jnp.log(jnp.maximum(proj.opacities / project_lib.ALPHA_THRESHOLD,
                              1.0))
  ellipse = jnp.concatenate([proj.means2d, proj.conics, level[:, None]],
                            -1)[emitter]

  def key_block(c):
    """Packs the (tile, emitter) keys of intersections [i B, i B + B)."""
    i, filled, buf = c
    first = i * block
    m = first + jnp.arange(block, dtype=jnp.int32)
    # The emitter of intersection m is the last whose start is <= m: from
    # the one that holds `first`, one more for each start passed.
    e0 = jnp.searchsorted(starts, first, side="right").astype(jnp.int32) - 1
    later = jax.lax.dynamic_slice(starts_p, (e0 + 1,), (block,)) - first
    passed = jnp.zeros(block, jnp.int32).at[later].add(1, mode="drop")
    owner = jnp.clip(e0 + jnp.cumsum(passed), 0, n - 1)
    start, lo_x, lo_y, width = jnp.moveaxis(rect[owner], -1, 0)
    local = m - start
    tx = lo_x + local % width
    ty = lo_y + local // width
    keep = (m < total) & _reaches(tx, ty, ellipse[owner], grid.tile)
    key = (((ty * grid.tiles_x + tx).astype(jnp.uint32) << rank_bits)
           | owner.astype(jnp.uint32))
    slot = filled + jnp.cumsum(keep, dtype=jnp.int32) - 1
    buf = buf.at[jnp.where(keep, slot, capacity)].set(key, mode="drop")
    return i + 1, filled + jnp.sum(keep, dtype=jnp.int32), buf

  def more(c):
    # Past a full buffer only the farthest splats' entries are left, and
    # they are dropped (counted by their rectangles, without the test).
    i, filled, _ = c
    return (i * block < total) & (filled < capacity)

  trips, filled, keys = jax.lax.while_loop(
      more, key_block,
      (jnp.int32(0), jnp.int32(0), jnp.full(capacity, _NO_KEY)))
  kept = jnp.minimum(filled, capacity)
  num_overflow = filled - kept + jnp.maximum(total - trips * block, 0)

  def sorted_keys(size):
    """The first `size` keys, sorted, padded to the buffer."""
    key = jnp.sort(keys[:size])  # one int key: 8x cheaper than a keyed sort
    return jnp.concatenate([key, jnp.full(capacity - size, _NO_KEY)])

  # Sorting costs O(buffer), so pick the smallest of a geometric ladder of
  # buffers that holds this view's intersections (lax.switch runs only that
  # branch); ratio 2/3 wastes at most a third of a sort.
  sizes = [capacity]
  while sizes[-1] * 2 // 3 >= _MIN_SORT_BUFFER:
    sizes.append(sizes[-1] * 2 // 3)
  branch = jnp.maximum(jnp.sum(jnp.array(sizes) >= kept) - 1, 0)
  key = jax.lax.switch(branch, [functools.partial(sorted_keys, sz)
                                for sz in sizes])
  gauss = emitter[(key & jnp.uint32((1 << rank_bits) - 1)).astype(jnp.int32)
                  .clip(0, n - 1)]
  bounds = jnp.searchsorted(
      key, jnp.arange(t + 1, dtype=jnp.uint32) << rank_bits).astype(jnp.int32)
  start = bounds[:-1]
  count = bounds[1:] - start
  # On overflow the lists lack the farthest splats, so the rectangles'
  # counts bound the longest list instead.
  max_count = jnp.where(num_overflow > 0, jnp.max(true_count),
                        jnp.max(count))
  return gauss, start, count, num_overflow, max_count


def _check_evidence_map(evidence_map, cam: camera_lib.Camera) -> None:
  shape = (int(cam.height), int(cam.width))
  if np.shape(evidence_map) != shape:
    raise ValueError(
        f"evidence_map must be a float [H, W] = {list(shape)} map of the "
        f"rendered view, got shape {np.shape(evidence_map)}; resize it to "
        "the camera's image size.")
  if not jnp.issubdtype(jnp.result_type(evidence_map), jnp.floating):
    raise ValueError(
        f"evidence_map must be floating point in [0, 1], got dtype "
        f"{jnp.result_type(evidence_map)}; cast it (e.g. mask.astype(float)).")


def _prepare(proj: project_lib.Projected, cam: camera_lib.Camera,
             cfg: config_lib.RenderConfig, valid_size=None):
  """What both blends need: the tile grid, the splats, the depth-sorted
  tile lists (gauss, start, count), the tiled pixel centres and which of
  them lie inside the image (and inside `valid_size`, int [2] width and
  height, when given), and the overflow and longest-list counts."""
  for name in ("tile_budget", "chunk_size", "tile_size"):
    if getattr(cfg, name) < 1:
      raise ValueError(f"RenderConfig.{name} must be >= 1, got "
                       f"{getattr(cfg, name)}.")
  grid = blend_lib.Grid(int(cam.width), int(cam.height), cfg.tile_budget,
                        cfg.chunk_size, cfg.lanes, cfg.tile_size)
  pix, pix_inside = _pixel_centers(grid, proj.means2d.dtype)
  if valid_size is not None:
    # Pixel centres sit at +0.5, so centre < size exactly for the pixels
    # of a size[0] x size[1] image in the top-left corner.
    size = jnp.asarray(valid_size, pix.dtype)
    pix_inside = pix_inside & jnp.all(pix < size, axis=-1)
  gauss, start, count, num_overflow, max_count = _bin(proj, grid)
  splats = (proj.means2d, proj.conics, proj.colors, proj.opacities,
            proj.depths)
  return (grid, splats, (gauss, start, count), pix, pix_inside,
          num_overflow, max_count)


def rasterize(proj: project_lib.Projected, cam: camera_lib.Camera,
              background: jax.Array, cfg: config_lib.RenderConfig,
              custom_vjp: bool = True,
              evidence_map: jax.Array | None = None,
              probe: jax.Array | None = None,
              valid_size: jax.Array | None = None) -> RenderOutput:
  """Bins, sorts and blends projected splats into an image.

  `custom_vjp=False` swaps in `blend.blend_autodiff` (benchmarks and tests
  only; it drops list entries past `tile_budget` per tile).
  `evidence_map` (float [H, W], values in [0, 1], no gradient flows into it)
  makes the same pass also return `RenderOutput.evidence`, per Gaussian the
  sum over pixels of blending weight times map value. Without it the traced
  program is the plain render and `evidence` is None.
  `probe` (float [C]) is the same sum for a map known only after the
  render, from the backward pass: it is blended as a fourth colour channel
  into `RenderOutput.probe_image`, so with probe = 0 and a loss term
  sum(stop_gradient(m) * probe_image) (worth 0) the gradient d loss /
  d probe_j is sum_i w_ij m_i, and no other gradient changes.
  `valid_size` (int [2], may be traced) is the width and height of the
  view's photo in the top-left corner of a larger canvas (the camera's
  size): pixels outside it are never blended (they show the background,
  alpha 0) and add nothing to `visible`, `contribution` or `evidence`.
  """
  grid, splats, tables, pix, pix_inside, num_overflow, max_count = (
      _prepare(proj, cam, cfg, valid_size))
  dtype = proj.means2d.dtype
  if probe is not None:
    if np.shape(probe) != np.shape(proj.depths):
      raise ValueError(f"probe must be float [C] = {list(np.shape(proj.depths))}"
                       f", one value per Gaussian, got {np.shape(probe)}.")
    means2d, conics, colors, opacities, depths = splats
    colors = jnp.concatenate([colors, probe.astype(dtype)[:, None]], -1)
    splats = (means2d, conics, colors, opacities, depths)
    background = jnp.concatenate([background.astype(dtype),
                                  jnp.zeros((1,), dtype)])
  emap = None
  if evidence_map is not None:
    _check_evidence_map(evidence_map, cam)
    emap = _tile(jax.lax.stop_gradient(jnp.asarray(evidence_map, dtype)),
                 grid)
  if custom_vjp:
    color, depth, trans, contrib, evidence = blend_lib.blend(
        grid, *splats, tables, pix, pix_inside, emap)
  else:
    color, depth, trans, contrib, evidence = blend_lib.blend_autodiff(
        grid, splats, tables, pix, pix_inside, emap)
  trans = _untile(trans, grid)
  alpha = 1.0 - trans
  image = _untile(color, grid) + trans[..., None] * background.astype(dtype)
  probe_image = None
  if probe is not None:
    image, probe_image = image[..., :3], image[..., 3]
  depth = _untile(depth, grid)
  has_alpha = alpha > 0
  depth = jnp.where(has_alpha, depth / jnp.where(has_alpha, alpha, 1.0), 0.0)
  return RenderOutput(
      image=image, alpha=alpha, depth=depth, visible=contrib > 0,
      contribution=contrib, evidence=evidence, probe_image=probe_image,
      num_overflow=num_overflow.astype(jnp.int32),
      max_tile_count=max_count.astype(jnp.int32))


def render(params: gaussians.GaussianParams, alive: jax.Array,
           cam: camera_lib.Camera, background: jax.Array,
           cfg: config_lib.RenderConfig = config_lib.RenderConfig(),
           sh_degree: jax.Array | int | None = None,
           evidence_map: jax.Array | None = None) -> RenderOutput:
  """Renders the alive Gaussians seen from `cam`.

  Args:
    params: GaussianParams with capacity C.
    alive: bool [C], slots in use.
    cam: the camera; its width and height fix the output size.
    background: float [3], colour behind the Gaussians.
    cfg: rasterizer settings (near plane, tile budget, chunk size).
    sh_degree: int [], SH bands used (default: all stored bands).
    evidence_map: float [H, W] in [0, 1] or None; if given, the output's
      `evidence` [C] holds each Gaussian's map-weighted blending weight
      (no gradient flows into the map).
  """
  gaussians.validate(params, alive)
  camera_lib.validate(cam)
  if np.shape(background) != (3,):
    raise ValueError(f"background must have shape (3,), got "
                     f"{np.shape(background)}.")
  if sh_degree is None:
    sh_degree = params.sh_degree
  proj = project_lib.project(params, alive, cam, near=cfg.near,
                             sh_degree=sh_degree)
  return rasterize(proj, cam, jnp.asarray(background), cfg,
                   evidence_map=evidence_map)


def blend_stats(proj: project_lib.Projected, cam: camera_lib.Camera,
                cfg: config_lib.RenderConfig) -> dict[str, Any]:
  """How much of the blend's work one view needs (host-side diagnostic).

  Runs binning and both blend passes once (outside any jit) and counts, per
  pass, the needed pixel evaluations (each tile: its list up to where its
  last pixel finished, times its pixels) against the executed ones (rounds x
  lanes x chunk x pixels), and the executed pixel-entry pairs whose alpha is
  non-zero. `lockstep_*` are the same counts for a blend that runs every
  tile in every round until the longest list ends (the layout this one
  replaced). For benchmarks; never called in training.
  """
  grid, splats, tables, pix, inside, _, _ = _prepare(proj, cam, cfg)
  gauss, start, count = tables
  color, depth, trans, n_contrib, _, _, rounds_fwd = blend_lib.forward(
      grid, splats, tables, pix, inside, None)
  _, rounds_bwd = blend_lib.backward(
      grid, splats, tables, pix, color, depth, trans,
      n_contrib, jnp.ones_like(color), jnp.ones_like(depth),
      jnp.ones_like(trans))
  count, n_contrib = np.asarray(count), np.asarray(n_contrib)
  gauss, start = np.asarray(gauss), np.asarray(start)
  p, b = grid.pixels_per_tile, grid.chunk_size
  # The forward evaluates a tile's entries until its list ends or its last
  # pixel finished (the entry that finishes a pixel is evaluated too).
  fwd_need = np.minimum(count, n_contrib.max(1) + 1)
  bwd_need = n_contrib.max(1)
  means, conics, opac, pix = (np.asarray(x) for x in (
      proj.means2d, proj.conics, proj.opacities, pix))
  nonzero = 0
  for t in range(grid.num_tiles):
    gid = gauss[start[t]:start[t] + fwd_need[t]]
    d = pix[t][:, None, :] - means[gid][None]                    # [P, E, 2]
    c = conics[gid]
    power = blend_lib.power(d[..., 0], d[..., 1], c[:, 0], c[:, 1], c[:, 2])
    raw = opac[gid] * np.exp(-np.maximum(power, 0.0))
    nonzero += int(np.sum((power >= 0)
                          & (raw >= project_lib.ALPHA_THRESHOLD)))
  slots = grid.num_lanes * b * p
  executed_fwd = max(int(rounds_fwd) * slots, 1)
  executed_bwd = max(int(rounds_bwd) * slots, 1)
  lockstep_rounds = int(np.max(-(-fwd_need // b)))
  lockstep = max(lockstep_rounds * grid.num_tiles * b * p, 1)
  return dict(
      num_tiles=grid.num_tiles, lanes=grid.num_lanes, tile_size=grid.tile,
      intersections=int(count.sum()), mean_list=round(float(count.mean()), 1),
      median_list=float(np.median(count)), max_list=int(count.max()),
      rounds_fwd=int(rounds_fwd), rounds_bwd=int(rounds_bwd),
      efficiency_fwd=round(float(fwd_need.sum()) * p / executed_fwd, 3),
      efficiency_bwd=round(float(bwd_need.sum()) * p / executed_bwd, 3),
      nonzero_alpha_share_fwd=round(nonzero / executed_fwd, 4),
      lockstep_rounds=lockstep_rounds,
      lockstep_efficiency_fwd=round(float(fwd_need.sum()) * p / lockstep, 3),
      lockstep_nonzero_alpha_share_fwd=round(nonzero / lockstep, 4))
