"""One training view: which view a step draws, and its render and gradients.

The train step (step.py) runs these once for each view of its batch.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from clipgs_jax import camera as camera_lib
from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import guidance
from clipgs_jax import losses
from clipgs_jax import semantic as semantic_lib
from clipgs_jax import state as state_lib
from clipgs_jax.maps import learned
from clipgs_jax.maps import residual as residual_lib
from clipgs_jax.maps import sources
from clipgs_jax.render import project
from clipgs_jax.render import rasterize

# fold_in tags that give each use of the run's key its own stream (tag 3,
# densification, is train.fit's).
_VIEW_STREAM = 1
_BACKGROUND_STREAM = 2
_RESIDUAL_STREAM = 4
_LANE_STREAM = 5


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


def lane_view(key: jax.Array, step: jax.Array, count: jax.Array,
              length: int) -> jax.Array:
  """int32 [], the position in its lane of the view of `step`.

  view_index for a lane of `count` views (traced, at most the static
  `length`): each epoch's permutation of `length` positions with those
  past `count` left out, so a full lane visits its views exactly as
  view_index(key, step, length) does.
  """
  epoch_key = jax.random.fold_in(jax.random.fold_in(key, _VIEW_STREAM),
                                 step // count)
  perm = jax.random.permutation(epoch_key, length)
  order = perm[jnp.argsort(perm >= count, stable=True)]
  return order[step % count]


def lane_key(key: jax.Array, lane: jax.Array) -> jax.Array:
  """The key of lane `lane` of a batch (sharding.py): its view order and
  its residual map's sampling. Lane 0 has the run's key, so a batch of one
  lane visits the views of the one-view step in the same order."""
  other = jax.random.fold_in(jax.random.fold_in(key, _LANE_STREAM), lane)
  data = jnp.where(lane == 0, jax.random.key_data(key),
                   jax.random.key_data(other))
  return jax.random.wrap_key_data(data, impl=jax.random.key_impl(key))


def background(key: jax.Array, step: jax.Array, cfg: config_lib.Config
               ) -> jax.Array:
  """float [3]: a uniform random colour per step, or the fixed background."""
  if cfg.train.random_background:
    k = jax.random.fold_in(jax.random.fold_in(key, _BACKGROUND_STREAM), step)
    return jax.random.uniform(k, (3,), jnp.float32)
  return jnp.asarray(cfg.train.background, jnp.float32)


class ViewPass(NamedTuple):
  """One view's render, loss and gradients (`render_and_grad`).

  Attributes:
    loss: float [], the view's loss.
    out: the rasterize.RenderOutput.
    proj: the project.Projected splats the render drew.
    terms: {"l1", "ssim"} of the photometric loss, and "semantic_loss"
      with a scorer.
    rmap: the view's sources.ResidualMap, or None.
    grads: GaussianParams, d loss / d params.
    grad2d: float [C, 2], d loss / d screen position, in pixels.
    probe_grad: float [C], each Gaussian's sum_i w_ij m_i of the residual
      map (from the backward pass), or None.
    evidence_map: float [H, W], the static map the render summed per
      Gaussian (out.evidence), or None.
    classifier_grad: the learned map's d loss / d classifier params of
      this view (learned.gradient), or None.
    memory: bool [H, W], the view's map memory after this visit
      (sources.remember), or None.
  """
  loss: jax.Array
  out: rasterize.RenderOutput
  proj: project.Projected
  terms: dict[str, jax.Array]
  rmap: sources.ResidualMap | None
  grads: gaussians.GaussianParams
  grad2d: jax.Array
  probe_grad: jax.Array | None
  evidence_map: jax.Array | None
  classifier_grad: dict[str, jax.Array] | None = None
  memory: jax.Array | None = None


def render_and_grad(state: state_lib.TrainState, scorer,
                    cfg: config_lib.Config, *, view: jax.Array,
                    cam: camera_lib.Camera, target: jax.Array,
                    bg: jax.Array, degree: jax.Array, key: jax.Array,
                    canvas: tuple[jax.Array, jax.Array] | None = None,
                    memory: jax.Array | None = None) -> ViewPass:
  """Renders one training view and differentiates its loss.

  Renders the view (project + rasterize, with a zero offset on the splat
  centres whose gradient is the screen-space positional gradient) and
  takes the 3DGS loss (1 - l) L1 + l (1 - SSIM), plus, with a scorer, the
  CLIP opacity term from reg_start. With pixel evidence the view's map m
  goes into the render, which returns each Gaussian's sum w m beside sum w,
  and (loss_masking) the photometric loss is weighted by 1 - m.

  Args:
    state: the TrainState before the step.
    scorer: None, or the guidance scorer, indexed by `view`.
    cfg: the config (static).
    view: int32 [], the view's index into the scorer's maps.
    cam, target: the view's camera and float [H, W, 3] photo.
    bg: float [3], the background; degree: int32 [], the SH degree.
    key: the key the residual map's warm-up samples from (folded with the
      step).
    canvas: None, or (int32 [2] width and height of the view's photo, float
      [H, W] 1 inside it): the view lies in the top-left corner of a larger
      canvas, and no pixel outside it is drawn, fitted or counted.
    memory: bool [H, W], the view's residual map memory
      (ResidualState.memory[v] for the view's index v in the training
      views), or None: given, the step's map holds what it remembers
      (sources.remember).
  """
  step = state.step
  sem = cfg.semantic
  localized = scorer is not None and sem.localized
  # The residual map depends on the render: it cannot go into the render's
  # pass, so its per-Gaussian sums come from the backward pass (probe).
  dynamic = scorer is not None and cfg.uses_residual
  size, valid = (None, None) if canvas is None else canvas
  evidence_map = (jax.lax.stop_gradient(scorer.score_map(view))
                  if localized and not dynamic else None)
  loss_weight = (1.0 - evidence_map
                 if evidence_map is not None and cfg.pixel.loss_masking
                 else None)
  sample_key = jax.random.fold_in(
      jax.random.fold_in(key, _RESIDUAL_STREAM), step)

  def loss_fn(params, offset, probe):
    proj = project.project(params, state.alive, cam, near=cfg.render.near,
                           sh_degree=degree)
    proj = proj.replace(means2d=proj.means2d + offset)
    out = rasterize.rasterize(proj, cam, bg, cfg.render,
                              evidence_map=evidence_map, probe=probe,
                              valid_size=size)
    weight, rmap, remembered = loss_weight, None, None
    if dynamic:
      rmap = sources.residual_map(scorer, state.maps, view, out.image,
                                  target, step, sample_key, cfg.residual,
                                  valid=valid,
                                  alpha=jax.lax.stop_gradient(out.alpha))
      rmap = sources.held_back(rmap, scorer, view, step, cfg.residual)
      if memory is not None:
        rmap, remembered = sources.remember(rmap, memory, step,
                                             cfg.residual)
      if cfg.pixel.loss_masking:
        weight = rmap.loss_weight
    loss, terms = losses.photometric(out.image, target,
                                     cfg.train.lambda_dssim, weight,
                                     valid=valid)
    if dynamic:
      # Worth exactly 0 (the probe is 0); its gradient with respect to the
      # probe is each Gaussian's sum_i w_ij m_i.
      loss = loss + jnp.sum(jax.lax.stop_gradient(rmap.transient)
                            * out.probe_image)
    if scorer is not None:
      terms["semantic_loss"] = guidance.opacity_regularizer(
          state.semantic, params.opacity_logits, state.alive, step, cfg)
      loss = loss + terms["semantic_loss"]
    return loss, (out, proj, terms, rmap, remembered)

  offset = jnp.zeros((state.capacity, 2), state.params.means.dtype)
  probe_grad = None
  if dynamic:
    probe = jnp.zeros((state.capacity,), state.params.means.dtype)
    (loss, aux), (grads, grad2d, probe_grad) = jax.value_and_grad(
        loss_fn, argnums=(0, 1, 2), has_aux=True)(state.params, offset, probe)
  else:
    (loss, aux), (grads, grad2d) = jax.value_and_grad(
        loss_fn, argnums=(0, 1), has_aux=True)(state.params, offset, None)
  out, proj, terms, rmap, remembered = aux
  classifier_grad = None
  if dynamic and cfg.uses_learned:
    # Labelled by the test on this step's residual, before the step's
    # statistics update (as the map's own threshold).
    classifier_grad = learned.gradient(
        state.maps.classifier.params, scorer.pixel_features[view],
        rmap.residual, state.maps, cfg.residual, cfg.learned, valid)
  return ViewPass(loss, out, proj, terms, rmap, grads, grad2d, probe_grad,
                  evidence_map, classifier_grad, remembered)


def reproduced_evidence(due, proj, cam, bg, cfg, evidence_map, image,
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


def _masked_mean(x: jax.Array, valid: jax.Array | None) -> jax.Array:
  if valid is None:
    return jnp.mean(x)
  return jnp.sum(x * valid) / jnp.maximum(jnp.sum(valid), 1.0)


def semantic_increment(vp: ViewPass, scorer, *, view: jax.Array,
                       step: jax.Array, cam: camera_lib.Camera,
                       bg: jax.Array, target: jax.Array,
                       cfg: config_lib.Config,
                       valid: jax.Array | None = None
                       ) -> tuple[state_lib.SemanticStats,
                                  dict[str, jax.Array]]:
  """One view's semantic evidence and its per-view metrics.

  Returns the SemanticStats increment (zero when the step does not
  score), which the train step sums over its views and adds to the run's
  stats, and the metrics: map_mean (the map's mean over `valid`) and
  scored, with the residual map the share of it that the agreement rule
  would keep, with the image-level rule the scores.
  """
  sem = cfg.semantic
  zero = state_lib.SemanticStats.zeros(vp.proj.depths.shape[0])
  out = vp.out
  due = guidance.scores_due(step, sem)
  if cfg.uses_residual:
    # The map's per-Gaussian sums are the probe's gradient.
    transient = vp.rmap.transient
    inc = semantic_lib.accumulate_pixel(zero, vp.probe_grad,
                                        out.contribution, out.visible, due)
    agree = semantic_lib.agreement(jax.lax.stop_gradient(out.image), target)
    return inc, dict(
        map_mean=_masked_mean(transient, valid), scored=due,
        agreement_share=jnp.sum(transient * agree)
        / jnp.maximum(jnp.sum(transient), 1.0))
  if sem.localized:
    evidence, weight = out.evidence, out.contribution
    if cfg.pixel.agreement:
      # The static map is 0 outside a canvas's photo, so the second pass's
      # sums leave those pixels out.
      reproduced = reproduced_evidence(
          due, vp.proj, cam, bg, cfg, vp.evidence_map, out.image, target)
      weight = semantic_lib.agreement_weight(weight, evidence, reproduced)
      evidence = reproduced
    inc = semantic_lib.accumulate_pixel(zero, evidence, weight, out.visible,
                                        due)
    return inc, dict(map_mean=_masked_mean(vp.evidence_map, valid),
                     scored=due)
  weight = None if sem.weighting == "visibility" else out.contribution
  return guidance.score_and_accumulate(
      zero, out.image, out.visible, weight, view, step, scorer, sem)


def update_maps(maps: residual_lib.ResidualState, cfg: config_lib.Config,
                histogram: jax.Array,
                classifier_grad: dict[str, jax.Array] | None = None
                ) -> residual_lib.ResidualState:
  """The residual map's statistics after a step: residual.update with the
  run's threshold settings on the `histogram` of the step's residuals
  (residual.counts summed over its views); with the learned map, its
  classifier after one Adam step on `classifier_grad` (summed over the
  views)."""
  rc = cfg.residual
  maps = residual_lib.update(maps, quantile=rc.quantile, decay=rc.decay,
                             median_factor=rc.median_factor,
                             minimum=rc.min_threshold,
                             histogram=histogram)
  if classifier_grad is None:
    return maps
  return maps.replace(classifier=learned.apply(
      maps.classifier, classifier_grad, cfg.learned, cfg.train.batch_size))
