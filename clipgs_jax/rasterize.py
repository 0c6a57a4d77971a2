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


@flax.struct.dataclass
class RenderOutput:
  """What one render returns.

  Attributes:
    image: float [H, W, 3], blended colour over the background.
    alpha: float [H, W], accumulated opacity, 1 - final transmittance.
    depth: float [H, W], expected depth sum(w z) / alpha (0 where alpha = 0).
    visible: bool [C], the slot gave a non-zero blending weight to a pixel.
    contribution: float [C], sum over pixels of its blending weights.
    num_overflow: int32 [], tile-list entries dropped because a tile held
      more than `tile_budget` Gaussians (0 means the render is exact).
    max_tile_count: int32 [], the longest tile list before the budget.
  """
  image: Any
  alpha: Any
  depth: Any
  visible: Any
  contribution: Any
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


def _untile(x: jax.Array, grid: _Grid) -> jax.Array:
  """[T, P, ...] tile layout to a cropped [H, W, ...] image."""
  rest = x.shape[2:]
  x = x.reshape((grid.tiles_y, grid.tiles_x, TILE, TILE) + rest)
  x = jnp.swapaxes(x, 1, 2).reshape(
      (grid.tiles_y * TILE, grid.tiles_x * TILE) + rest)
  return x[:grid.height, :grid.width]


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

  # Gaussians in depth order (stable, so ties keep index order).
  order = jnp.argsort(jnp.where(proj.valid, proj.depths, jnp.inf),
                      stable=True).astype(jnp.int32)
  counts = n_tiles[order]
  ends = jnp.cumsum(counts)
  starts = ends - counts
  total = ends[-1]
  # owner[m]: depth rank of the Gaussian that emits intersection m.
  marks = jnp.zeros(capacity + 1, jnp.int32).at[
      jnp.where(counts > 0, starts, capacity)].add(1, mode="drop")
  owner = jnp.cumsum(marks[:capacity]) - 1                      # [T * K]
  owner = jnp.clip(owner, 0, n - 1)
  m = jnp.arange(capacity, dtype=jnp.int32)
  local = m - starts[owner]
  g = order[owner]
  width = span[g, 0]
  tile_x = lo_i[g, 0] + local % jnp.maximum(width, 1)
  tile_y = lo_i[g, 1] + local // jnp.maximum(width, 1)
  tile = tile_y * grid.tiles_x + tile_x
  key = (tile.astype(jnp.uint32) << rank_bits) | owner.astype(jnp.uint32)
  key = jnp.where(m < total, key, jnp.uint32(0xFFFFFFFF))
  key = jnp.sort(key)          # one int key: far cheaper than a keyed sort
  gauss = order[(key & jnp.uint32((1 << rank_bits) - 1)).astype(jnp.int32)
                .clip(0, n - 1)]
  bounds = jnp.searchsorted(
      key, jnp.arange(t + 1, dtype=jnp.uint32) << rank_bits).astype(jnp.int32)
  start, raw_count = bounds[:-1], bounds[1:] - bounds[:-1]
  count = jnp.minimum(raw_count, k)
  num_overflow = total - jnp.sum(count)
  return gauss, start, count, num_overflow, jnp.max(raw_count)


def _chunk(r, splats, tables, pix):
  """Alphas of list entries [r*B, (r+1)*B) of every tile: [T, B, P] tensors."""
  means2d, conics, colors, opacities, depths = splats
  gauss, start, count, chunk_size = tables
  k = r * chunk_size + jnp.arange(chunk_size)
  in_list = k[None, :] < count[:, None]                          # [T, B]
  gid = gauss[jnp.clip(start[:, None] + k[None, :], 0, gauss.shape[0] - 1)]
  mean = means2d[gid]                                            # [T, B, 2]
  conic = conics[gid]                                            # [T, B, 3]
  d = pix[:, None, :, :] - mean[:, :, None, :]                   # [T, B, P, 2]
  dx, dy = d[..., 0], d[..., 1]
  ca, cb, cc = (conic[..., i][..., None] for i in range(3))
  power = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy     # [T, B, P]
  gauss_val = jnp.exp(-jnp.maximum(power, 0.0))
  raw = opacities[gid][..., None] * gauss_val
  keep = in_list[..., None] & (power >= 0) & (raw >= project_lib.ALPHA_THRESHOLD)
  alpha = jnp.where(keep, jnp.minimum(raw, MAX_ALPHA), 0.0)
  return dict(gid=gid, in_list=in_list, dx=dx, dy=dy, conic=conic,
              gauss_val=gauss_val, raw=raw, keep=keep, alpha=alpha,
              color=colors[gid], depth=depths[gid])


def _exclusive_cumprod(x, init):
  """init * prod_{j<k} x_j along axis 1, and the inclusive product."""
  inclusive = init[:, None, :] * jnp.cumprod(x, axis=1)
  exclusive = jnp.concatenate([init[:, None, :], inclusive[:, :-1]], axis=1)
  return exclusive, inclusive


def _forward_init(grid, splats, pix, pix_inside):
  t, p = pix.shape[:2]
  dtype = splats[0].dtype
  return (jnp.int32(0), jnp.ones((t, p), dtype), jnp.zeros((t, p, 3), dtype),
          jnp.zeros((t, p), dtype), jnp.zeros((t, p), jnp.int32), ~pix_inside,
          jnp.zeros((splats[0].shape[0],), dtype))


def _forward_round(grid, splats, tables, pix, pix_inside, carry):
  """Blends list entries [r*B, (r+1)*B) of every tile into the carry."""
  r, trans, color, depth, n_contrib, done, contrib = carry
  c = _chunk(r, splats, tables + (grid.chunk_size,), pix)
  t_before, t_after = _exclusive_cumprod(1.0 - c["alpha"], trans)
  include = ((t_after >= TRANSMITTANCE_THRESHOLD) & ~done[:, None, :]
             & c["in_list"][..., None])
  w = jnp.where(include, c["alpha"] * t_before, 0.0)             # [T, B, P]
  color = color + jnp.einsum("tbp,tbc->tpc", w, c["color"])
  depth = depth + jnp.einsum("tbp,tb->tp", w, c["depth"])
  new_trans = jnp.min(jnp.where(include, t_after, jnp.inf), axis=1)
  trans = jnp.minimum(trans, new_trans)
  n_contrib = n_contrib + jnp.sum(include, axis=1, dtype=jnp.int32)
  done = done | jnp.any(~include, axis=1)
  per_entry = jnp.sum(jnp.where(pix_inside[:, None, :], w, 0.0), axis=2)
  contrib = contrib.at[c["gid"].reshape(-1)].add(
      jnp.where(c["in_list"], per_entry, 0.0).reshape(-1))
  return r + 1, trans, color, depth, n_contrib, done, contrib


def _blend_forward(grid, splats, tables, pix, pix_inside):
  count = tables[2]

  def cond(carry):
    r, done = carry[0], carry[5]
    # A tile is active while its list has entries left and a pixel is open.
    active = (r * grid.chunk_size < count) & ~jnp.all(done, axis=1)
    return (r < grid.num_rounds) & jnp.any(active)

  body = functools.partial(_forward_round, grid, splats, tables, pix,
                           pix_inside)
  carry = jax.lax.while_loop(
      cond, body, _forward_init(grid, splats, pix, pix_inside))
  _, trans, color, depth, n_contrib, _, contrib = carry
  return color, depth, trans, n_contrib, contrib


def blend_autodiff(grid, splats, tables, pix, pix_inside):
  """The same blend as a fixed-length scan, for plain reverse-mode autodiff.

  `while_loop` cannot be reverse-differentiated, so this runs every round
  (no early exit) and autodiff stores every round's intermediates. It exists
  to measure what the custom VJP saves (bench_rasterizer.py) and as a second
  gradient check; training never uses it.
  """
  body = functools.partial(_forward_round, grid, splats, tables, pix,
                           pix_inside)
  carry = jax.lax.scan(lambda c, _: (body(c), None),
                       _forward_init(grid, splats, pix, pix_inside), None,
                       length=grid.num_rounds)[0]
  _, trans, color, depth, _, _, contrib = carry
  return color, depth, trans, contrib


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _blend(grid, means2d, conics, colors, opacities, depths, tables, pix,
           pix_inside):
  splats = (means2d, conics, colors, opacities, depths)
  color, depth, trans, _, contrib = _blend_forward(grid, splats, tables, pix,
                                                   pix_inside)
  return color, depth, trans, contrib


def _blend_fwd(grid, means2d, conics, colors, opacities, depths, tables, pix,
               pix_inside):
  splats = (means2d, conics, colors, opacities, depths)
  color, depth, trans, n_contrib, contrib = _blend_forward(
      grid, splats, tables, pix, pix_inside)
  residuals = (splats, tables, pix, color, depth, trans, n_contrib)
  return (color, depth, trans, contrib), residuals


def _blend_bwd(grid, residuals, cotangents):
  splats, tables, pix, color, depth, trans_final, n_contrib = residuals
  g_color, g_depth, g_trans, _ = cotangents   # contribution: not differentiable
  n = splats[0].shape[0]
  dtype = splats[0].dtype
  t, p = pix.shape[:2]
  # Linearised loss L = sum_k w_k v_k + T_final g_T with v = c.gC + z gD; the
  # total of the first term comes from the forward outputs.
  v_total = jnp.einsum("tpc,tpc->tp", color, g_color) + depth * g_depth
  tail_const = trans_final * g_trans

  def body(carry):
    r, trans, v_prefix, grads = carry
    c = _chunk(r, splats, tables + (grid.chunk_size,), pix)
    pos = r * grid.chunk_size + jnp.arange(grid.chunk_size)
    include = pos[None, :, None] < n_contrib[:, None, :]        # [T, B, P]
    alpha = jnp.where(include, c["alpha"], 0.0)
    t_before, t_after = _exclusive_cumprod(1.0 - alpha, trans)
    w = alpha * t_before
    v = (jnp.einsum("tbc,tpc->tbp", c["color"], g_color)
         + c["depth"][..., None] * g_depth[:, None, :])
    v_cum = v_prefix[:, None, :] + jnp.cumsum(w * v, axis=1)
    suffix = v_total[:, None, :] - v_cum + tail_const[:, None, :]
    g_alpha = jnp.where(include, t_before * v - suffix / (1.0 - alpha), 0.0)
    # alpha = min(0.99, o G) with G = exp(-power): the cap has zero slope.
    live = c["keep"] & (c["raw"] < MAX_ALPHA) & include
    g_raw = jnp.where(live, g_alpha, 0.0)
    g_opac = jnp.sum(g_raw * c["gauss_val"], axis=2)             # [T, B]
    g_power = -g_raw * c["raw"]                                  # [T, B, P]
    dx, dy = c["dx"], c["dy"]
    ca, cb, cc = (c["conic"][..., i][..., None] for i in range(3))
    g_conic = jnp.stack([jnp.sum(g_power * 0.5 * dx * dx, 2),
                         jnp.sum(g_power * dx * dy, 2),
                         jnp.sum(g_power * 0.5 * dy * dy, 2)], -1)
    g_mean = jnp.stack([jnp.sum(-g_power * (ca * dx + cb * dy), 2),
                        jnp.sum(-g_power * (cb * dx + cc * dy), 2)], -1)
    g_col = jnp.einsum("tbp,tpc->tbc", w, g_color)
    g_dep = jnp.einsum("tbp,tp->tb", w, g_depth)
    rows = jnp.concatenate([g_mean, g_conic, g_col, g_opac[..., None],
                            g_dep[..., None]], -1)               # [T, B, 10]
    rows = jnp.where(c["in_list"][..., None], rows, 0.0)
    grads = grads.at[c["gid"].reshape(-1)].add(rows.reshape(-1, 10))
    trans = t_after[:, -1]
    v_prefix = v_cum[:, -1, :]
    return r + 1, trans, v_prefix, grads

  max_contrib = jnp.max(n_contrib)

  def cond(carry):
    return carry[0] * grid.chunk_size < max_contrib

  init = (jnp.int32(0), jnp.ones((t, p), dtype), jnp.zeros((t, p), dtype),
          jnp.zeros((n, 10), dtype))
  grads = jax.lax.while_loop(cond, body, init)[3]
  return (grads[:, 0:2], grads[:, 2:5], grads[:, 5:8], grads[:, 8],
          grads[:, 9], None, None, None)


_blend.defvjp(_blend_fwd, _blend_bwd)


def rasterize(proj: project_lib.Projected, cam: camera_lib.Camera,
              background: jax.Array, cfg: config_lib.RenderConfig,
              custom_vjp: bool = True) -> RenderOutput:
  """Bins, sorts and blends projected splats into an image.

  `custom_vjp=False` swaps in `blend_autodiff` (benchmarks and tests only).
  """
  grid = _Grid(int(cam.width), int(cam.height), cfg.tile_budget,
               cfg.chunk_size)
  dtype = proj.means2d.dtype
  pix, pix_inside = _pixel_centers(grid, dtype)
  gauss, start, count, num_overflow, max_count = _bin(proj, grid)
  splats = (proj.means2d, proj.conics, proj.colors, proj.opacities,
            proj.depths)
  if custom_vjp:
    color, depth, trans, contrib = _blend(grid, *splats, (gauss, start, count),
                                          pix, pix_inside)
  else:
    color, depth, trans, contrib = blend_autodiff(
        grid, splats, (gauss, start, count), pix, pix_inside)
  trans = _untile(trans, grid)
  alpha = 1.0 - trans
  image = _untile(color, grid) + trans[..., None] * background.astype(dtype)
  depth = _untile(depth, grid)
  has_alpha = alpha > 0
  depth = jnp.where(has_alpha, depth / jnp.where(has_alpha, alpha, 1.0), 0.0)
  return RenderOutput(
      image=image, alpha=alpha, depth=depth, visible=contrib > 0,
      contribution=contrib, num_overflow=num_overflow.astype(jnp.int32),
      max_tile_count=max_count.astype(jnp.int32))


def render(params: gaussians.GaussianParams, alive: jax.Array,
           cam: camera_lib.Camera, background: jax.Array,
           cfg: config_lib.RenderConfig = config_lib.RenderConfig(),
           sh_degree: jax.Array | int | None = None) -> RenderOutput:
  """Renders the alive Gaussians seen from `cam`.

  Args:
    params: GaussianParams with capacity C.
    alive: bool [C], slots in use.
    cam: the camera; its width and height fix the output size.
    background: float [3], colour behind the Gaussians.
    cfg: rasterizer settings (near plane, tile budget, chunk size).
    sh_degree: int [], SH bands used (default: all stored bands).
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
  return rasterize(proj, cam, jnp.asarray(background), cfg)
