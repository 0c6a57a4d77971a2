"""The host side of `train.fit`: the run's record and the hooks between steps.

`train.fit` is a short loop: one jitted train step, then the hooks below in
a fixed order (evaluate, semantic prune, densify/reset, log, checkpoint).
Each hook takes the TrainState and the run's `FitLog` and returns new ones;
what no hook changes (config, scene, compiled functions, the progress bar)
is the `Context`. The host waits for the device only inside hooks: at log
steps, before a densify (capacity growth), at evaluations, prunes and
checkpoints.
"""

import dataclasses
import logging
import math
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import checkpoint
from clipgs_jax import config as config_lib
from clipgs_jax import densify as densify_lib
from clipgs_jax import evaluation
from clipgs_jax import guidance
from clipgs_jax import render_without
from clipgs_jax import semantic
from clipgs_jax import sharding
from clipgs_jax import sh
from clipgs_jax import state as state_lib

_log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class FitLog:
  """What the host records about a run; hooks return a new one.

  Attributes:
    curve: [{step, seconds, test_psnr}] of every evaluation.
    scores: [{step, view, <per-step score keys>}] of every scored step.
    prune_events: [{step, num_alive_before, ...}] of every semantic prune.
    pruned: numpy GaussianParams of the rows each prune removed by score.
    log: the host floats of every logging step.
    train_seconds: training wall time so far, evaluations and checkpoint
      writing excluded.
    tic: time.perf_counter() when the clock last (re)started.
    pending: (step, device metrics) of the per-step scores not yet fetched.
    last_metrics: the device metrics of the latest train step.
    last_info: the device counts of the latest densify, or None.
    mask_quality: the latest evaluation.mask_quality (with per-view
      values), or None.
  """
  curve: list[dict[str, float]] = dataclasses.field(default_factory=list)
  scores: list[dict[str, Any]] = dataclasses.field(default_factory=list)
  prune_events: list[dict[str, Any]] = dataclasses.field(
      default_factory=list)
  pruned: list[Any] = dataclasses.field(default_factory=list)
  log: list[dict[str, float]] = dataclasses.field(default_factory=list)
  train_seconds: float = 0.0
  tic: float = 0.0
  pending: list[tuple[int, dict[str, jax.Array]]] = dataclasses.field(
      default_factory=list)
  last_metrics: dict[str, jax.Array] | None = None
  last_info: dict[str, jax.Array] | None = None
  mask_quality: dict[str, Any] | None = None


@dataclasses.dataclass(frozen=True)
class Context:
  """What the hooks read and never change.

  Attributes:
    cfg: the resolved config.
    scene: the data.scene.Scene (test views for evaluations).
    ckpt_path: the run's checkpoint file.
    end: the last step this call runs (cfg.train.steps unless stopped
      early).
    densify_key: the key densify folds each step into.
    scorer: the run's guidance scorer, or None.
    bar: a tqdm progress bar, or None.
    summary: a summary.Writer (TensorBoard), or None.
  """
  cfg: config_lib.Config
  scene: Any
  ckpt_path: str
  end: int
  densify_key: jax.Array
  scorer: Any = None
  bar: Any = None
  summary: Any = None

  @property
  def per_step_keys(self) -> tuple[str, ...]:
    return guidance.per_step_keys(self.cfg.semantic)


# The checkpoint record of the rows semantic prunes removed (one array per
# GaussianParams field), so a resumed run still has them.
_PRUNED_RECORD = "pruned/"


def restore(state: state_lib.TrainState, ckpt_path: str,
            cfg: config_lib.Config, resume: bool
            ) -> tuple[state_lib.TrainState, FitLog]:
  """(state, FitLog): from the checkpoint when resuming and one exists,
  else the step-0 `state` and an empty log."""
  flog = FitLog()
  if resume and os.path.exists(ckpt_path):
    checkpoint.check_resumable(ckpt_path, cfg)
    state, meta = checkpoint.restore(ckpt_path, state)
    extra = meta["extra"]
    prefix = checkpoint.ARRAYS_PREFIX + _PRUNED_RECORD
    pruned = {k[len(prefix):]: v for k, v in
              checkpoint.read_arrays(ckpt_path, prefix).items()}
    flog = FitLog(curve=list(extra.get("curve", [])),
                  train_seconds=float(extra.get("train_seconds", 0.0)),
                  scores=list(extra.get("scores", [])),
                  prune_events=list(extra.get("prune_events", [])),
                  pruned=[type(state.params)(**pruned)] if pruned else [])
    _log.info("resumed from %s at step %d", ckpt_path, int(state.step))
  elif resume:
    _log.info("no checkpoint at %s; starting from step 0", ckpt_path)
  return state, flog


def _every(step: int, every: int) -> bool:
  return bool(every) and step % every == 0


def eval_due(step: int, ctx: Context) -> bool:
  """Evaluate after `step` steps: every eval_every and at the last step
  (in a multi-host run, only the process that writes the run folder)."""
  return sharding.is_writer() and len(ctx.scene.test.images) > 0 and (
      step == ctx.cfg.train.steps or _every(step, ctx.cfg.train.eval_every))


def log_due(step: int, ctx: Context) -> bool:
  return step == ctx.end or _every(step, ctx.cfg.train.log_every)


def checkpoint_due(step: int, ctx: Context) -> bool:
  return step == ctx.end or _every(step, ctx.cfg.train.checkpoint_every)


def start_clock(flog: FitLog) -> FitLog:
  return dataclasses.replace(flog, tic=time.perf_counter())


def stop_clock(state: state_lib.TrainState, flog: FitLog) -> FitLog:
  """Waits for the device and adds the time since the clock started."""
  jax.block_until_ready(state)
  elapsed = time.perf_counter() - flog.tic
  return dataclasses.replace(flog, train_seconds=flog.train_seconds + elapsed)


def record_step(flog: FitLog, step: int, metrics: dict[str, jax.Array],
                ctx: Context) -> FitLog:
  """Keeps the step's metrics on the device (scores until the next log)."""
  pending = flog.pending
  if ctx.cfg.semantic.enabled:
    pending = pending + [(step - 1, {k: metrics[k]
                                     for k in ctx.per_step_keys})]
  if ctx.bar is not None:
    ctx.bar.update(1)
  return dataclasses.replace(flog, pending=pending, last_metrics=metrics)


def eval_point(state: state_lib.TrainState, flog: FitLog, step: int,
               ctx: Context) -> FitLog:
  """Test PSNR of the current model, appended to the curve; with pixel
  evidence on a scene with masks, also the quality of the maps the loss
  uses (evaluation.mask_quality)."""
  # On one device's copy: a replicated state would render on every device.
  params, alive, maps, done = sharding.local(
      (state.params, state.alive, state.maps, state.step))
  result = evaluation.evaluate(params, alive, ctx.scene.test, ctx.cfg,
                               psnr_only=True)
  _log.info("step %d: test PSNR %.3f after %.1f s of training, %d alive",
            step, result["mean/psnr"], flog.train_seconds,
            int(jnp.sum(state.alive)))
  point = {"step": step, "seconds": flog.train_seconds,
           "test_psnr": result["mean/psnr"]}
  quality = flog.mask_quality
  if ctx.cfg.semantic.localized and ctx.scene.train.masks is not None:
    quality = evaluation.mask_quality(params, alive, maps, ctx.scorer,
                                      ctx.scene.train, ctx.cfg,
                                      _degree(done, ctx))
    point.update({f"mask_{k}": quality[k]
                  for k in ("precision", "recall", "iou")})
    _log.info("step %d: transient maps vs ground truth: precision %s, "
              "recall %s, IoU %s", step, *(
                  "n/a" if quality[k] is None else f"{quality[k]:.3f}"
                  for k in ("precision", "recall", "iou")))
  if ctx.summary is not None:
    ctx.summary.scalars(step, {"test/psnr": result["mean/psnr"]} | {
        f"mask/{k}": point[f"mask_{k}"] for k in ("precision", "recall",
                                                  "iou")
        if point.get(f"mask_{k}") is not None})
    summarize_view(sharding.local(state), step, ctx)
  return dataclasses.replace(flog, curve=flog.curve + [point],
                             mask_quality=quality)


def _degree(step: jax.Array, ctx: Context) -> jax.Array:
  """int32 [], the SH degree the train steps use after `step` steps."""
  return sh.active_degree(step, ctx.cfg.densify.sh_degree_every,
                          ctx.cfg.gaussians.sh_degree)


def summary_view(scene) -> int:
  """The training view TensorBoard shows: the one with the most transient
  pixels where the scene has masks, else the first."""
  masks = scene.train.masks
  return 0 if masks is None else int(np.argmax(np.mean(masks, axis=(1, 2))))


def summarize_view(state: state_lib.TrainState, step: int,
                   ctx: Context) -> None:
  """TensorBoard images of `summary_view`: our render, the photo, and the
  transient map the loss would use now and the ground-truth mask where
  they exist."""
  i, train = summary_view(ctx.scene), ctx.scene.train
  one = dataclasses.replace(
      train, cameras=jax.tree.map(lambda x: x[i:i + 1], train.cameras),
      images=train.images[i:i + 1], names=train.names[i:i + 1], masks=None)
  image = next(evaluation.renders(state.params, state.alive, one,
                                  ctx.cfg))[0]
  ctx.summary.image(step, "train_view/render", image)
  ctx.summary.image(step, "train_view/photo", train.images[i])
  if ctx.cfg.semantic.localized and ctx.scorer is not None:
    ctx.summary.image(step, "train_view/transient_map", evaluation.view_map(
        state.params, state.alive, state.maps, ctx.scorer, train, i,
        ctx.cfg, _degree(state.step, ctx)))
  if train.masks is not None:
    ctx.summary.image(step, "train_view/ground_truth_mask", train.masks[i])


def evaluate(state: state_lib.TrainState, flog: FitLog, step: int,
             ctx: Context) -> FitLog:
  """eval_point with the clock stopped (evaluation is not training time)."""
  flog = eval_point(state, stop_clock(state, flog), step, ctx)
  return start_clock(flog)


def _finite_or_none(x) -> float | None:
  x = float(x)
  return x if math.isfinite(x) else None


def flush_scores(flog: FitLog, ctx: Context) -> FitLog:
  """Fetches the pending per-step scores; keeps the scored steps.

  Raises:
    FloatingPointError: a scorer returned a non-finite required score.
  """
  if not flog.pending:
    return flog
  keys = guidance.per_step_value_keys(ctx.cfg.semantic)
  rows = []
  for step, batch in jax.device_get(flog.pending):
    # One row per view (a step has B of each value).
    for i in range(np.size(batch["view"])):
      values = {k: np.ravel(v)[i] for k, v in batch.items()}
      if not values["scored"]:
        continue
      check_finite(step, {k: float(values[k]) for k in keys
                          if k not in guidance.OPTIONAL_SCORE_KEYS},
                   f"the {ctx.cfg.semantic.scorer!r} scorer returned it "
                   f"for training view {int(values['view'])}")
      rows.append({"step": step, "view": int(values["view"])} | {
          k: _finite_or_none(values[k]) for k in keys})
  return dataclasses.replace(flog, scores=flog.scores + rows, pending=[])


def semantic_prune(state: state_lib.TrainState, flog: FitLog, step: int,
                   ctx: Context) -> tuple[state_lib.TrainState, FitLog]:
  """Eq. 13 through the guard; keeps the removed rows for the mask IoU.

  The prune clears alive and the rows' moments and statistics but leaves
  their parameters (state.write_rows with values None), so the rows are
  gathered after it, on the device, and only they are fetched.
  """
  cfg = ctx.cfg
  if ctx.summary is not None:       # s_j before the prune donates `state`
    scores = np.asarray(semantic.normalized_scores(state.semantic))
    ctx.summary.histogram(step, "semantic/s_j",
                          scores[np.asarray(state.alive)],
                          bins=guidance.histogram_edges(cfg.semantic))
  spared, num_spared = _spared_rows(state, ctx)
  state, info = guidance.make_prune(cfg)(state, spared)
  info = jax.device_get(info) | {"num_spared": num_spared}
  rows = np.nonzero(info.pop("pruned_semantic"))[0]
  pruned = jax.device_get(jax.tree.map(lambda x: x[rows], state.params))
  event = {"step": step} | {k: np.asarray(v).tolist()
                            for k, v in info.items()}
  if ctx.summary is not None:
    ctx.summary.scalars(step, {f"prune/{k}": float(v)
                               for k, v in event.items()
                               if k != "step" and np.ndim(v) == 0})
  if event["guarded"]:
    _log.warning(
        "step %d: semantic prune REFUSED: it would remove %d of %d "
        "Gaussians, more than max_prune_fraction = %g; nothing removed. "
        "The threshold is below the scores of most of the scene.", step,
        event["num_refused"], event["num_alive_before"],
        cfg.semantic.max_prune_fraction)
  else:
    _log.info("step %d: semantic prune removed %d (s_j > tau; %d spared) "
              "+ %d (rarely seen, faint) of %d", step,
              event["num_pruned_semantic"], num_spared,
              event["num_pruned_visibility"], event["num_alive_before"])
  return state, dataclasses.replace(
      flog, pruned=flog.pruned + [pruned],
      prune_events=flog.prune_events + [event])


def _spared_rows(state: state_lib.TrainState, ctx: Context
                 ) -> tuple[jax.Array | None, int]:
  """The semantic clause's rows that semantic.prune_harm keeps (None when
  the test is off), and how many (render_without.py)."""
  sem = ctx.cfg.semantic
  if sem.prune_harm <= 0:
    return None, 0
  candidates = np.asarray(guidance.prune_candidates(state, ctx.cfg)[0])
  if not candidates.any():
    return None, 0
  share, _, _ = render_without.harmed_share(
      state.params, state.alive, candidates, ctx.scene.train,
      render_without.HARM_TOLERANCE, _degree(state.step, ctx), ctx.cfg)
  spared = candidates & (share >= sem.prune_harm)
  return jnp.asarray(spared), int(spared.sum())


def grow_if_needed(state: state_lib.TrainState, cfg: config_lib.Config
                   ) -> state_lib.TrainState:
  """Doubles C (up to max_capacity) when the next densify asks for more
  clones/splits than there are free slots."""
  requested, free = (int(x) for x in jax.device_get(
      densify_lib.make_count_requests(cfg)(state)))
  capacity = state.capacity
  if requested <= free or capacity >= cfg.gaussians.max_capacity:
    return state
  new = capacity
  while (new - (capacity - free) < requested
         and new < cfg.gaussians.max_capacity):
    new = min(2 * new, cfg.gaussians.max_capacity)
  _log.info("step %d: capacity %d -> %d (%d requests, %d free); the train "
            "step recompiles once", int(state.step), capacity, new,
            requested, free)
  return state_lib.resize(state, new)


def densify(state: state_lib.TrainState, flog: FitLog, step: int,
            ctx: Context) -> tuple[state_lib.TrainState, FitLog]:
  """The densify (after growing C if needed) and opacity reset `step` is
  due for (densify.due); the densify's counts go to the next log."""
  do_densify, do_reset = densify_lib.due(step, ctx.cfg)
  if do_densify:
    state = grow_if_needed(state, ctx.cfg)
    state, info = densify_lib.make_densify(ctx.cfg)(
        state, jax.random.fold_in(ctx.densify_key, step))
    if ctx.summary is not None:
      ctx.summary.scalars(step, {f"densify/{k}": v for k, v in
                                 jax.device_get(info).items()})
    flog = dataclasses.replace(flog, last_info=info)
  if do_reset:
    state = densify_lib.make_reset_opacity(ctx.cfg)(state)
  return state, flog


def check_finite(step: int, values: dict[str, float],
                 fix: str = "lower the learning rates or check the input "
                 "images and cameras") -> None:
  """Raises FloatingPointError naming the non-finite values, the step and
  `fix`."""
  bad = [k for k, v in values.items() if not math.isfinite(v)]
  if bad:
    raise FloatingPointError(
        f"train: non-finite {', '.join(bad)} at step {step}; {fix}.")


def log(flog: FitLog, step: int, ctx: Context) -> FitLog:
  """Fetches the step's metrics (and the last densify's counts), checks
  them and appends them to the log."""
  flog = flush_scores(flog, ctx)
  values = {k: float(v) for k, v in jax.device_get(flog.last_metrics).items()
            if k not in ctx.per_step_keys}
  if flog.last_info is not None:
    values.update({k: float(v) for k, v in
                   jax.device_get(flog.last_info).items()})
  check_finite(step, values)
  if ctx.summary is not None:     # densify counts: at their own step
    ctx.summary.scalars(step, {f"train/{k}": v for k, v in values.items()
                               if k not in (flog.last_info or {})})
  if values.get("num_overflow", 0) > 0:
    # Inexact render: the view's tile/Gaussian intersections did not fit
    # the buffer of tiles x tile_budget pairs.
    _log.warning(
        "step %d: %d tile-list entries dropped (the view's intersections "
        "exceed tiles x render.tile_budget = %d per tile; longest tile list "
        "%d); raise RenderConfig.tile_budget", step,
        int(values["num_overflow"]), ctx.cfg.render.tile_budget,
        int(values["max_tile_count"]))
  values["step"] = step
  if ctx.bar is not None:
    ctx.bar.set_postfix(loss=f"{values['loss']:.4f}",
                        psnr=f"{values['psnr']:.2f}",
                        n=int(values["num_alive"]), refresh=False)
  return dataclasses.replace(flog, log=flog.log + [values])


def save(state: state_lib.TrainState, flog: FitLog, ctx: Context
         ) -> FitLog:
  """Writes the checkpoint with the run's record (scores fetched first);
  in a multi-host run only the process that writes the run folder."""
  flog = flush_scores(flog, ctx)
  pruned = concatenated(flog.pruned)
  if sharding.is_writer():
    checkpoint.save(ctx.ckpt_path, state, ctx.cfg, extra={
        "curve": flog.curve, "train_seconds": flog.train_seconds,
        "scores": flog.scores, "prune_events": flog.prune_events},
        records=None if pruned is None else {
            _PRUNED_RECORD + k: v
            for k, v in checkpoint.flatten(pruned).items()})
  return flog


def save_checkpoint(state: state_lib.TrainState, flog: FitLog,
                    ctx: Context) -> FitLog:
  """`save` with the clock stopped."""
  return start_clock(save(state, stop_clock(state, flog), ctx))


@dataclasses.dataclass
class FitResult:
  """What `train.fit` returns.

  Attributes:
    state: the final state.
    cfg: the resolved config the run used.
    curve: list of {step, seconds, test_psnr}.
    train_seconds: wall time of the training loop, compilation included,
      evaluation and checkpoint writing excluded.
    log: the metrics fetched at each logging step (host floats), with the
      counts of the most recent densify (num_cloned, num_split,
      num_pruned, num_unplaced) once one has run.
    scores: semantic guidance only: {step, view, s_hat_d, s_hat_s} of every
      scored step (s_hat_s None where the scorer has none).
    prune_events: semantic guidance only: {step, num_alive_before,
      num_pruned_semantic, num_pruned_visibility, num_refused, guarded,
      histogram} per prune.
    pruned: semantic guidance only: numpy GaussianParams of the rows the
      semantic rule removed, as they were when removed (None if none were),
      those removed before a resume included (the checkpoint keeps them).
    mask_quality: pixel evidence on a scene with masks: the last
      evaluation.mask_quality, else None.
  """
  state: state_lib.TrainState
  cfg: config_lib.Config
  curve: list[dict[str, float]]
  train_seconds: float
  log: list[dict[str, float]]
  scores: list[dict[str, Any]]
  prune_events: list[dict[str, Any]]
  pruned: Any = None
  mask_quality: dict[str, Any] | None = None


def concatenated(pruned: list[Any]):
  """One numpy GaussianParams of FitLog.pruned's rows, or None."""
  return (jax.tree.map(lambda *x: np.concatenate(x), *pruned)
          if pruned else None)


def result(state: state_lib.TrainState, cfg: config_lib.Config,
           flog: FitLog) -> FitResult:
  """The FitResult of a finished loop; the pruned rows concatenated."""
  return FitResult(state=state, cfg=cfg, curve=flog.curve,
                   train_seconds=flog.train_seconds, log=flog.log,
                   scores=flog.scores, prune_events=flog.prune_events,
                   pruned=concatenated(flog.pruned),
                   mask_quality=flog.mask_quality)
