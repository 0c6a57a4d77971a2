"""The CLIP-GS semantic stage as pure functions (the paper's eqs. 5-13).

Per training step: score the rendered view (eqs. 5-7), accumulate the score
into the Gaussians that contributed to it (eqs. 8-9), normalise by view count
(eq. 10), penalise opacity by the normalised score (eqs. 11-12) and prune
(eq. 13). The per-row statistics are `state.SemanticStats`, a field of the
train state, so densification and pruning (state.apply_rows) move them with
the parameters.
"""

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import state as state_lib

# s_hat = (cos + 1) / 2 maps cosine similarity to [0, 1]; 0.5 (cos = 0) is
# the neutral point below which a view adds no distractor evidence.
NEUTRAL_SCORE = 0.5
# Pixel evidence: a Gaussian is judged only once its blending weights over
# the scored views sum to at least one whole pixel. Below that, s_j is the
# ratio of a few partial edge pixels, and one misclassified pixel can move
# it across any threshold.
MIN_EVIDENCE_WEIGHT = 1.0
# Agreement-weighted pixel evidence: a transient pixel is evidence about
# the Gaussians that draw it only in proportion to how well the render
# reproduces the photo there, falling linearly to 0 at this mean absolute
# colour error; the rest of its weight counts neither way. A Gaussian that
# fits the transient (a ghost) reproduces it; a static Gaussian that the
# transient hides in this photo draws something else there. 0.1 (26/255)
# is about twice a fitted render's L1 error on the benchmarks at 1000 steps
# (train l1 0.03-0.05) and well below the contrast of a pasted object
# against what it hides.
AGREEMENT_TOLERANCE = 0.1


def normalized_max_cosine(image_embedding: jax.Array,
                          prompt_embeddings: jax.Array) -> jax.Array:
  """(max_p cos(f_I, f_p) + 1) / 2 (eqs. 5-7) for L2-normalised inputs.

  Args:
    image_embedding: float [D], the rendered view's normalised CLIP feature.
    prompt_embeddings: float [P, D], normalised text features, P >= 1.
  Returns:
    float [], the normalised score in [0, 1].
  """
  if prompt_embeddings.shape[0] == 0:
    raise ValueError("normalized_max_cosine needs at least one prompt.")
  cos = prompt_embeddings @ image_embedding                       # [P]
  return (jnp.max(cos) + 1.0) / 2.0


def _check_score(score) -> None:
  """Host-side check of a concrete score (skipped under jit)."""
  if isinstance(score, jax.core.Tracer):
    return
  value = np.asarray(score)
  if not np.all(np.isfinite(value)) or np.any(value < 0) or np.any(value > 1):
    raise ValueError(f"s_hat_d must be a finite score in [0, 1], got {value}.")


def accumulate(stats: state_lib.SemanticStats, visible: jax.Array,
               s_hat_d: jax.Array, beta: float,
               weight: jax.Array | None = None,
               scored: jax.Array | bool = True) -> state_lib.SemanticStats:
  """Eqs. 8-9: acc += w * beta * max(0, s_hat_d - 0.5), weight += w, n += v.

  With the paper's weight w = v_j (visibility, the default), every visible
  Gaussian gains the view's score once and s_j = acc / weight is the mean
  score of the views that saw it. A float weight (the Gaussian's
  blending-weight sum in the view, SemanticConfig.weighting =
  "contribution") makes s_j the contribution-weighted mean instead. n
  always counts views, so eq. 13's n_min keeps its meaning.

  Args:
    stats: per-row acc, weight and n, float [C].
    visible: bool [C], the rasterizer's per-Gaussian visibility (a non-zero
      blending weight on some pixel); dead slots have none.
    s_hat_d: float [], the view's normalised distractor score.
    beta: accumulation rate (paper: 0.1).
    weight: float [C] >= 0 or None (= visible).
    scored: bool [], the view was scored; False adds nothing (s_hat_d is
      then a placeholder).
  Returns:
    The updated statistics. A non-finite score (possible only under jit,
    where it cannot raise; train.fit raises on it at the next log step)
    leaves the statistics unchanged.
  """
  _check_score(s_hat_d)
  ok = jnp.logical_and(scored, jnp.isfinite(s_hat_d))
  gain = beta * jnp.maximum(0.0, jnp.where(ok, s_hat_d, 0.0) - NEUTRAL_SCORE)
  dtype = stats.acc.dtype
  v = jnp.where(ok, visible.astype(dtype), 0.0)
  w = v if weight is None else jnp.where(ok, weight.astype(dtype), 0.0)
  return stats.replace(acc=stats.acc + gain * w, weight=stats.weight + w,
                       n=stats.n + v)


def accumulate_pixel(stats: state_lib.SemanticStats, evidence: jax.Array,
                     contribution: jax.Array, visible: jax.Array,
                     due: jax.Array) -> state_lib.SemanticStats:
  """Localized evidence: acc += sum_i w_ij m_i, weight += sum_i w_ij.

  s_j = acc_j / weight_j is then the share of Gaussian j's blending weight,
  over all scored views, that fell on pixels the map calls transient: a
  probability in [0, 1] whose scale does not depend on the scorer or the
  scene (unlike the image-level s_j, which lives on beta times the CLIP
  cosine scale).

  Args:
    stats: per-row acc, weight and n, float [C].
    evidence: float [C], the rasterizer's sum_i w_ij m_i for the map m.
    contribution: float [C], the weight s_j is a share of: the
      rasterizer's sum_i w_ij (less, under agreement weighting, the weight
      on transient pixels that the render does not reproduce).
    visible: bool [C], contribution > 0; n counts the views.
    due: bool [], this step scores (otherwise the stats are unchanged).
  """
  dtype = stats.acc.dtype
  on = due.astype(dtype)
  return stats.replace(
      acc=stats.acc + on * evidence.astype(dtype),
      weight=stats.weight + on * contribution.astype(dtype),
      n=stats.n + on * visible.astype(dtype))


def agreement(render: jax.Array, photo: jax.Array,
              tolerance: float = AGREEMENT_TOLERANCE) -> jax.Array:
  """float [H, W] in [0, 1]: 1 - mean_c |render - photo| / tolerance,
  clipped; how well the render reproduces each pixel of the photo."""
  err = jnp.mean(jnp.abs(render - photo), axis=-1)
  return jnp.clip(1.0 - err / tolerance, 0.0, 1.0)


def agreement_weight(weight, evidence, reproduced, xnp=jnp):
  """float [C], the weight s_j is a share of under agreement weighting.

  Transient pixels that the render does not reproduce say nothing about
  the Gaussians drawn there (the photo hides them, or the transient is not
  fitted yet): their weight, evidence - reproduced, leaves the
  denominator as `reproduced` replaces `evidence` in the numerator.

  Args:
    weight, evidence, reproduced: float [C], sum_i w_ij, sum_i w_ij m_i and
      sum_i w_ij m_i a_i (a = `agreement`), over the same views.
    xnp: the array module (numpy for host-side float64 sums).
  """
  return xnp.maximum(weight - evidence + reproduced, 0.0)


def normalized_scores(stats: state_lib.SemanticStats) -> jax.Array:
  """Eq. 10: s_j = acc_j / weight_j (= n_j for visibility), 0 unseen."""
  seen = stats.weight > 0
  return jnp.where(seen, stats.acc / jnp.where(seen, stats.weight, 1.0),
                   0.0)


def opacity_loss(stats: state_lib.SemanticStats, opacity_logits: jax.Array,
                 alive: jax.Array, weight: float) -> jax.Array:
  """Eqs. 11-12: lambda_c * mean over alive j of stop_grad(s_j) * alpha_j."""
  s = jax.lax.stop_gradient(normalized_scores(stats))
  alpha = jax.nn.sigmoid(opacity_logits)
  count = jnp.maximum(jnp.sum(alive), 1)
  return weight * jnp.sum(jnp.where(alive, s * alpha, 0.0)) / count


def prune_masks(stats: state_lib.SemanticStats, opacity_logits: jax.Array,
                alive: jax.Array, *, tau: float, n_min: float,
                alpha_min: float, min_weight: float = 0.0,
                rare_needs_evidence: bool = False
                ) -> tuple[jax.Array, jax.Array]:
  """Eq. 13, split by condition so each can be counted.

  Args:
    min_weight: the semantic condition also needs weight_j >= min_weight
      (pixel evidence: MIN_EVIDENCE_WEIGHT; the paper's rule: 0).
    rare_needs_evidence: the visibility condition also needs s_j > 0.
  Returns:
    semantic: bool [C], alive, s_j > tau and weight_j >= min_weight.
    visibility: bool [C], alive, not semantic, n_j < n_min and
      alpha_j < alpha_min (and s_j > 0 under rare_needs_evidence). Prune
      `semantic | visibility`.
  """
  s = normalized_scores(stats)
  semantic = alive & (s > tau) & (stats.weight >= min_weight)
  alpha = jax.nn.sigmoid(opacity_logits)
  visibility = alive & ~semantic & (stats.n < n_min) & (alpha < alpha_min)
  if rare_needs_evidence:
    visibility &= s > 0
  return semantic, visibility


def oracle_score(mask: jax.Array, saturation: float,
                 area: jax.Array | None = None) -> jax.Array:
  """The s_hat_d a perfect image-level detector gives a view (benchmarks).

  The score rises linearly with the transient area fraction f of the view,
  s_hat_d = 0.5 + 0.5 min(1, f / saturation): exactly neutral (0.5) for a
  clean view, and fully confident (1.0) once `saturation` of the image is
  transient. Reads the ground-truth mask, so it is labelled "oracle"
  wherever it is used.

  Args:
    mask: bool [H, W], the view's ground-truth transient mask.
    saturation: area fraction in (0, 1] at which the score reaches 1.
    area: float [], the photo's pixels when it lies on a larger canvas
      (the mask is False outside it); None: the mask's size.
  """
  if not 0 < saturation <= 1:
    raise ValueError(f"oracle saturation must be in (0, 1], got {saturation}.")
  if area is None:
    f = jnp.mean(mask.astype(jnp.float32))
  else:
    f = jnp.sum(mask.astype(jnp.float32)) / area
  return NEUTRAL_SCORE + NEUTRAL_SCORE * jnp.minimum(1.0, f / saturation)


def guard_prune(semantic_mask: jax.Array, visibility_mask: jax.Array,
                alive: jax.Array, max_fraction: float
                ) -> tuple[jax.Array, jax.Array, jax.Array]:
  """No prune event deletes the scene: one that would remove more than
  `max_fraction` of the alive rows removes none.

  Returns:
    (semantic, visibility, guarded): the masks to apply (all False when
    guarded) and bool [], the event was refused.
  """
  removed = jnp.sum(semantic_mask | visibility_mask)
  guarded = removed > max_fraction * jnp.sum(alive)
  keep = ~guarded
  return semantic_mask & keep, visibility_mask & keep, guarded


def state_bytes(stats: state_lib.SemanticStats) -> int:
  """Bytes of the per-slot semantic arrays (three float32 per slot)."""
  return int(sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(stats)))
