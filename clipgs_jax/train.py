"""A run's initial state and `fit`, the training loop around step.py."""

import dataclasses
import logging
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import guidance
from clipgs_jax import initialize
from clipgs_jax import loop
from clipgs_jax import optim
from clipgs_jax import sharding
from clipgs_jax import state as state_lib
from clipgs_jax import step as step_lib
from clipgs_jax import summary
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.maps import learned
from clipgs_jax.maps import residual as residual_lib

_log = logging.getLogger(__name__)

# The fold_in tags of densification's stream of the run's key and of the
# learned map's initial weights (view.py holds the others).
_DENSIFY_STREAM = 3
_CLASSIFIER_STREAM = 6

CHECKPOINT_NAME = "checkpoint.npz"


def init_state(cfg: config_lib.Config, params: gaussians.GaussianParams,
               alive, memory_shape: tuple[int, int, int] | None = None
               ) -> state_lib.TrainState:
  """Step-0 state: zero moments and statistics, the run's key from seed.

  `memory_shape` (training views, canvas height, width) sizes the residual
  map's memory, which cfg.residual.remember needs (`initial_state` gives
  the scene's).
  """
  if not cfg.scene_extent > 0:
    raise ValueError("train.init_state: cfg.scene_extent must be positive; "
                     "call train.resolve(cfg, scene) first.")
  if cfg.uses_memory and memory_shape is None:
    raise ValueError("train.init_state: --config.residual.remember=True "
                     "needs memory_shape (the training views and their "
                     "canvas); use initial_state.")
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
      maps=(residual_lib.ResidualState.initial(
          learned.init(cfg.learned, jax.random.fold_in(
              jax.random.key(cfg.train.seed), _CLASSIFIER_STREAM))
          if cfg.uses_learned else None,
          memory_shape if cfg.uses_memory else None)
            if cfg.uses_residual else None))


def resolve(cfg: config_lib.Config, scene) -> config_lib.Config:
  """Fills the scene-dependent config fields from `scene`: scene_extent,
  and train.background where the photos have an alpha channel (the colour
  they were composited onto, data.background: a model of a photo on white
  must not draw the white)."""
  background = getattr(scene, "background", None)
  if background is not None and tuple(cfg.train.background) != background:
    _log.info("photos with alpha on %s: train.background %s -> %s",
              cfg.data.background, cfg.train.background, background)
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(
        cfg.train, background=background))
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
  memory_shape = None
  if cfg.uses_memory:
    width, height = sharding.canvas_of(scene)
    memory_shape = (len(np.asarray(cams.fx)), height, width)
  return init_state(cfg, params, alive, memory_shape)


def fit(cfg: config_lib.Config, scene, workdir: str, *, scorer=None,
        resume: bool = False, progress: bool = True,
        stop_after: int | None = None, devices=None,
        summary_dir: str | None = None) -> loop.FitResult:
  """Trains on scene.train, tracking test PSNR on scene.test.

  Each step runs the jitted train step (step.py: train.batch_size views
  over the devices), then the host hooks of `loop`, in this order: a test
  evaluation (every eval_every steps and at the end; its time is excluded
  from the curve's seconds), the semantic prune
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
    scorer: guidance.make_scorer(cfg, scene, ...); None exactly
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
  step_fn, lanes, state, step_scorer = step_lib.for_scene(
      cfg, scene, state, scorer, devices)
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
      state, metrics = step_fn(state, lanes, step_scorer)
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
