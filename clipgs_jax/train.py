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
import optax

from clipgs_jax import camera as camera_lib
from clipgs_jax import config as config_lib
from clipgs_jax import densify
from clipgs_jax import gaussians
from clipgs_jax import guidance
from clipgs_jax import initialize
from clipgs_jax import losses
from clipgs_jax import loop
from clipgs_jax import map_sources
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import optim
from clipgs_jax import project
from clipgs_jax import rasterize
from clipgs_jax import residual as residual_lib
from clipgs_jax import semantic as semantic_lib
from clipgs_jax import sh
from clipgs_jax import state as state_lib
from clipgs_jax import summary

_log = logging.getLogger(__name__)

# fold_in tags that give each use of the run's key its own stream.
_VIEW_STREAM = 1
_BACKGROUND_STREAM = 2
_DENSIFY_STREAM = 3
_RESIDUAL_STREAM = 4

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


def make_optimizer(cfg: config_lib.Config) -> optax.GradientTransformation:
  return optim.make(cfg.optim, cfg.scene_extent, cfg.train.steps)


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
      opt_state=make_optimizer(cfg).init(params),
      densify=state_lib.DensifyStats.zeros(capacity),
      semantic=state_lib.SemanticStats.zeros(capacity),
      step=jnp.zeros((), jnp.int32),
      key=jax.random.key(cfg.train.seed),
      maps=(residual_lib.ResidualState.initial()
            if cfg.semantic.uses_residual else None))


def view_index(key: jax.Array, step: jax.Array, num_views: int
               ) -> jax.Array:
  """int32 [], the training view of `step`.

  Views are visited in a fresh random permutation each epoch (epoch =
  step // V), as the reference 3DGS loop does; the permutation is a pure
  function of (key, epoch), so a resumed run sees the same views.
  """
  epoch_key = jax.random.fold_in(jax.random.fold_in(key, _VIEW_STREAM),
                                 step // num_views)
  return jax.random.permutation(epoch_key, num_views)[step % num_views]


def background(key: jax.Array, step: jax.Array, cfg: config_lib.Config
               ) -> jax.Array:
  """float [3]: a uniform random colour per step, or the fixed background."""
  if cfg.train.random_background:
    k = jax.random.fold_in(jax.random.fold_in(key, _BACKGROUND_STREAM), step)
    return jax.random.uniform(k, (3,), jnp.float32)
  return jnp.asarray(cfg.train.background, jnp.float32)


def train_step(state: state_lib.TrainState, batch: Batch, scorer=None, *,
               cfg: config_lib.Config
               ) -> tuple[state_lib.TrainState, dict[str, jax.Array]]:
  """One optimisation step on one training view.

  Renders the view (project + rasterize, with a zero offset on the splat
  centres whose gradient is the screen-space positional gradient), takes
  the 3DGS loss (1 - l) L1 + l (1 - SSIM), applies Adam, and accumulates
  the densification statistics. With a scorer (semantic guidance on) the
  loss gains the CLIP opacity term from reg_start, and the same render is
  scored and accumulated into state.semantic when due; without one the
  step is exactly the vanilla 3DGS step. With pixel evidence the view's
  map m goes into the render, which returns each Gaussian's sum w m beside
  sum w, and (loss_masking) the photometric loss is weighted by 1 - m.

  Args:
    state: the TrainState (donated by make_train_step).
    batch: all training views.
    scorer: None, or a guidance scorer (frozen; never differentiated).
    cfg: the config (static).
  """
  guidance.check_scorer(cfg.semantic, scorer, "train.train_step")
  num_views, height, width = batch.images.shape[:3]
  step = state.step
  view = view_index(state.key, step, num_views)
  cam = camera_lib.camera_at(batch.cameras, view)
  target = batch.images[view]
  bg = background(state.key, step, cfg)
  degree = sh.active_degree(step, cfg.densify.sh_degree_every,
                           cfg.gaussians.sh_degree)
  sem = cfg.semantic
  localized = scorer is not None and sem.localized
  # The residual map depends on the render: it cannot go into the render's
  # pass, so its per-Gaussian sums come from the backward pass (probe).
  dynamic = scorer is not None and sem.uses_residual
  evidence_map = (jax.lax.stop_gradient(scorer.score_map(view))
                  if localized and not dynamic else None)
  loss_weight = (1.0 - evidence_map
                 if evidence_map is not None and sem.loss_masking else None)
  sample_key = jax.random.fold_in(
      jax.random.fold_in(state.key, _RESIDUAL_STREAM), step)

  def loss_fn(params, offset, probe):
    proj = project.project(params, state.alive, cam, near=cfg.render.near,
                           sh_degree=degree)
    proj = proj.replace(means2d=proj.means2d + offset)
    out = rasterize.rasterize(proj, cam, bg, cfg.render,
                              evidence_map=evidence_map, probe=probe)
    weight, rmap = loss_weight, None
    if dynamic:
      rmap = map_sources.residual_map(scorer, state.maps, view, out.image,
                                      target, step, sample_key, sem)
      if sem.loss_masking:
        weight = rmap.loss_weight
    loss, terms = losses.photometric(out.image, target,
                                     cfg.train.lambda_dssim, weight)
    if dynamic:
      # Worth exactly 0 (the probe is 0); its gradient with respect to the
      # probe is each Gaussian's sum_i w_ij m_i.
      loss = loss + jnp.sum(jax.lax.stop_gradient(rmap.transient)
                            * out.probe_image)
    if scorer is not None:
      terms["semantic_loss"] = guidance.opacity_regularizer(
          state.semantic, params.opacity_logits, state.alive, step, cfg)
      loss = loss + terms["semantic_loss"]
    return loss, (out, proj, terms, rmap)

  offset = jnp.zeros((state.capacity, 2), state.params.means.dtype)
  if dynamic:
    probe = jnp.zeros((state.capacity,), state.params.means.dtype)
    (loss, (out, proj, terms, rmap)), (grads, grad2d, probe_grad) = (
        jax.value_and_grad(loss_fn, argnums=(0, 1, 2), has_aux=True)(
            state.params, offset, probe))
  else:
    (loss, (out, proj, terms, rmap)), (grads, grad2d) = jax.value_and_grad(
        loss_fn, argnums=(0, 1), has_aux=True)(state.params, offset, None)
  # Dead rows get no gradient from the render; the mask makes it explicit.
  grads = jax.tree.map(
      lambda g: jnp.where(
          state.alive.reshape((-1,) + (1,) * (g.ndim - 1)), g, 0.0), grads)
  tx = make_optimizer(cfg)
  updates, opt_state = tx.update(grads, state.opt_state, state.params)
  params = optax.apply_updates(state.params, updates)

  proj = jax.lax.stop_gradient(proj)
  seen = densify.on_screen(proj, width, height) & state.alive
  stats = densify.accumulate(state.densify, grad2d, seen,
                             densify.screen_radius(proj), width, height)
  metrics = {
      "loss": loss, "l1": terms["l1"], "ssim": terms["ssim"],
      "psnr": metrics_lib.psnr(out.image, target),
      "num_alive": jnp.sum(state.alive, dtype=jnp.int32),
      "num_overflow": out.num_overflow,
      "max_tile_count": out.max_tile_count,
      "sh_degree": degree,
      "means_lr": optim.means_lr(step, cfg.optim, cfg.scene_extent,
                                 cfg.train.steps),
  }
  for field in optim.FIELDS:
    metrics[f"grad_norm/{field}"] = optax.tree.norm(getattr(grads, field))
  semantic_stats = state.semantic
  maps = state.maps
  if dynamic:
    maps = residual_lib.update(maps, rmap.residual,
                               quantile=sem.residual_quantile,
                               decay=sem.residual_decay,
                               median_factor=sem.residual_median_factor,
                               minimum=sem.residual_min_threshold)
    due = guidance.scores_due(step, sem)
    semantic_stats = semantic_lib.accumulate_pixel(
        state.semantic, probe_grad, out.contribution, out.visible, due)
    metrics["semantic_loss"] = terms["semantic_loss"]
    metrics.update(
        map_mean=jnp.mean(rmap.transient), view=view, scored=due,
        residual_threshold=state.maps.threshold,
        # The share of the map that the agreement rule would keep.
        agreement_share=jnp.sum(rmap.transient * semantic_lib.agreement(
            jax.lax.stop_gradient(out.image), target))
        / jnp.maximum(jnp.sum(rmap.transient), 1.0))
  elif localized:
    metrics["semantic_loss"] = terms["semantic_loss"]
    due = guidance.scores_due(step, sem)
    evidence, weight = out.evidence, out.contribution
    if sem.agreement:
      reproduced = _reproduced_evidence(due, proj, cam, bg, cfg,
                                        evidence_map, out.image, target)
      weight = semantic_lib.agreement_weight(weight, evidence, reproduced)
      evidence = reproduced
    semantic_stats = semantic_lib.accumulate_pixel(
        state.semantic, evidence, weight, out.visible, due)
    metrics.update(map_mean=jnp.mean(evidence_map), view=view, scored=due)
  elif scorer is not None:
    metrics["semantic_loss"] = terms["semantic_loss"]
    weight = None if sem.weighting == "visibility" else out.contribution
    semantic_stats, scores = guidance.score_and_accumulate(
        state.semantic, out.image, out.visible, weight, view, step, scorer,
        sem)
    metrics.update(scores, view=view)
  new_state = state.replace(params=params, opt_state=opt_state,
                            densify=stats, semantic=semantic_stats,
                            step=step + 1, maps=maps)
  return new_state, metrics


def _reproduced_evidence(due, proj, cam, bg, cfg, evidence_map, image,
                         target):
  """float [C], sum_i w_ij m_i a_i with a = semantic.agreement(render, photo).

  The agreement needs the finished render, so this is a second forward
  pass of the same projected splats (no gradient), run only on scoring
  steps (lax.cond); other steps return zeros.
  """
  proj = jax.lax.stop_gradient(proj)
  weighted = evidence_map * semantic_lib.agreement(
      jax.lax.stop_gradient(image), target)
  return jax.lax.cond(
      due,
      lambda: rasterize.rasterize(proj, cam, bg, cfg.render,
                                  evidence_map=weighted).evidence,
      lambda: jnp.zeros_like(proj.depths))


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
  cams = scene.train.cameras
  centers = -np.einsum("vji,vj->vi", np.asarray(cams.rotation, np.float64),
                       np.asarray(cams.translation, np.float64))
  points = getattr(scene, "points", None)
  params, alive = initialize.initialize(
      points, getattr(scene, "point_colors", None), centers, cfg.gaussians,
      seed=cfg.train.seed)
  return init_state(cfg, params, alive)


def fit(cfg: config_lib.Config, scene, workdir: str, *, scorer=None,
        resume: bool = False, progress: bool = True,
        stop_after: int | None = None,
        summary_dir: str | None = None) -> loop.FitResult:
  """Trains on scene.train, tracking test PSNR on scene.test.

  Each step runs the jitted train step, then the host hooks of `loop`, in
  this order: a test evaluation (every eval_every steps and at the end;
  its time is excluded from the curve's seconds), the semantic prune
  (guidance.prune_due), densify with capacity growth and the opacity reset
  (densify.due), the log (every log_every steps: metrics fetched and
  checked for non-finite values) and the checkpoint (workdir/
  checkpoint.npz, every checkpoint_every steps and at the end). So an
  evaluation at step N sees the model before step N's housekeeping and a
  checkpoint at step N after it.

  Args:
    cfg: the checked config (config.check), resolved for `scene`
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
    summary_dir: TensorBoard event files go here (summary.Writer), or
      nowhere when None.
  """
  guidance.check_scorer(cfg.semantic, scorer, "train.fit")
  os.makedirs(workdir, exist_ok=True)
  ckpt_path = os.path.join(workdir, CHECKPOINT_NAME)
  batch = make_batch(scene.train)
  state, flog = loop.restore(initial_state(cfg, scene), ckpt_path, cfg,
                             resume)
  step_fn = make_train_step(cfg)
  total = cfg.train.steps
  start = int(state.step)
  ctx = loop.Context(
      cfg=cfg, scene=scene, ckpt_path=ckpt_path,
      end=total if stop_after is None else min(total, stop_after),
      densify_key=jax.random.fold_in(state.key, _DENSIFY_STREAM),
      scorer=scorer)
  if summary_dir is not None:
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
      state, metrics = step_fn(state, batch, scorer)
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
