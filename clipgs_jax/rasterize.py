"""Tile rasterizer: bin splats into 16x16 tiles, depth-sort, alpha-blend.

The blend is a `jax.custom_vjp` whose backward pass recomputes each chunk's
alphas front to back instead of storing per-pixel per-Gaussian tensors, so
memory is O(pixels x chunk_size). Projection (`project.py`) is plain JAX and
differentiated by autodiff; it is O(N) and cheap.
"""

import dataclasses
import functools
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import camera as camera_lib
from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import project as project_lib

TILE = 16                      # tile side in pixels
PIXELS_PER_TILE = TILE * TILE
MAX_ALPHA = 0.99               # cap so 1 / (1 - alpha) stays <= 100
# A pixel stops blending when its transmittance would fall below this; the
# remaining light cannot change an 8-bit colour visibly (reference 3DGS).
TRANSMITTANCE_THRESHOLD = 1e-4
# Smallest intersection buffer tried before sorting; below this, sorting is
# cheap enough that more lax.switch branches would only add compile time.
_MIN_SORT_BUFFER = 1 << 15
_NO_KEY = np.uint32(0xFFFFFFFF)   # sorts after every real (tile, rank) key


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
    num_overflow: int32 [], tile-list entries dropped because a tile held
      more than `tile_budget` Gaussians (0 means the render is exact).
    max_tile_count: int32 [], the longest tile list before the budget.
  """
  image: Any
  alpha: Any
  depth: Any
  visible: Any
  contribution: Any
  evidence: Any
  num_overflow: Any
  max_tile_count: Any


@dataclasses.dataclass(frozen=True)
class _Grid:
  """Static tiling of one image size (hashable: a custom_vjp static arg)."""
  width: int
  height: int
  tile_budget: int
  chunk_size: int

  @property
  def tiles_x(self) -> int:
    return -(-self.width // TILE)

  @property
  def tiles_y(self) -> int:
    return -(-self.height // TILE)

  @property
  def num_tiles(self) -> int:
    return self.tiles_x * self.tiles_y

  @property
  def num_rounds(self) -> int:
    return -(-self.tile_budget // self.chunk_size)


def _pixel_centers(grid: _Grid, dtype):
  """float [T, P, 2] pixel centres per tile and bool [T, P] inside-image."""
  ty, tx, py, px = np.meshgrid(np.arange(grid.tiles_y), np.arange(grid.tiles_x),
                               np.arange(TILE), np.arange(TILE), indexing="ij")
  x = (tx * TILE + px).reshape(grid.num_tiles, PIXELS_PER_TILE)
  y = (ty * TILE + py).reshape(grid.num_tiles, PIXELS_PER_TILE)
  inside = (x < grid.width) & (y < grid.height)
  centers = np.stack([x + 0.5, y + 0.5], -1).astype(dtype)
  return jnp.asarray(centers), jnp.asarray(inside)


def _tile(x: jax.Array, grid: _Grid) -> jax.Array:
  """[H, W] image to the [T, P] tile layout (padding pixels get 0)."""
  x = jnp.pad(x, ((0, grid.tiles_y * TILE - grid.height),
                  (0, grid.tiles_x * TILE - grid.width)))
  x = x.reshape(grid.tiles_y, TILE, grid.tiles_x, TILE)
  return jnp.swapaxes(x, 1, 2).reshape(grid.num_tiles, PIXELS_PER_TILE)


def _untile(x: jax.Array, grid: _Grid) -> jax.Array:
  """[T, P, ...] tile layout to a cropped [H, W, ...] image."""
  rest = x.shape[2:]
  x = x.reshape((grid.tiles_y, grid.tiles_x, TILE, TILE) + rest)
  x = jnp.swapaxes(x, 1, 2).reshape(
      (grid.tiles_y * TILE, grid.tiles_x * TILE) + rest)
  return x[:grid.height, :grid.width]


def _cumsum(x: jax.Array) -> jax.Array:
  """Inclusive 1D prefix sum; jnp.cumsum is 6x slower on XLA:CPU (1M ints)."""
  return jax.lax.associative_scan(jnp.add, x)


def _bin(proj: project_lib.Projected, grid: _Grid):
  """Depth-sorted per-tile lists as one sorted array plus tile ranges.

  Returns:
    gauss: int32 [T * K], Gaussian ids grouped by tile, near to far.
    start: int32 [T], first entry of each tile in `gauss`.
    count: int32 [T], entries of each tile, capped at the budget K.
    num_overflow: int32 [], intersections dropped by the budget.
    max_count: int32 [], longest tile list before the cap.
  """
  n = proj.depths.shape[0]
  t, k = grid.num_tiles, grid.tile_budget
  capacity = t * k
  rank_bits = max(1, int(np.ceil(np.log2(n))))
  tile_bits = int(np.ceil(np.log2(t + 1)))
  if rank_bits + tile_bits > 32:
    raise ValueError(
        f"{n} Gaussian slots and {t} tiles do not fit a 32-bit sort key; "
        "lower the capacity or render at a lower resolution.")
  lo = jnp.floor((proj.means2d - proj.extents) / TILE)
  hi = jnp.floor((proj.means2d + proj.extents) / TILE)
  limit = jnp.array([grid.tiles_x - 1, grid.tiles_y - 1], lo.dtype)
  # Clip in float before the int cast, so huge splats cannot overflow int32.
  lo_i = jnp.clip(lo, 0, limit).astype(jnp.int32)
  hi_i = jnp.clip(hi, -1, limit).astype(jnp.int32)
  span = jnp.maximum(hi_i - lo_i + 1, 0) * (hi >= 0) * (lo <= limit)
  n_tiles = jnp.where(proj.valid, span[:, 0] * span[:, 1], 0)     # [N]
  # Exact per-tile counts from a 2D difference array of the tile rectangles:
  # O(N + T), and independent of how many intersections the buffer holds.
  hit = (n_tiles > 0).astype(jnp.int32)
  x0, y0 = lo_i[:, 0], lo_i[:, 1]
  x1, y1 = hi_i[:, 0] + 1, hi_i[:, 1] + 1
  diff = jnp.zeros((grid.tiles_y + 1, grid.tiles_x + 1), jnp.int32)
  diff = (diff.at[y0, x0].add(hit).at[y0, x1].add(-hit)
          .at[y1, x0].add(-hit).at[y1, x1].add(hit))
  true_count = jnp.cumsum(jnp.cumsum(diff, 0), 1)[:-1, :-1].reshape(-1)

  # Gaussians in depth order (stable, so ties keep index order).
  order = jnp.argsort(jnp.where(proj.valid, proj.depths, jnp.inf),
                      stable=True).astype(jnp.int32)
  counts = n_tiles[order]
  ends = _cumsum(counts)
  starts = ends - counts
  total = ends[-1]

  def sorted_keys(size):
    """Sorted (tile, depth rank) keys of the first `size` intersections."""
    # owner[m]: depth rank of the Gaussian that emits intersection m, i.e.
    # the last rank whose start is <= m (zero-count ranks share the start
    # of the next rank, so they are never the last).
    marks = jnp.zeros(size, jnp.int32).at[starts].add(1, mode="drop")
    owner = jnp.clip(_cumsum(marks) - 1, 0, n - 1)                # [size]
    m = jnp.arange(size, dtype=jnp.int32)
    local = m - starts[owner]
    g = order[owner]
    width = jnp.maximum(span[g, 0], 1)
    tile = ((lo_i[g, 1] + local // width) * grid.tiles_x
            + lo_i[g, 0] + local % width)
    key = (tile.astype(jnp.uint32) << rank_bits) | owner.astype(jnp.uint32)
    key = jnp.where(m < total, key, _NO_KEY)
    key = jnp.sort(key)        # one int key: 8x cheaper than a keyed sort
    return jnp.concatenate([key, jnp.full(capacity - size, _NO_KEY)])

  # Sorting costs O(buffer), so pick the smallest of a geometric ladder of
  # buffers that holds this view's intersections (lax.switch runs only that
  # branch); ratio 2/3 wastes at most a third of a sort.
  sizes = [capacity]
  while sizes[-1] * 2 // 3 >= _MIN_SORT_BUFFER:
    sizes.append(sizes[-1] * 2 // 3)
  branch = jnp.maximum(jnp.sum(jnp.array(sizes) >= total) - 1, 0)
  key = jax.lax.switch(branch, [functools.partial(sorted_keys, sz)
                                for sz in sizes])
  gauss = order[(key & jnp.uint32((1 << rank_bits) - 1)).astype(jnp.int32)
                .clip(0, n - 1)]
  bounds = jnp.searchsorted(
      key, jnp.arange(t + 1, dtype=jnp.uint32) << rank_bits).astype(jnp.int32)
  start = bounds[:-1]
  count = jnp.minimum(bounds[1:] - start, k)
  # Dropped: entries past a tile's budget, and any the buffer could not hold.
  num_overflow = total - jnp.sum(count)
  return gauss, start, count, num_overflow, jnp.max(true_count)


def _entries(r, splats, tables, chunk_size):
  """Gaussian ids and attributes of list entries [r*B, (r+1)*B) per tile."""
  gauss, start, count = tables
  k = r * chunk_size + jnp.arange(chunk_size)
  in_list = k[None, :] < count[:, None]                          # [T, B]
  gid = gauss[jnp.clip(start[:, None] + k[None, :], 0, gauss.shape[0] - 1)]
  return gid, in_list, tuple(x[gid] for x in splats)             # [T, B, ...]


def _alpha(pix, mean, conic, opacity):
  """Blend alpha of one entry per tile at every pixel of the tile.

  Args:
    pix: float [T, P, 2]; mean: [T, 2]; conic: [T, 3]; opacity: [T].
  Returns:
    alpha, raw = opacity * gauss, gauss = exp(-power), dx, dy, keep: [T, P].
  """
  dx = pix[..., 0] - mean[:, None, 0]
  dy = pix[..., 1] - mean[:, None, 1]
  ca, cb, cc = conic[:, None, 0], conic[:, None, 1], conic[:, None, 2]
  power = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
  gauss = jnp.exp(-jnp.maximum(power, 0.0))
  raw = opacity[:, None] * gauss
  keep = (power >= 0) & (raw >= project_lib.ALPHA_THRESHOLD)
  alpha = jnp.where(keep, jnp.minimum(raw, MAX_ALPHA), 0.0)
  return alpha, raw, gauss, dx, dy, keep


def _forward_init(splats, pix, pix_inside, emap):
  """Initial forward carry; its evidence slot is None without a map."""
  t, p = pix.shape[:2]
  dtype = splats[0].dtype
  carry = (jnp.int32(0), jnp.ones((t, p), dtype), jnp.zeros((t, p, 3), dtype),
           jnp.zeros((t, p), dtype), jnp.zeros((t, p), jnp.int32),
           ~pix_inside, jnp.zeros((splats[0].shape[0],), dtype))
  return carry + (None if emap is None else jnp.zeros_like(carry[-1]),)


def _forward_round(grid, splats, tables, pix, emap, carry):
  """Blends list entries [r*B, (r+1)*B) of every tile into the carry.

  The B entries are walked one at a time on [T, P] arrays, which stay in
  cache (a [T, B, P] formulation was memory-bound at 400 MB per round), in a
  fori_loop rather than unrolled (unrolling B = 32 took a minute to compile).
  `emap` (float [T, P] or None) adds the map-weighted sums; with None the
  traced program is the plain blend (a Python-level branch).
  """
  r, trans, color, depth, n_contrib, done, contrib, evidence = carry
  gid, in_list, (means2d, conics, colors, opacities, depths) = _entries(
      r, splats, tables, grid.chunk_size)

  def entry(b, state):
    trans, color, depth, n_contrib, done, per_entry, per_ev = state
    alpha = _alpha(pix, means2d[:, b], conics[:, b], opacities[:, b])[0]
    t_after = trans * (1.0 - alpha)
    include = ((t_after >= TRANSMITTANCE_THRESHOLD) & ~done
               & in_list[:, b, None])
    w = jnp.where(include, alpha * trans, 0.0)                   # [T, P]
    color = color + w[..., None] * colors[:, b, None, :]
    depth = depth + w * depths[:, b, None]
    trans = jnp.where(include, t_after, trans)
    n_contrib = n_contrib + include
    # Out of list or below the transmittance floor: this pixel is finished.
    done = done | ~include
    # Pixels outside the image start `done`, so their w is already 0.
    per_entry = per_entry.at[:, b].set(jnp.sum(w, axis=1))
    if emap is not None:
      per_ev = per_ev.at[:, b].set(jnp.sum(w * emap, axis=1))
    return trans, color, depth, n_contrib, done, per_entry, per_ev

  zeros = jnp.zeros(in_list.shape, trans.dtype)
  state = (trans, color, depth, n_contrib, done, zeros,
           None if emap is None else zeros)
  trans, color, depth, n_contrib, done, per_entry, per_ev = jax.lax.fori_loop(
      0, grid.chunk_size, entry, state)
  per_entry = jnp.where(in_list, per_entry, 0.0)
  contrib = contrib.at[gid.reshape(-1)].add(per_entry.reshape(-1))
  if emap is not None:
    per_ev = jnp.where(in_list, per_ev, 0.0)
    evidence = evidence.at[gid.reshape(-1)].add(per_ev.reshape(-1))
  return r + 1, trans, color, depth, n_contrib, done, contrib, evidence


def _blend_forward(grid, splats, tables, pix, pix_inside, emap):
  count = tables[2]

  def cond(carry):
    r, done = carry[0], carry[5]
    # A tile is active while its list has entries left and a pixel is open.
    active = (r * grid.chunk_size < count) & ~jnp.all(done, axis=1)
    return (r < grid.num_rounds) & jnp.any(active)

  body = functools.partial(_forward_round, grid, splats, tables, pix, emap)
  carry = jax.lax.while_loop(
      cond, body, _forward_init(splats, pix, pix_inside, emap))
  _, trans, color, depth, n_contrib, _, contrib, evidence = carry
  return color, depth, trans, n_contrib, contrib, evidence


def blend_autodiff(grid, splats, tables, pix, pix_inside, emap=None):
  """The same blend as a fixed-length scan, for plain reverse-mode autodiff.

  `while_loop` cannot be reverse-differentiated, so this runs every round
  (no early exit) and autodiff stores every round's intermediates. It exists
  to measure what the custom VJP saves (bench_rasterizer.py) and as a second
  gradient check; training never uses it. `emap` (float [T, P] or None)
  adds the evidence sums exactly as the custom-VJP blend does.
  """
  body = functools.partial(_forward_round, grid, splats, tables, pix, emap)
  carry = jax.lax.scan(lambda c, _: (body(c), None),
                       _forward_init(splats, pix, pix_inside, emap), None,
                       length=grid.num_rounds)[0]
  _, trans, color, depth, _, _, contrib, evidence = carry
  return color, depth, trans, contrib, evidence


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _blend(grid, means2d, conics, colors, opacities, depths, tables, pix,
           pix_inside, emap):
  splats = (means2d, conics, colors, opacities, depths)
  color, depth, trans, _, contrib, evidence = _blend_forward(
      grid, splats, tables, pix, pix_inside, emap)
  return color, depth, trans, contrib, evidence


def _blend_fwd(grid, means2d, conics, colors, opacities, depths, tables, pix,
               pix_inside, emap):
  splats = (means2d, conics, colors, opacities, depths)
  color, depth, trans, n_contrib, contrib, evidence = _blend_forward(
      grid, splats, tables, pix, pix_inside, emap)
  residuals = (splats, tables, pix, color, depth, trans, n_contrib)
  return (color, depth, trans, contrib, evidence), residuals


def _blend_bwd(grid, residuals, cotangents):
  splats, tables, pix, color, depth, trans_final, n_contrib = residuals
  # Contribution and evidence are not differentiable.
  g_color, g_depth, g_trans = cotangents[:3]
  n = splats[0].shape[0]
  dtype = splats[0].dtype
  t, p = pix.shape[:2]
  # Linearised loss L = sum_k w_k v_k + T_final g_T with v_k = c_k.gC + z_k gD
  # per pixel. Walking front to back, the part of the first sum behind entry
  # k is v_total minus the running prefix, so nothing is stored per entry.
  v_total = jnp.einsum("tpc,tpc->tp", color, g_color) + depth * g_depth
  tail = trans_final * g_trans

  def body(carry):
    r, trans, v_prefix, grads = carry
    gid, in_list, (means2d, conics, colors, opacities, depths) = _entries(
        r, splats, tables, grid.chunk_size)

    def entry(b, state):
      trans, v_prefix, rows = state
      alpha, raw, gauss, dx, dy, keep = _alpha(
          pix, means2d[:, b], conics[:, b], opacities[:, b])
      include = r * grid.chunk_size + b < n_contrib               # [T, P]
      alpha = jnp.where(include, alpha, 0.0)
      w = alpha * trans
      v = (jnp.einsum("tc,tpc->tp", colors[:, b], g_color)
           + depths[:, b, None] * g_depth)
      v_prefix = v_prefix + w * v
      behind = v_total - v_prefix + tail
      g_alpha = jnp.where(include, trans * v - behind / (1.0 - alpha), 0.0)
      # alpha = min(0.99, o G), G = exp(-power): the cap has zero slope.
      g_raw = jnp.where(keep & (raw < MAX_ALPHA) & include, g_alpha, 0.0)
      g_power = -g_raw * raw
      # power = a dx^2 / 2 + b dx dy + c dy^2 / 2 with dx = px - mean_x, so
      # every splat gradient is a conic-weighted moment of g_power over the
      # tile's pixels.
      gx, gy = jnp.sum(g_power * dx, 1), jnp.sum(g_power * dy, 1)
      ca, cb, cc = (conics[:, b, i] for i in range(3))
      row = jnp.concatenate([
          jnp.stack([-(ca * gx + cb * gy), -(cb * gx + cc * gy),
                     0.5 * jnp.sum(g_power * dx * dx, 1),
                     jnp.sum(g_power * dx * dy, 1),
                     0.5 * jnp.sum(g_power * dy * dy, 1)], -1),
          jnp.einsum("tp,tpc->tc", w, g_color),
          jnp.stack([jnp.sum(g_raw * gauss, 1), jnp.sum(w * g_depth, 1)],
                    -1)], -1)                                    # [T, 10]
      return trans * (1.0 - alpha), v_prefix, rows.at[:, b].set(row)

    rows = jnp.zeros(in_list.shape + (10,), dtype)
    trans, v_prefix, rows = jax.lax.fori_loop(
        0, grid.chunk_size, entry, (trans, v_prefix, rows))
    rows = jnp.where(in_list[..., None], rows, 0.0)
    grads = grads.at[gid.reshape(-1)].add(rows.reshape(-1, 10))
    return r + 1, trans, v_prefix, grads

  max_contrib = jnp.max(n_contrib)

  def cond(carry):
    return carry[0] * grid.chunk_size < max_contrib

  init = (jnp.int32(0), jnp.ones((t, p), dtype), jnp.zeros((t, p), dtype),
          jnp.zeros((n, 10), dtype))
  grads = jax.lax.while_loop(cond, body, init)[3]
  # Columns: mean (2), conic (3), colour (3), opacity, depth.
  return (grads[:, 0:2], grads[:, 2:5], grads[:, 5:8], grads[:, 8],
          grads[:, 9], None, None, None, None)


_blend.defvjp(_blend_fwd, _blend_bwd)


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


def rasterize(proj: project_lib.Projected, cam: camera_lib.Camera,
              background: jax.Array, cfg: config_lib.RenderConfig,
              custom_vjp: bool = True,
              evidence_map: jax.Array | None = None) -> RenderOutput:
  """Bins, sorts and blends projected splats into an image.

  `custom_vjp=False` swaps in `blend_autodiff` (benchmarks and tests only).
  `evidence_map` (float [H, W], values in [0, 1], no gradient flows into it)
  makes the same pass also return `RenderOutput.evidence`, per Gaussian the
  sum over pixels of blending weight times map value. Without it the traced
  program is the plain render and `evidence` is None.
  """
  grid = _Grid(int(cam.width), int(cam.height), cfg.tile_budget,
               cfg.chunk_size)
  dtype = proj.means2d.dtype
  pix, pix_inside = _pixel_centers(grid, dtype)
  gauss, start, count, num_overflow, max_count = _bin(proj, grid)
  splats = (proj.means2d, proj.conics, proj.colors, proj.opacities,
            proj.depths)
  emap = None
  if evidence_map is not None:
    _check_evidence_map(evidence_map, cam)
    emap = _tile(jax.lax.stop_gradient(jnp.asarray(evidence_map, dtype)),
                 grid)
  if custom_vjp:
    color, depth, trans, contrib, evidence = _blend(
        grid, *splats, (gauss, start, count), pix, pix_inside, emap)
  else:
    color, depth, trans, contrib, evidence = blend_autodiff(
        grid, splats, (gauss, start, count), pix, pix_inside, emap)
  trans = _untile(trans, grid)
  alpha = 1.0 - trans
  image = _untile(color, grid) + trans[..., None] * background.astype(dtype)
  depth = _untile(depth, grid)
  has_alpha = alpha > 0
  depth = jnp.where(has_alpha, depth / jnp.where(has_alpha, alpha, 1.0), 0.0)
  return RenderOutput(
      image=image, alpha=alpha, depth=depth, visible=contrib > 0,
      contribution=contrib, evidence=evidence,
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
