"""Alpha blending of depth-sorted tile lists, with work that follows each list.

A fixed set of `lanes` walks the tiles: each lane blends one tile's list
`chunk_size` entries per round and, when that tile's list ends or all its
pixels saturate, writes the tile out and takes the next tile from a queue
ordered longest list first. So a round costs lanes x chunk x tile pixel
evaluations however long the longest list is, and the number of rounds
follows the total work (sum of the lists) divided by the lanes, bounded
below by the longest list. Per pixel the order of operations is exactly the
sequential front-to-back blend, so results equal the dense reference.

The blend is a `jax.custom_vjp` whose backward pass walks the lists again
front to back with the same lane schedule (tiles queued by how many entries
their pixels blended), recomputing alphas instead of storing them. A round
keeps three per-pixel terms of each entry (lanes x chunk x tile pixels) and
sums them over the pixels once, after its chunk; memory is O(pixels + lanes
x chunk x tile pixels) plus O(N) gradient rows.

Colours may have any number of channels K (RGB is 3). The rasterizer adds
a fourth, the evidence probe (rasterize.rasterize), when a per-pixel map
known only after the render must be summed per Gaussian with the blending
weights: the backward pass's colour gradient of that channel is the sum.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp

from clipgs_jax.render import project as project_lib

MAX_ALPHA = 0.99               # cap so 1 / (1 - alpha) stays <= 100
# A pixel stops blending when its transmittance would fall below this; the
# remaining light cannot change an 8-bit colour visibly (reference 3DGS).
TRANSMITTANCE_THRESHOLD = 1e-4
# Automatic lane count: a sixth of the tiles. On the bird ds4 view at 16x16
# (135 tiles, lists of mean 198 / max 1,206 entries) the longest list sets the
# rounds (38); a sixth keeps them (40) with 23 lanes instead of 34, so the
# share of executed pixel evaluations that a tile needed rises from 0.645 to
# 0.906. Blend time did not move (a round's cost is half fixed overhead);
# BUILD_NOTES.md, "Rasterizer".
_AUTO_LANES_DIVISOR = 6
# Gradient columns besides the K colour channels: mean 2, conic 3, opacity,
# depth.
_GEOMETRY_COLUMNS = 7


@dataclasses.dataclass(frozen=True)
class Grid:
  """Static tiling of one image size (hashable: a custom_vjp static arg)."""
  width: int
  height: int
  tile_budget: int
  chunk_size: int
  lanes: int = 0               # 0: automatic (num_tiles / 6)
  tile: int = 8                # tile side in pixels (RenderConfig.tile_size)

  @property
  def pixels_per_tile(self) -> int:
    return self.tile * self.tile

  @property
  def tiles_x(self) -> int:
    return -(-self.width // self.tile)

  @property
  def tiles_y(self) -> int:
    return -(-self.height // self.tile)

  @property
  def num_tiles(self) -> int:
    return self.tiles_x * self.tiles_y

  @property
  def num_lanes(self) -> int:
    if self.lanes > 0:
      return min(self.lanes, self.num_tiles)
    return max(1, -(-self.num_tiles // _AUTO_LANES_DIVISOR))

  @property
  def num_rounds(self) -> int:
    """Rounds of the fixed-length autodiff blend (lists capped at K)."""
    return -(-self.tile_budget // self.chunk_size)


def power(dx, dy, a, b, c):
  """0.5 (a dx^2 + c dy^2) + b dx dy: the exponent of a splat with conic
  (a, b, c) at offset (dx, dy) from its mean (any broadcastable arrays)."""
  return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy


def alpha(pix, mean, conic, opacity):
  """Blend alpha of one entry per lane at every pixel of the lane's tile.

  Args:
    pix: float [L, P, 2]; mean: [L, 2]; conic: [L, 3]; opacity: [L].
  Returns:
    alpha, raw = opacity * gauss, gauss = exp(-power), keep: [L, P].
  """
  dx = pix[..., 0] - mean[:, None, 0]
  dy = pix[..., 1] - mean[:, None, 1]
  p = power(dx, dy, conic[:, None, 0], conic[:, None, 1], conic[:, None, 2])
  gauss = jnp.exp(-jnp.maximum(p, 0.0))
  raw = opacity[:, None] * gauss
  keep = (p >= 0) & (raw >= project_lib.ALPHA_THRESHOLD)
  a = jnp.where(keep, jnp.minimum(raw, MAX_ALPHA), 0.0)
  return a, raw, gauss, keep


def _pad_row(x, value):
  """Appends one dummy tile row (index T) filled with `value`."""
  return jnp.concatenate([x, jnp.full((1,) + x.shape[1:], value, x.dtype)])


def _entries(tiles, chunk, splats, gauss, start, length, chunk_size):
  """Gaussian ids and attributes of entries [c*B, (c+1)*B) of lane tiles."""
  k = chunk[:, None] * chunk_size + jnp.arange(chunk_size)
  in_list = k < length[tiles][:, None]                           # [L, B]
  gid = gauss[jnp.clip(start[tiles][:, None] + k, 0, gauss.shape[0] - 1)]
  return gid, in_list, tuple(x[gid] for x in splats)             # [L, B, ...]


def _take_tiles(lane_tile, head, queue, num_queued, none):
  """Gives every free lane the next queued tile; returns taken lanes too."""
  free = lane_tile == none
  slot = head + jnp.cumsum(free.astype(jnp.int32)) - 1
  take = free & (slot < num_queued)
  tile = jnp.where(take, queue[jnp.clip(slot, 0, queue.shape[0] - 1)],
                   lane_tile)
  return tile, head + jnp.sum(take, dtype=jnp.int32), take


def forward(grid, splats, tables, pix, pix_inside, emap):
  """Blends every tile; the lane loop of the module docstring.

  Args:
    grid: Grid.
    splats: (means2d [N, 2], conics [N, 3], colors [N, K], opacities [N],
      depths [N]).
    tables: (gauss int32 [M], start int32 [T], count int32 [T]): each tile's
      depth-sorted list is gauss[start : start + count].
    pix: float [T, P, 2] pixel centres; pix_inside: bool [T, P].
    emap: float [T, P] evidence map or None (then no evidence code is traced).
  Returns:
    color [T, P, K], depth [T, P], trans [T, P], n_contrib int32 [T, P],
    contrib [N], evidence [N] or None, rounds int32 [].
  """
  gauss, start, count = tables
  t, p = pix.shape[:2]
  lanes, chunk_size = grid.num_lanes, grid.chunk_size
  dtype = splats[0].dtype
  n, channels = splats[2].shape
  queue = jnp.argsort(-count, stable=True).astype(jnp.int32)
  num_queued = jnp.sum(count > 0, dtype=jnp.int32)
  start_p, count_p = _pad_row(start, 0), _pad_row(count, 0)
  pix_p, inside_p = _pad_row(pix, 0), _pad_row(pix_inside, False)
  emap_p = None if emap is None else _pad_row(emap, 0)

  def cond(c):
    return (c["head"] < num_queued) | jnp.any(c["tile"] != t)

  def body(c):
    tile, head, take = _take_tiles(c["tile"], c["head"], queue, num_queued, t)
    fresh = take[:, None]
    trans = jnp.where(fresh, 1.0, c["trans"])
    color = jnp.where(fresh[..., None], 0.0, c["color"])
    depth = jnp.where(fresh, 0.0, c["depth"])
    n_contrib = jnp.where(fresh, 0, c["n_contrib"])
    done = jnp.where(fresh, ~inside_p[tile], c["done"])
    chunk = jnp.where(take, 0, c["chunk"])
    gid, in_list, (means2d, conics, colors, opacities, depths) = _entries(
        tile, chunk, splats, gauss, start_p, count_p, chunk_size)
    pix_l = pix_p[tile]
    emap_l = None if emap_p is None else emap_p[tile]

    def entry(b, s):
      trans, color, depth, n_contrib, done, per_entry, per_ev = s
      a = alpha(pix_l, means2d[:, b], conics[:, b], opacities[:, b])[0]
      t_after = trans * (1.0 - a)
      include = ((t_after >= TRANSMITTANCE_THRESHOLD) & ~done
                 & in_list[:, b, None])
      w = jnp.where(include, a * trans, 0.0)                     # [L, P]
      color = color + w[..., None] * colors[:, b, None, :]
      depth = depth + w * depths[:, b, None]
      trans = jnp.where(include, t_after, trans)
      n_contrib = n_contrib + include
      # Out of list or below the transmittance floor: the pixel is finished.
      done = done | ~include
      per_entry = per_entry.at[:, b].set(jnp.sum(w, axis=1))
      if emap_l is not None:
        per_ev = per_ev.at[:, b].set(jnp.sum(w * emap_l, axis=1))
      return trans, color, depth, n_contrib, done, per_entry, per_ev

    zeros = jnp.zeros(in_list.shape, dtype)
    s = (trans, color, depth, n_contrib, done, zeros,
         None if emap_l is None else zeros)
    # Two entries per loop trip: 6-7 % faster steps at the same compile
    # time (bonsai ds2 and bird ds4; four, slower; BUILD_NOTES.md,
    # "Rasterizer").
    trans, color, depth, n_contrib, done, per_entry, per_ev = (
        jax.lax.fori_loop(0, chunk_size, entry, s, unroll=2))
    out = dict(c)
    out["contrib"] = c["contrib"].at[gid.reshape(-1)].add(
        jnp.where(in_list, per_entry, 0.0).reshape(-1))
    if emap_l is not None:
      out["evidence"] = c["evidence"].at[gid.reshape(-1)].add(
          jnp.where(in_list, per_ev, 0.0).reshape(-1))
    chunk = chunk + 1
    finished = (tile != t) & ((chunk * chunk_size >= count_p[tile])
                              | jnp.all(done, axis=1))
    dest = jnp.where(finished, tile, t)          # row t is a dump
    out["out_trans"] = c["out_trans"].at[dest].set(trans)
    out["out_color"] = c["out_color"].at[dest].set(color)
    out["out_depth"] = c["out_depth"].at[dest].set(depth)
    out["out_n"] = c["out_n"].at[dest].set(n_contrib)
    out.update(tile=jnp.where(finished, t, tile), head=head, chunk=chunk,
               trans=trans, color=color, depth=depth, n_contrib=n_contrib,
               done=done, rounds=c["rounds"] + 1)
    return out

  init = dict(
      tile=jnp.full((lanes,), t, jnp.int32), head=jnp.int32(0),
      chunk=jnp.zeros((lanes,), jnp.int32), rounds=jnp.int32(0),
      trans=jnp.ones((lanes, p), dtype),
      color=jnp.zeros((lanes, p, channels), dtype),
      depth=jnp.zeros((lanes, p), dtype),
      n_contrib=jnp.zeros((lanes, p), jnp.int32),
      done=jnp.ones((lanes, p), bool),
      out_trans=jnp.ones((t + 1, p), dtype),
      out_color=jnp.zeros((t + 1, p, channels), dtype),
      out_depth=jnp.zeros((t + 1, p), dtype),
      out_n=jnp.zeros((t + 1, p), jnp.int32),
      contrib=jnp.zeros((n,), dtype))
  if emap is not None:
    init["evidence"] = jnp.zeros((n,), dtype)
  c = jax.lax.while_loop(cond, body, init)
  return (c["out_color"][:t], c["out_depth"][:t], c["out_trans"][:t],
          c["out_n"][:t], c["contrib"], c.get("evidence"), c["rounds"])


def backward(grid, splats, tables, pix, color, depth, trans_final, n_contrib,
             g_color, g_depth, g_trans):
  """Gradient rows [N, 7 + K] of the linearised loss, and its rounds.

  Linearised loss L = sum_k w_k v_k + T_final g_T with v_k = c_k.gC + z_k gD
  per pixel. Walking front to back, the part of the first sum behind entry
  k is v_total minus the running prefix, so no list is stored.
  Columns: mean (2), conic (3), colour (K), opacity, depth.
  """
  gauss, start, _ = tables
  t, p = pix.shape[:2]
  lanes, chunk_size = grid.num_lanes, grid.chunk_size
  dtype = splats[0].dtype
  n, channels = splats[2].shape
  columns = _GEOMETRY_COLUMNS + channels
  need = jnp.max(n_contrib, axis=1)                              # [T]
  queue = jnp.argsort(-need, stable=True).astype(jnp.int32)
  num_queued = jnp.sum(need > 0, dtype=jnp.int32)
  v_total = jnp.einsum("tpc,tpc->tp", color, g_color) + depth * g_depth
  tail = trans_final * g_trans
  start_p, need_p = _pad_row(start, 0), _pad_row(need, 0)
  pix_p, n_contrib_p = _pad_row(pix, 0), _pad_row(n_contrib, 0)
  v_total_p, tail_p = _pad_row(v_total, 0), _pad_row(tail, 0)
  g_color_p, g_depth_p = _pad_row(g_color, 0), _pad_row(g_depth, 0)

  def cond(c):
    return (c[1] < num_queued) | jnp.any(c[0] != t)

  def body(c):
    tile, head, chunk, trans, v_prefix, grads, rounds = c
    tile, head, take = _take_tiles(tile, head, queue, num_queued, t)
    trans = jnp.where(take[:, None], 1.0, trans)
    v_prefix = jnp.where(take[:, None], 0.0, v_prefix)
    chunk = jnp.where(take, 0, chunk)
    gid, in_list, (means2d, conics, colors, opacities, depths) = _entries(
        tile, chunk, splats, gauss, start_p, need_p, chunk_size)
    pix_l, n_l, gc_l, gd_l = (pix_p[tile], n_contrib_p[tile], g_color_p[tile],
                              g_depth_p[tile])
    behind_l = v_total_p[tile] + tail_p[tile]

    def entry(b, s):
      trans, v_prefix, g_power_b, w_b, g_opac_b = s
      a, raw, gauss_v, keep = alpha(
          pix_l, means2d[:, b], conics[:, b], opacities[:, b])
      include = chunk[:, None] * chunk_size + b < n_l             # [L, P]
      a = jnp.where(include, a, 0.0)
      w = a * trans
      color_b = colors[:, b, None, :]
      v = color_b[..., 0] * gc_l[..., 0]
      for k in range(1, channels):
        v = v + color_b[..., k] * gc_l[..., k]
      v = v + depths[:, b, None] * gd_l
      v_prefix = v_prefix + w * v
      behind = behind_l - v_prefix
      g_alpha = jnp.where(include, trans * v - behind / (1.0 - a), 0.0)
      # alpha = min(0.99, o G), G = exp(-power): the cap has zero slope.
      g_raw = jnp.where(keep & (raw < MAX_ALPHA) & include, g_alpha, 0.0)
      # Per-pixel terms only: the sums over the tile's pixels run once per
      # chunk below. Summed here, each entry was ~10 small reduce and dot
      # kernels of its own (BUILD_NOTES.md, "Rasterizer").
      return (trans * (1.0 - a), v_prefix,
              g_power_b.at[:, b].set(-g_raw * raw), w_b.at[:, b].set(w),
              g_opac_b.at[:, b].set(g_raw * gauss_v))

    per_pixel = jnp.zeros(in_list.shape + (p,), dtype)            # [L, B, P]
    trans, v_prefix, g_power, w, g_opac = jax.lax.fori_loop(
        0, chunk_size, entry, (trans, v_prefix, per_pixel, per_pixel,
                               per_pixel), unroll=2)       # as in forward
    # power = a dx^2 / 2 + b dx dy + c dy^2 / 2 with dx = px - mean_x, so
    # every splat gradient is a conic-weighted moment of g_power over the
    # tile's pixels.
    dx = pix_l[:, None, :, 0] - means2d[:, :, None, 0]            # [L, B, P]
    dy = pix_l[:, None, :, 1] - means2d[:, :, None, 1]
    gx, gy = jnp.sum(g_power * dx, -1), jnp.sum(g_power * dy, -1)
    ca, cb, cc = conics[..., 0], conics[..., 1], conics[..., 2]
    rows = jnp.stack([
        -(ca * gx + cb * gy), -(cb * gx + cc * gy),
        0.5 * jnp.sum(g_power * dx * dx, -1), jnp.sum(g_power * dx * dy, -1),
        0.5 * jnp.sum(g_power * dy * dy, -1)]
        + [jnp.sum(w * gc_l[:, None, :, k], -1) for k in range(channels)]
        + [jnp.sum(g_opac, -1), jnp.sum(w * gd_l[:, None], -1)],
        -1)                                                  # [L, B, 7 + K]
    rows = jnp.where(in_list[..., None], rows, 0.0)
    grads = grads.at[gid.reshape(-1)].add(rows.reshape(-1, columns))
    chunk = chunk + 1
    finished = (tile != t) & (chunk * chunk_size >= need_p[tile])
    tile = jnp.where(finished, t, tile)
    return tile, head, chunk, trans, v_prefix, grads, rounds + 1

  init = (jnp.full((lanes,), t, jnp.int32), jnp.int32(0),
          jnp.zeros((lanes,), jnp.int32), jnp.ones((lanes, p), dtype),
          jnp.zeros((lanes, p), dtype), jnp.zeros((n, columns), dtype),
          jnp.int32(0))
  c = jax.lax.while_loop(cond, body, init)
  return c[5], c[6]


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def blend(grid, means2d, conics, colors, opacities, depths, tables, pix,
          pix_inside, emap):
  """Returns color [T, P, K], depth, trans [T, P], contrib [N], evidence."""
  splats = (means2d, conics, colors, opacities, depths)
  color, depth, trans, _, contrib, evidence, _ = forward(
      grid, splats, tables, pix, pix_inside, emap)
  return color, depth, trans, contrib, evidence


def _blend_fwd(grid, means2d, conics, colors, opacities, depths, tables, pix,
               pix_inside, emap):
  splats = (means2d, conics, colors, opacities, depths)
  color, depth, trans, n_contrib, contrib, evidence, _ = forward(
      grid, splats, tables, pix, pix_inside, emap)
  residuals = (splats, tables, pix, color, depth, trans, n_contrib)
  return (color, depth, trans, contrib, evidence), residuals


def _blend_bwd(grid, residuals, cotangents):
  splats, tables, pix, color, depth, trans, n_contrib = residuals
  # Contribution and evidence are not differentiable.
  g_color, g_depth, g_trans = cotangents[:3]
  grads, _ = backward(grid, splats, tables, pix, color, depth, trans,
                      n_contrib, g_color, g_depth, g_trans)
  k = 5 + splats[2].shape[1]
  return (grads[:, 0:2], grads[:, 2:5], grads[:, 5:k], grads[:, k],
          grads[:, k + 1], None, None, None, None)


blend.defvjp(_blend_fwd, _blend_bwd)


def blend_autodiff(grid, splats, tables, pix, pix_inside, emap=None):
  """The same blend as a fixed-length lockstep scan, for plain autodiff.

  `while_loop` cannot be reverse-differentiated, so every tile walks the
  first K = `tile_budget` entries of its list in lockstep (entries past K
  are dropped here) and autodiff stores every round's intermediates. It
  exists to measure what the custom VJP saves (bench.py) and as
  a second gradient check; training never uses it.
  """
  gauss, start, count = tables
  t, p = pix.shape[:2]
  dtype = splats[0].dtype
  tiles = jnp.arange(t, dtype=jnp.int32)
  count = jnp.minimum(count, grid.tile_budget)

  def round_(c, r):
    trans, color, depth, done, contrib, evidence = c
    gid, in_list, (means2d, conics, colors, opacities, depths) = _entries(
        tiles, jnp.full((t,), r), splats, gauss, start, count,
        grid.chunk_size)

    def entry(b, s):
      trans, color, depth, done, per_entry, per_ev = s
      a = alpha(pix, means2d[:, b], conics[:, b], opacities[:, b])[0]
      t_after = trans * (1.0 - a)
      include = ((t_after >= TRANSMITTANCE_THRESHOLD) & ~done
                 & in_list[:, b, None])
      w = jnp.where(include, a * trans, 0.0)
      color = color + w[..., None] * colors[:, b, None, :]
      depth = depth + w * depths[:, b, None]
      trans = jnp.where(include, t_after, trans)
      done = done | ~include
      per_entry = per_entry.at[:, b].set(jnp.sum(w, axis=1))
      if emap is not None:
        per_ev = per_ev.at[:, b].set(jnp.sum(w * emap, axis=1))
      return trans, color, depth, done, per_entry, per_ev

    zeros = jnp.zeros(in_list.shape, dtype)
    trans, color, depth, done, per_entry, per_ev = jax.lax.fori_loop(
        0, grid.chunk_size, entry,
        (trans, color, depth, done, zeros, None if emap is None else zeros))
    contrib = contrib.at[gid.reshape(-1)].add(
        jnp.where(in_list, per_entry, 0.0).reshape(-1))
    if emap is not None:
      evidence = evidence.at[gid.reshape(-1)].add(
          jnp.where(in_list, per_ev, 0.0).reshape(-1))
    return (trans, color, depth, done, contrib, evidence), None

  zeros_n = jnp.zeros((splats[0].shape[0],), dtype)
  init = (jnp.ones((t, p), dtype),
          jnp.zeros((t, p, splats[2].shape[1]), dtype),
          jnp.zeros((t, p), dtype), ~pix_inside, zeros_n,
          None if emap is None else zeros_n)
  trans, color, depth, _, contrib, evidence = jax.lax.scan(
      round_, init, jnp.arange(grid.num_rounds))[0]
  return color, depth, trans, contrib, evidence
