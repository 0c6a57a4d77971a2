"""Adaptive density control at a fixed capacity (3DGS).

The densification statistics (`state.DensifyStats`) are accumulated by the
train step (`accumulate`) and read here every `every` steps: rows with a
large positional gradient are cloned or split into free slots, faint or
oversized rows are pruned. Every row edit goes through `state.write_rows`,
so parameters, Adam moments and per-row statistics move together.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import compiled
from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import optim
from clipgs_jax import state as state_lib
from clipgs_jax import tree_util
from clipgs_jax.render import project as project_lib

# Radius of a splat = this many standard deviations along its major axis
# (the 3DGS convention for the screen-size statistic).
RADIUS_SIGMAS = 3.0
# Floor of the eigenvalue discriminant, as in the 3DGS radius: keeps the
# square root away from negative rounding error for near-isotropic splats.
_DISCRIMINANT_FLOOR = 0.1


def screen_radius(proj: project_lib.Projected) -> jax.Array:
  """float [C], 3 sigma of each splat's major axis in pixels (0 if culled)."""
  a, b, c = proj.conics[:, 0], proj.conics[:, 1], proj.conics[:, 2]
  det_conic = a * c - b * b
  ok = proj.valid & (det_conic > 0)
  inv = 1.0 / jnp.where(ok, det_conic, 1.0)
  # Covariance = inverse conic: [[c, -b], [-b, a]] / det.
  var_x, var_y, det_cov = c * inv, a * inv, inv
  mid = 0.5 * (var_x + var_y)
  lam = mid + jnp.sqrt(jnp.maximum(mid * mid - det_cov, _DISCRIMINANT_FLOOR))
  return jnp.where(ok, RADIUS_SIGMAS * jnp.sqrt(jnp.maximum(lam, 0.0)), 0.0)


def on_screen(proj: project_lib.Projected, width: int, height: int
              ) -> jax.Array:
  """bool [C], the splat's 1/255 box overlaps the image (3DGS 'radii > 0')."""
  lo = proj.means2d - proj.extents
  hi = proj.means2d + proj.extents
  return (proj.valid & (hi[:, 0] > 0) & (hi[:, 1] > 0) & (lo[:, 0] < width)
          & (lo[:, 1] < height))


def accumulate(stats: state_lib.DensifyStats, grad_means2d: jax.Array,
               seen: jax.Array, radius: jax.Array, width: int, height: int
               ) -> state_lib.DensifyStats:
  """Adds one view's positional gradients to the statistics.

  Args:
    stats: the running statistics.
    grad_means2d: float [C, 2], d loss / d means2d in pixels.
    seen: bool [C], rows whose splat overlapped the image in this view.
    radius: float [C], screen radius in pixels this view.
    width, height: image size; the gradient is converted to normalised
      device coordinates (pixel = (ndc + 1) * size / 2 - 0.5), where the
      3DGS threshold 2e-4 is defined: d/d ndc = d/d pixel * size / 2.
  """
  scale = jnp.array([0.5 * width, 0.5 * height], grad_means2d.dtype)
  norm = jnp.linalg.norm(grad_means2d * scale, axis=-1)
  return state_lib.DensifyStats(
      grad_accum=stats.grad_accum + jnp.where(seen, norm, 0.0),
      denom=stats.denom + seen.astype(jnp.float32),
      max_radius=jnp.where(seen, jnp.maximum(stats.max_radius, radius),
                           stats.max_radius))


def _wanted(state: state_lib.TrainState, cfg: config_lib.Config):
  """bool [C] rows asking for a clone or split, and their mean gradient."""
  stats = state.densify
  mean_grad = stats.grad_accum / jnp.maximum(stats.denom, 1.0)
  want = (state.alive & (stats.denom > 0)
          & (mean_grad >= cfg.densify.grad_threshold))
  return want, mean_grad


def count_requests(state: state_lib.TrainState, *, cfg: config_lib.Config
                   ) -> tuple[jax.Array, jax.Array]:
  """(int32 [] clones + splits the next densify asks for, int32 [] free slots)."""
  want, _ = _wanted(state, cfg)
  return (jnp.sum(want, dtype=jnp.int32),
          jnp.sum(~state.alive, dtype=jnp.int32))


def densify(state: state_lib.TrainState, key: jax.Array, *,
            cfg: config_lib.Config):
  """One adaptive density control step: clone, split, prune, reset stats.

  Rows whose mean NDC positional gradient reaches the threshold are cloned
  (largest scale <= percent_dense x extent: an exact copy into a free slot)
  or split (larger: two children sampled from the Gaussian, scales / 1.6;
  one replaces the parent in place, one goes into a free slot). When free
  slots run out, the rows with the largest gradients are served first and
  the rest are counted in `num_unplaced`. Then rows with opacity <
  min_opacity are pruned, and after the first opacity reset also rows
  larger than max_world_size x extent or max_screen_size pixels. The
  densification statistics restart from zero.

  Returns:
    (state, info) with info int32 [] counts num_cloned, num_split,
    num_pruned and num_unplaced.
  """
  d = cfg.densify
  extent = cfg.scene_extent
  capacity = state.alive.shape[0]
  rows = jnp.arange(capacity, dtype=jnp.int32)
  params = state.params
  want, mean_grad = _wanted(state, cfg)

  # Wanted rows ranked by decreasing gradient; rank r takes the r-th free
  # slot if there is one.
  score = jnp.where(want, mean_grad, -jnp.inf)
  order = jnp.argsort(-score, stable=True)
  rank = jnp.zeros((capacity,), jnp.int32).at[order].set(rows)
  num_free = jnp.sum(~state.alive, dtype=jnp.int32)
  placed = want & (rank < num_free)
  free_slots = jnp.nonzero(~state.alive, size=capacity,
                           fill_value=capacity)[0].astype(jnp.int32)
  dst = jnp.where(placed, free_slots[jnp.minimum(rank, capacity - 1)],
                  capacity)                                      # [C]

  act = gaussians.activate(params)
  small = jnp.max(act.scales, axis=-1) <= d.percent_dense * extent
  clone = placed & small
  split = placed & ~small
  noise = jax.random.normal(key, (2, capacity, 3), params.means.dtype)
  offsets = jnp.einsum("cij,kcj->kci", act.rotations,
                       noise * act.scales[None])                 # [2, C, 3]
  child_log_scales = params.log_scales - np.log(d.split_scale)
  child_in_place = params.replace(means=params.means + offsets[0],
                                  log_scales=child_log_scales)
  child_free = params.replace(means=params.means + offsets[1],
                              log_scales=child_log_scales)
  to_free_slot = tree_util.tree_select(split, child_free, params)
  state = state_lib.write_rows(state, dst, to_free_slot, alive=True)
  state = state_lib.write_rows(state, jnp.where(split, rows, capacity),
                               child_in_place, alive=True)

  act = gaussians.activate(state.params)
  after_reset = (d.opacity_reset_every > 0) & (
      state.step > d.opacity_reset_every)
  too_big = ((jnp.max(act.scales, axis=-1) > d.max_world_size * extent)
             | (state.densify.max_radius > d.max_screen_size))
  prune = state.alive & ((act.opacities < d.min_opacity)
                         | (after_reset & too_big))
  state = state_lib.write_rows(state, jnp.where(prune, rows, capacity),
                               None, alive=False)
  state = state.replace(densify=state_lib.DensifyStats.zeros(capacity))
  info = {
      "num_cloned": jnp.sum(clone, dtype=jnp.int32),
      "num_split": jnp.sum(split, dtype=jnp.int32),
      "num_pruned": jnp.sum(prune, dtype=jnp.int32),
      "num_unplaced": jnp.sum(want & ~placed, dtype=jnp.int32),
  }
  return state, info


def reset_opacity(state: state_lib.TrainState, *, cfg: config_lib.Config
                  ) -> state_lib.TrainState:
  """Opacity -> min(opacity, opacity_reset_to) and zero opacity moments."""
  target = cfg.densify.opacity_reset_to
  logit = float(np.log(target / (1.0 - target)))
  params = state.params.replace(
      opacity_logits=jnp.minimum(state.params.opacity_logits, logit))
  return state.replace(
      params=params,
      opt_state=optim.zero_field(state.opt_state, "opacity_logits",
                                 state.alive.shape[0]))


def _control_active(step, cfg: config_lib.Config):
  """Density control (densify, reset) may run after `step` finished steps:
  0 < step < min(densify.stop, train.steps). An int or a traced int32."""
  return (0 < step) & (step < min(cfg.densify.stop, cfg.train.steps))


def due(step: int, cfg: config_lib.Config) -> tuple[bool, bool]:
  """Host-side: (densify?, reset opacity?) after `step` finished steps.

  Both run only while step < densify.stop and before the last step (a
  reset right before the end would leave a washed-out model); densify
  after `start`, every `every` steps; reset every opacity_reset_every.
  """
  d = cfg.densify
  active = _control_active(step, cfg)
  do_densify = active and step > d.start and step % d.every == 0
  do_reset = (active and d.opacity_reset_every > 0
              and step % d.opacity_reset_every == 0)
  return do_densify, do_reset


def since_reset_within(step, window: int, cfg: config_lib.Config):
  """Whether the last opacity reset (densify.due) came at most `window`
  steps before `step` finished steps: 0 <= step - R < window.

  Works on a Python int (host) and on a traced int32 (inside the step).
  """
  every = cfg.densify.opacity_reset_every
  if every <= 0 or window <= 0:
    return False
  last = (step // every) * every
  return _control_active(last, cfg) & (step - last < window)


@compiled.cache_by_compiled_part()
def make_densify(cfg: config_lib.Config):
  """Jitted densify(state, key) -> (state, info); the state is donated."""
  return jax.jit(functools.partial(densify, cfg=cfg), donate_argnums=(0,))


@compiled.cache_by_compiled_part()
def make_reset_opacity(cfg: config_lib.Config):
  """Jitted reset_opacity(state) -> state; the state is donated."""
  return jax.jit(functools.partial(reset_opacity, cfg=cfg),
                 donate_argnums=(0,))


@compiled.cache_by_compiled_part()
def make_count_requests(cfg: config_lib.Config):
  """Jitted count_requests(state) -> (requests, free slots)."""
  return jax.jit(functools.partial(count_requests, cfg=cfg))
