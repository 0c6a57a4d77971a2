"""The pure train step and `fit`, the training loop."""

import dataclasses
import functools
import logging
import math
import os

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import batch_step
from clipgs_jax import camera as camera_lib
from clipgs_jax import config as config_lib
from clipgs_jax import densify
from clipgs_jax import gaussians
from clipgs_jax import guidance
from clipgs_jax import initialize
from clipgs_jax import loop
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import optim
from clipgs_jax import residual as residual_lib
from clipgs_jax import sh
from clipgs_jax import sharding
from clipgs_jax import state as state_lib
from clipgs_jax import summary
from clipgs_jax import view as view_lib
from clipgs_jax.data import scene as scene_lib

_log = logging.getLogger(__name__)

# The fold_in tag of densification's stream of the run's key (view.py
# holds the others).
_DENSIFY_STREAM = 3

CHECKPOINT_NAME = "checkpoint.npz"


@flax.struct.dataclass
class Batch:
  """All training views, on device for the whole run.

  Attributes:
    images: float32 [V, H, W, 3] in [0, 1].
    cameras: Camera whose array fields are stacked along a leading [V].
  """
  images: jax.Array
  cameras: camera_lib.Camera


def make_batch(views) -> Batch:
  """Device-resident Batch from a data.scene.Views (or any object with
  `images` [V, H, W, 3] and stacked `cameras`)."""
  images = np.asarray(views.images, np.float32)
  if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] == 0:
    raise ValueError(f"train.make_batch: views.images must be [V, H, W, 3] "
                     f"with V > 0, got {images.shape}.")
  cams = views.cameras
  if (cams.width, cams.height) != (images.shape[2], images.shape[1]):
    raise ValueError(f"train.make_batch: cameras are {cams.width}x"
                     f"{cams.height} but images are {images.shape[2]}x"
                     f"{images.shape[1]}.")
  cams = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), cams)
  return Batch(images=jnp.asarray(images), cameras=cams)


def init_state(cfg: config_lib.Config, params: gaussians.GaussianParams,
               alive) -> state_lib.TrainState:
  """Step-0 state: zero moments and statistics, the run's key from seed."""
  if not cfg.scene_extent > 0:
    raise ValueError("train.init_state: cfg.scene_extent must be positive; "
                     "call train.resolve(cfg, scene) first.")
  alive = jnp.asarray(alive, bool)
  gaussians.validate(params, alive)
  params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), params)
  capacity = alive.shape[0]
  return state_lib.TrainState(
      params=params, alive=alive,
      opt_state=optim.for_run(cfg).init(params),
      densify=state_lib.DensifyStats.zeros(capacity),
      semantic=state_lib.SemanticStats.zeros(capacity),
      step=jnp.zeros((), jnp.int32),
      key=jax.random.key(cfg.train.seed),
      maps=(residual_lib.ResidualState.initial()
            if cfg.semantic.uses_residual else None))


def train_step(state: state_lib.TrainState, batch: Batch, scorer=None, *,
               cfg: config_lib.Config
               ) -> tuple[state_lib.TrainState, dict[str, jax.Array]]:
  """One optimisation step on one training view.

  Renders the view and differentiates its loss (view.render_and_grad),
  applies Adam, and accumulates the densification statistics. With a
  scorer (semantic guidance on) the same render is scored and accumulated
  into state.semantic when due; without one the step is exactly the
  vanilla 3DGS step. (batch_step: B views per step, over devices.)

  Args:
    state: the TrainState (donated by make_train_step).
    batch: all training views.
    scorer: None, or a guidance scorer (frozen; never differentiated).
    cfg: the config (static).
  """
  guidance.check_scorer(cfg.semantic, scorer, "train.train_step")
  num_views, height, width = batch.images.shape[:3]
  step = state.step
  view = view_lib.view_index(state.key, step, num_views)
  cam = camera_lib.camera_at(batch.cameras, view)
  target = batch.images[view]
  bg = view_lib.background(state.key, step, cfg)
  degree = sh.active_degree(step, cfg.densify.sh_degree_every,
                           cfg.gaussians.sh_degree)
  vp = view_lib.render_and_grad(
      state, scorer, cfg, view=view, cam=cam, target=target, bg=bg,
      degree=degree, key=state.key)
  params, opt_state, grad_norms = optim.apply(state, vp.grads, cfg)

  out = vp.out
  proj = jax.lax.stop_gradient(vp.proj)
  seen = densify.on_screen(proj, width, height) & state.alive
  stats = densify.accumulate(state.densify, vp.grad2d, seen,
                             densify.screen_radius(proj), width, height)
  metrics = {
      "loss": vp.loss, "l1": vp.terms["l1"], "ssim": vp.terms["ssim"],
      "psnr": metrics_lib.psnr(out.image, target),
      "num_alive": jnp.sum(state.alive, dtype=jnp.int32),
      "num_overflow": out.num_overflow,
      "max_tile_count": out.max_tile_count,
      "sh_degree": degree,
      "means_lr": optim.means_lr(step, cfg.optim, cfg.scene_extent,
                                 cfg.train.steps),
  }
  metrics.update(grad_norms)
  semantic_stats, maps = state.semantic, state.maps
  if scorer is not None:
    increment, extra = view_lib.semantic_increment(
        vp, scorer, view=view, step=step, cam=cam, bg=bg, target=target,
        cfg=cfg)
    semantic_stats = jax.tree.map(jnp.add, state.semantic, increment)
    metrics.update(extra, view=view,
                   semantic_loss=vp.terms["semantic_loss"])
  if vp.rmap is not None:
    maps = view_lib.update_maps(maps, cfg.semantic, res=vp.rmap.residual)
    metrics["residual_threshold"] = state.maps.threshold
  new_state = state.replace(params=params, opt_state=opt_state,
                            densify=stats, semantic=semantic_stats,
                            step=step + 1, maps=maps)
  return new_state, metrics


@config_lib.cache_by_compiled_part(
    semantic_dropped=config_lib.SEMANTIC_FIELDS_NOT_IN_STEP)
def make_train_step(cfg: config_lib.Config):
  """Jitted train_step(state, batch, scorer=None) -> (state, metrics).

  The state is donated; the scorer (frozen CLIP weights or masks) is not.

  Cached by the config's compiled part, so every caller whose config
  differs only in what the step does not read (data, eval, seed, cadences,
  the prune rule) shares one compiled step (it recompiles only when the
  capacity changes).
  """
  return jax.jit(functools.partial(train_step, cfg=cfg), donate_argnums=(0,))


# ----------------------------------------------------------------------------
# Host loop.


def resolve(cfg: config_lib.Config, scene) -> config_lib.Config:
  """Fills the scene-dependent config fields (scene_extent) from `scene`."""
  if cfg.scene_extent > 0:
    return cfg
  extent = float(scene.extent)
  if not extent > 0 or not math.isfinite(extent):
    raise ValueError(f"train.resolve: scene extent {extent} is not positive; "
                     "the scene needs at least two distinct cameras, or set "
                     "Config.scene_extent.")
  return dataclasses.replace(cfg, scene_extent=extent)


def initial_state(cfg: config_lib.Config, scene) -> state_lib.TrainState:
  """Step-0 state from the scene's points (random points if it has none)."""
  cams = scene_lib.all_train_cameras(scene)
  centers = -np.einsum("vji,vj->vi", np.asarray(cams.rotation, np.float64),
                       np.asarray(cams.translation, np.float64))
  points = getattr(scene, "points", None)
  params, alive = initialize.initialize(
      points, getattr(scene, "point_colors", None), centers, cfg.gaussians,
      seed=cfg.train.seed)
  return init_state(cfg, params, alive)


def batched(cfg: config_lib.Config, scene) -> bool:
  """Whether `scene` trains with batch_step: more than one view per step,
  photos of different sizes, or a process holding only its own views."""
  return (cfg.train.batch_size > 1
          or getattr(scene.train, "sizes", None) is not None
          or getattr(scene, "train_cameras", None) is not None)


def _stepper(cfg: config_lib.Config, scene, state: state_lib.TrainState,
             scorer, devices):
  """(jitted step, its views, state, scorer) of a run: train_step on a
  Batch of every view, or batch_step on the views' lanes over the devices
  (sharding.py) with the state replicated and the scorer's per-view
  fields dealt into lanes."""
  if not batched(cfg, scene):
    return make_train_step(cfg), make_batch(scene.train), state, scorer
  mesh = sharding.make_mesh(cfg.train.batch_size, devices)
  lanes, rows = sharding.lanes_of(scene, cfg.train.batch_size, mesh)
  height, width = lanes.images.shape[2:4]
  return (batch_step.make_step(cfg, mesh), lanes,
          sharding.replicate(state, mesh),
          sharding.scorer_lanes(scorer, rows, height, width, mesh))


def fit(cfg: config_lib.Config, scene, workdir: str, *, scorer=None,
        resume: bool = False, progress: bool = True,
        stop_after: int | None = None, devices=None,
        summary_dir: str | None = None) -> loop.FitResult:
  """Trains on scene.train, tracking test PSNR on scene.test.

  Each step runs the jitted train step (train_step; batch_step when
  train.batch_size > 1 or the photos differ in size), then the host hooks
  of `loop`, in
  this order: a test evaluation (every eval_every steps and at the end;
  its time is excluded from the curve's seconds), the semantic prune
  (guidance.prune_due), densify with capacity growth and the opacity reset
  (densify.due), the log (every log_every steps: metrics fetched and
  checked for non-finite values) and the checkpoint (workdir/
  checkpoint.npz, every checkpoint_every steps and at the end). So an
  evaluation at step N sees the model before step N's housekeeping and a
  checkpoint at step N after it.

  Args:
    cfg: the checked config (config_file.check), resolved for `scene`
      (`resolve`).
    scene: a data.scene.Scene (train/test Views, points, extent).
    workdir: where the checkpoint goes (created if missing).
    scorer: guidance.make_scorer(cfg.semantic, scene, ...); None exactly
      when cfg.semantic is not enabled.
    resume: continue from workdir/checkpoint.npz if it exists; the result
      is bit-identical to an uninterrupted run.
    progress: show a tqdm progress bar.
    stop_after: stop once this many steps are done, with a checkpoint, as
      a preemption would (a later resume=True call finishes the run).
    devices: the devices a batch of views spreads over
      (sharding.make_mesh); default every device.
    summary_dir: TensorBoard event files go here (summary.Writer), or
      nowhere when None.
  """
  guidance.check_scorer(cfg.semantic, scorer, "train.fit")
  os.makedirs(workdir, exist_ok=True)
  ckpt_path = os.path.join(workdir, CHECKPOINT_NAME)
  state, flog = loop.restore(initial_state(cfg, scene), ckpt_path, cfg,
                             resume)
  step_fn, data, state, step_scorer = _stepper(cfg, scene, state, scorer,
                                               devices)
  total = cfg.train.steps
  start = int(state.step)
  ctx = loop.Context(
      cfg=cfg, scene=scene, ckpt_path=ckpt_path,
      end=total if stop_after is None else min(total, stop_after),
      densify_key=jax.random.fold_in(state.key, _DENSIFY_STREAM),
      scorer=scorer)
  if summary_dir is not None and sharding.is_writer():
    ctx = dataclasses.replace(ctx, summary=summary.Writer(summary_dir,
                                                          start_step=start))
  try:
    if start == 0 and cfg.train.eval_every and loop.eval_due(0, ctx):
      flog = loop.eval_point(state, flog, 0, ctx)
    if progress:
      import tqdm  # pylint: disable=g-import-not-at-top
      ctx = dataclasses.replace(ctx, bar=tqdm.tqdm(
          total=total, initial=start, dynamic_ncols=True, mininterval=1.0))
    flog = loop.start_clock(flog)
    for step in range(start + 1, ctx.end + 1):   # `step` = steps done after
      state, metrics = step_fn(state, data, step_scorer)
      flog = loop.record_step(flog, step, metrics, ctx)
      # Evaluate the optimisation steps' result before this step's
      # housekeeping (as 3DGS reports); a densify would show a transient.
      if loop.eval_due(step, ctx):
        flog = loop.evaluate(state, flog, step, ctx)
      # The semantic prune reads the trained opacities and statistics, so
      # it runs before the densify (whose children start at n = 0) and the
      # opacity reset (which would put every alpha under alpha_min).
      if guidance.prune_due(step, cfg):
        state, flog = loop.semantic_prune(state, flog, step, ctx)
      state, flog = loop.densify(state, flog, step, ctx)
      if loop.log_due(step, ctx):
        flog = loop.log(flog, step, ctx)
      # Checkpoint after the housekeeping, so a resume continues exactly.
      if loop.checkpoint_due(step, ctx):
        flog = loop.save_checkpoint(state, flog, ctx)
  finally:
    if ctx.bar is not None:
      ctx.bar.close()
    if ctx.summary is not None:
      ctx.summary.close()
  jax.block_until_ready(state)
  if start >= total:
    _log.info("checkpoint is already at step %d >= %d steps", start, total)
  return loop.result(state, cfg, loop.flush_scores(flog, ctx))
