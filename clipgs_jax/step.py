"""The train step: B >= 1 views, dealt into lanes over D >= 1 devices.

Every run trains with this one step. train.batch_size = B views per step,
dealt into lanes over a device mesh (sharding.py): B = 1 is a batch of
one, one device a mesh of one, photos of one size a canvas with no
padding. Each device renders and differentiates its lanes' views
(view.render_and_grad; when it holds several, vmapped together on an
accelerator and one after another, lax.scan, on a CPU: `lanes_vmapped`),
then the step combines them as one optimisation step:
  * the loss is the mean of the views' losses: the views' gradients are
    summed on each device and across devices (psum) and divided by B, and
    every device applies the same Adam update to its replicated state;
  * the densification statistics take every view separately, as B
    one-view steps would: grad_accum gains |d L_v / d NDC xy| of each
    view's own loss L_v (B times the gradient of the batch's mean loss
    with respect to that view's splats: gsplat's normalisation, so the
    3DGS threshold keeps its meaning), denom gains 1 for each view that
    saw the Gaussian, max_radius the largest radius of the step;
  * semantic evidence accumulates every view of the batch (each view's
    increment, summed), and the residual map's histogram takes every
    view's residuals before its one update per step; the learned map's
    classifier takes one Adam step on the mean of its views' gradients;
  * the step counter counts batches, so every schedule (learning rates,
    densification, SH degree, the semantic schedule) counts optimisation
    steps.
A mesh of one device runs the device's step without shard_map (no
collectives). With B = 1 it is the one-view 3DGS step: lane 0 has the
run's key (view.lane_key), so it visits the views in the one-view order,
and the sums and the division by B are exact. Equality tests and
measured cost: BUILD_NOTES.md, "Multi-device training".
"""

import functools

import jax
import jax.numpy as jnp
from jax.sharding import PartitionSpec

from clipgs_jax import camera as camera_lib
from clipgs_jax import compiled
from clipgs_jax import config as config_lib
from clipgs_jax import densify
from clipgs_jax import guidance
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import optim
from clipgs_jax import sh
from clipgs_jax import sharding
from clipgs_jax import state as state_lib
from clipgs_jax import view as view_lib
from clipgs_jax.maps import residual as residual_lib

# The per-view output that carries each view's map memory (not a metric).
_MEMORY = "map_memory"
# Per-view metrics the step reports as their mean over the batch; the
# per-step keys (guidance.per_step_keys) are kept per view.
_MEAN_KEYS = ("loss", "l1", "ssim", "psnr", "semantic_loss",
              "agreement_share")


def _combine(a, b):
  """Sums of two views' (grads, DensifyStats, evidence, histogram), the
  largest radius of both."""
  total = jax.tree.map(jnp.add, a, b)
  dens = total[1].replace(max_radius=jnp.maximum(a[1].max_radius,
                                                 b[1].max_radius))
  return (total[0], dens) + total[2:]


def lanes_vmapped(mesh) -> bool:
  """Whether a device renders its lanes together (vmap) rather than one
  after another (lax.scan): on accelerators, not on CPUs. Measured on an
  H200 (bird ds4): vmap gives 1.19x / 1.79x the views per second of the
  scan at 2 / 4 lanes; on XLA:CPU it costs 4x, as every branch of the
  rasterizer's sort-buffer switch and the longest tile's blend loop then
  run for every lane (BUILD_NOTES.md, "Multi-device training")."""
  return mesh.devices.flat[0].platform != "cpu"


def device_step(state: state_lib.TrainState, lanes: sharding.Lanes, scorer,
                *, cfg: config_lib.Config, num_devices: int,
                vmap_lanes: bool = False):
  """One optimisation step, as one device runs it (inside shard_map).

  Args:
    state: the replicated TrainState.
    lanes: this device's B / num_devices lanes (sharding.Lanes).
    scorer: the guidance scorer with this device's lanes of its per-view
      fields (sharding.scorer_lanes), or None.
    cfg: the config (static).
    num_devices: D, the mesh's size.
    vmap_lanes: render the device's lanes together (`lanes_vmapped`).
  Returns:
    (state, metrics), both the same on every device. The metrics: loss,
    l1, ssim, psnr (means over the batch), num_overflow (summed),
    max_tile_count, num_alive, sh_degree, means_lr, grad_norm/<field>;
    with a scorer semantic_loss and the scorer's per-view values, with the
    residual map residual_threshold. The per-step keys (view, scored and
    scores: guidance.per_step_keys) stay per view: int / float [B].
  """
  guidance.check_scorer(cfg.semantic, scorer, "step.device_step")
  batch = cfg.train.batch_size
  local = batch // num_devices
  step = state.step
  capacity = state.capacity
  height, width = lanes.images.shape[2:4]
  bg = view_lib.background(state.key, step, cfg)
  degree = sh.active_degree(step, cfg.densify.sh_degree_every,
                           cfg.gaussians.sh_degree)
  # A mesh of one device runs this without shard_map: no collectives.
  across = num_devices > 1
  first = jax.lax.axis_index(sharding.AXIS) * local if across else 0
  remembers = scorer is not None and cfg.uses_memory

  def one_view(i):
    lane = first + i
    key = view_lib.lane_key(state.key, lane)
    pos = view_lib.lane_view(key, step, lanes.counts[i],
                             lanes.images.shape[1])
    cam = camera_lib.camera_at(jax.tree.map(lambda x: x[i], lanes.cameras),
                               pos)
    target = lanes.images[i, pos]
    canvas, valid, w, h = None, None, width, height
    if lanes.sizes is not None:
      size = lanes.sizes[i, pos]
      valid = sharding.valid_mask(size, height, width)
      canvas, w, h = (size, valid), size[0], size[1]
    view_scorer = sharding.scorer_at(scorer, i)
    # The view's index in the training views (as the metric "view").
    index = lane + pos * batch
    memory = (state.maps.memory[index] if remembers else None)
    vp = view_lib.render_and_grad(
        state, view_scorer, cfg, view=pos, cam=cam, target=target, bg=bg,
        degree=degree, key=key, canvas=canvas, memory=memory)
    proj = jax.lax.stop_gradient(vp.proj)
    seen = densify.on_screen(proj, w, h) & state.alive
    dens = densify.accumulate(state_lib.DensifyStats.zeros(capacity),
                              vp.grad2d, seen, densify.screen_radius(proj),
                              w, h)
    metrics = {"loss": vp.loss, "l1": vp.terms["l1"],
               "ssim": vp.terms["ssim"],
               "psnr": metrics_lib.psnr(vp.out.image, target, valid),
               "num_overflow": vp.out.num_overflow,
               "max_tile_count": vp.out.max_tile_count,
               "view": index}
    if remembers:
      metrics[_MEMORY] = vp.memory
    evidence, hist = None, None
    if scorer is not None:
      evidence, extra = view_lib.semantic_increment(
          vp, view_scorer, view=pos, step=step, cam=cam, bg=bg,
          target=target, cfg=cfg, valid=valid)
      metrics.update(extra, semantic_loss=vp.terms["semantic_loss"])
      if vp.rmap is not None:
        hist = residual_lib.counts(vp.rmap.residual, valid)
    return (vp.grads, dens, evidence, hist, vp.classifier_grad), metrics

  if local == 1:
    sums, per_view = one_view(0)
    per_view = jax.tree.map(lambda x: x[None], per_view)
  elif vmap_lanes:
    outs, per_view = jax.vmap(one_view)(jnp.arange(local))
    # Combined lane by lane in the scan's order, by the scan's rule.
    sums = functools.reduce(
        _combine, [jax.tree.map(lambda x, i=i: x[i], outs)
                   for i in range(local)])
  else:
    # The device's views one after another: one compiled view, whatever
    # the batch.
    def body(carry, i):
      out, metrics = one_view(i)
      return _combine(carry, out), metrics
    zeros = (jax.tree.map(jnp.zeros_like, state.params),
             state_lib.DensifyStats.zeros(capacity),
             None if scorer is None else state_lib.SemanticStats.zeros(
                 capacity),
             (jnp.zeros((residual_lib.HISTOGRAM_BINS,), jnp.float32)
              if cfg.uses_residual and scorer is not None
              else None),
             (jax.tree.map(jnp.zeros_like, state.maps.classifier.params)
              if cfg.uses_learned and scorer is not None else None))
    sums, per_view = jax.lax.scan(body, zeros, jnp.arange(local))
  grads, dens, evidence, hist, classifier_grad = sums
  # Not a metric: each view's memory after the step, written back below.
  memory = per_view.pop(_MEMORY) if remembers else None
  grad_accum, denom, max_radius = dens.grad_accum, dens.denom, dens.max_radius
  if across:
    grads, grad_accum, denom, evidence, hist, classifier_grad = jax.lax.psum(
        (grads, grad_accum, denom, evidence, hist, classifier_grad),
        sharding.AXIS)
    max_radius = jax.lax.pmax(max_radius, sharding.AXIS)
    per_view = jax.lax.all_gather(per_view, sharding.AXIS, tiled=True)
    if remembers:
      memory = jax.lax.all_gather(memory, sharding.AXIS, tiled=True)

  params, opt_state, grad_norms = optim.apply(state, grads, cfg, batch)
  old = state.densify
  stats = state_lib.DensifyStats(
      grad_accum=old.grad_accum + grad_accum, denom=old.denom + denom,
      max_radius=jnp.maximum(old.max_radius, max_radius))
  semantic_stats, maps = state.semantic, state.maps
  if evidence is not None:
    semantic_stats = jax.tree.map(jnp.add, state.semantic, evidence)
  if hist is not None:
    maps = view_lib.update_maps(maps, cfg, hist, classifier_grad)
  if remembers:
    maps = maps.replace(memory=maps.memory.at[per_view["view"]].set(memory))
  metrics = {k: (jnp.mean(v) if k in _MEAN_KEYS else v)
             for k, v in per_view.items()}
  metrics.update(
      num_overflow=jnp.sum(per_view["num_overflow"]),
      max_tile_count=jnp.max(per_view["max_tile_count"]),
      num_alive=jnp.sum(state.alive, dtype=jnp.int32), sh_degree=degree,
      means_lr=optim.means_lr(step, cfg.optim, cfg.scene_extent,
                              cfg.train.steps))
  if cfg.uses_residual:
    metrics["residual_threshold"] = state.maps.threshold
  metrics.update(grad_norms)
  new_state = state.replace(params=params, opt_state=opt_state,
                            densify=stats, semantic=semantic_stats,
                            step=step + 1, maps=maps)
  return new_state, metrics


def train_step(state: state_lib.TrainState, lanes: sharding.Lanes, scorer,
               *, cfg: config_lib.Config, mesh, vmap_lanes: bool):
  """The train step: device_step on every device of `mesh` (shard_map),
  the state and metrics replicated, the lanes and the scorer's per-view
  fields sharded; on a mesh of one device, device_step itself."""
  body = functools.partial(device_step, cfg=cfg, num_devices=mesh.size,
                           vmap_lanes=vmap_lanes)
  if mesh.size == 1:
    return body(state, lanes, scorer)
  # check_vma off: the rasterizer's loops carry values that would all need
  # marking as varying over the mesh; the outputs are replicated because
  # they are made from psums and the replicated state only.
  return jax.shard_map(
      body, mesh=mesh,
      in_specs=(PartitionSpec(), sharding.lanes_specs(lanes),
                sharding.scorer_specs(scorer)),
      out_specs=PartitionSpec(), check_vma=False)(state, lanes, scorer)


@functools.lru_cache(maxsize=None)
def _make(cfg: config_lib.Config, mesh, vmap_lanes: bool):
  return jax.jit(functools.partial(train_step, cfg=cfg, mesh=mesh,
                                   vmap_lanes=vmap_lanes),
                 donate_argnums=(0,))


def make_train_step(cfg: config_lib.Config, mesh,
                    vmap_lanes: bool | None = None):
  """Jitted train_step(state, lanes, scorer) -> (state, metrics); the
  state is donated, the scorer (frozen weights or maps) is not.

  Cached by the config's compiled part (compiled.py), the mesh
  and `vmap_lanes` (None: `lanes_vmapped(mesh)`), so every caller whose
  config differs only in what the step does not read (data, eval, seed,
  cadences, the prune rule) shares one compiled step; it recompiles only
  when the capacity changes.
  """
  if vmap_lanes is None:
    vmap_lanes = lanes_vmapped(mesh)
  return _make(compiled.compiled_part(
      cfg, compiled.NOT_IN_STEP), mesh, vmap_lanes)


make_train_step.cache_clear = _make.cache_clear


def for_scene(cfg: config_lib.Config, scene, state: state_lib.TrainState,
              scorer=None, devices=None):
  """(jitted step, lanes, state, scorer) that train a scene: the training
  views dealt into lanes over the mesh of `devices` (sharding.make_mesh;
  default every device, one for B = 1), the state replicated and the
  scorer's per-view fields dealt like the views. Then

    state, metrics = step(state, lanes, scorer)

  is one optimisation step.
  """
  mesh = sharding.make_mesh(cfg.train.batch_size, devices)
  lanes, rows = sharding.lanes_of(scene, cfg.train.batch_size, mesh)
  height, width = lanes.images.shape[2:4]
  return (make_train_step(cfg, mesh), lanes, sharding.replicate(state, mesh),
          sharding.scorer_lanes(scorer, rows, height, width, mesh))
