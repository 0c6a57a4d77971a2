"""Transient maps from the step's own residual: no weights, no oracle.

A pixel whose colour the current model cannot reproduce, while most of the
image it can, is likely transient. Each step takes the render's per-pixel
residual r = mean_c |render - photo| (no gradient) and calls a pixel an
inlier when r is under a running quantile of the residuals seen so far;
the transient map is m = 1 - inlier. Two rules (BUILD_NOTES.md, "Transient
masks without an oracle"):
  - "sls" (SpotLessSplats' RobustFilter): the threshold is the `quantile`
    of an exponentially decayed histogram of every step's residuals; a
    pixel is an inlier if it is under the threshold or if more than half
    of its 3x3 neighbourhood is.
  - "robustnerf" (RobustNeRF): the threshold is the quantile of the
    previous step's residuals alone (decay 0); a pixel is an inlier where
    more than half of its 3x3 neighbourhood is, and each 8x8 block takes
    the verdict of the 16x16 window around it (inlier when more than
    PATCH_INLIER_SHARE of that window is).
The running statistics are a `ResidualState` in the train state, so a
resumed run continues bit for bit; their size is fixed at construction.
"""

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from clipgs_jax import guidance_config

# Residual histogram bins over [0, 1]: the threshold is a bin edge, so this
# is its resolution (1e-4 of the colour range; SpotLessSplats uses 10,000).
HISTOGRAM_BINS = 10_000
# Before any residual has been seen every pixel is an inlier.
INITIAL_THRESHOLD = 1.0
# RobustNeRF's patch rule: 8x8 blocks judged on the 16x16 window around
# them, inlier when more than this share of the window is.
PATCH_BLOCK = 8
PATCH_WINDOW = 16
PATCH_INLIER_SHARE = 0.6


@flax.struct.dataclass
class ResidualState:
  """Running residual statistics of the residual map.

  Attributes:
    histogram: float32 [HISTOGRAM_BINS], decayed counts of the residuals of
      past steps' pixels over [0, 1].
    threshold: float32 [], the inlier threshold the next step uses.
    classifier: the learned map's classifier (learned.Classifier), trained
      on this test's confident pixels, or None (the residual map).
    memory: bool [V, H, W] or None (ResidualConfig.remember off): for
      each training view (its index in the scene's training views) and
      canvas pixel, whether the map has marked it (sources.remember).
  """
  histogram: jax.Array
  threshold: jax.Array
  classifier: Any = None
  memory: jax.Array | None = None

  @classmethod
  def initial(cls, classifier: Any = None,
              memory_shape: tuple[int, int, int] | None = None
              ) -> "ResidualState":
    """Nothing seen yet; `memory_shape` (views, height, width) sizes the
    map's memory (None: none)."""
    return cls(histogram=jnp.zeros((HISTOGRAM_BINS,), jnp.float32),
               threshold=jnp.float32(INITIAL_THRESHOLD),
               classifier=classifier,
               memory=(None if memory_shape is None
                       else jnp.zeros(memory_shape, bool)))


def residual(render: jax.Array, photo: jax.Array) -> jax.Array:
  """float [H, W], mean over channels of |render - photo|, no gradient."""
  return jnp.mean(jnp.abs(jax.lax.stop_gradient(render) - photo), axis=-1)


def _bins(res: jax.Array) -> jax.Array:
  return jnp.clip((res * HISTOGRAM_BINS).astype(jnp.int32), 0,
                  HISTOGRAM_BINS - 1)


def histogram_quantile(cumulative: jax.Array, q: float) -> jax.Array:
  """float32 [], the lower edge of the first bin whose cumulative count
  reaches q of the total (a residual strictly below it is under q)."""
  first = jnp.argmax(cumulative >= q * cumulative[-1])
  return first.astype(jnp.float32) / HISTOGRAM_BINS


def counts(res: jax.Array, valid: jax.Array | None = None) -> jax.Array:
  """float32 [HISTOGRAM_BINS], the histogram of one view's residuals.

  Args:
    res: float [H, W], the view's residual map.
    valid: None, or float [H, W] in {0, 1}: only these pixels count (the
      rest of a canvas is no residual at all).
  """
  ones = 1.0 if valid is None else valid.reshape(-1).astype(jnp.float32)
  return jnp.zeros((HISTOGRAM_BINS,), jnp.float32).at[
      _bins(res).reshape(-1)].add(ones)


def update(state: ResidualState, res: jax.Array | None = None, *,
           quantile: float, decay: float,
           median_factor: float = 0.0, minimum: float = 0.0,
           histogram: jax.Array | None = None) -> ResidualState:
  """Adds one step's residuals; the threshold becomes their quantile.

  Args:
    state: the running statistics.
    res: float [H, W], this step's residual map; or None and
    histogram: `counts` summed over the step's views.
    quantile: the inlier share, e.g. 0.7: the threshold is the residual
      under which this share of the (decayed) histogram lies.
    decay: weight of the past histogram (0: this step's residuals only).
    median_factor: the threshold is at least this times the histogram's
      median (0: the quantile alone). A quantile calls the same share of
      pixels outliers whether or not the views hold transients; the floor
      keeps pixels whose residual is ordinary for the current fit.
    minimum: the threshold is at least this (a mean absolute colour
      error in [0, 1]; 0: no absolute floor).
  """
  step_counts = counts(res) if histogram is None else histogram
  histogram = decay * state.histogram + step_counts
  cumulative = jnp.cumsum(histogram)
  threshold = histogram_quantile(cumulative, quantile)
  if median_factor > 0:
    threshold = jnp.maximum(threshold,
                            median_factor * histogram_quantile(cumulative, 0.5))
  if minimum > 0:
    threshold = jnp.maximum(threshold, jnp.float32(minimum))
  return state.replace(histogram=histogram, threshold=threshold)


def _box3(x: jax.Array) -> jax.Array:
  """float [H, W], the mean of each pixel's 3x3 neighbourhood (zero
  outside the image, always divided by 9)."""
  padded = jnp.pad(x, 1)
  h, w = x.shape
  total = sum(padded[i:i + h, j:j + w] for i in range(3) for j in range(3))
  return total / 9.0


def _patch_verdict(inlier: jax.Array, valid: jax.Array | None = None
                   ) -> jax.Array:
  """RobustNeRF's patch rule: every PATCH_BLOCK block becomes an inlier
  exactly when more than PATCH_INLIER_SHARE of the PATCH_WINDOW window
  centred on it (the part inside the image, or inside `valid`) is."""
  h, w = inlier.shape
  b, margin = PATCH_BLOCK, (PATCH_WINDOW - PATCH_BLOCK) // 2
  bh, bw = -(-h // b), -(-w // b)
  pad = ((margin, bh * b - h + margin), (margin, bw * b - w + margin))
  inside = jnp.pad(jnp.ones_like(inlier) if valid is None else valid, pad)
  values = jnp.pad(inlier, pad)
  window = (PATCH_WINDOW, PATCH_WINDOW)
  count = jax.lax.reduce_window(values, 0.0, jax.lax.add, window, (b, b),
                                "VALID")
  area = jax.lax.reduce_window(inside, 0.0, jax.lax.add, window, (b, b),
                               "VALID")
  verdict = (count > PATCH_INLIER_SHARE * area).astype(inlier.dtype)
  return jnp.repeat(jnp.repeat(verdict, b, axis=0), b, axis=1)[:h, :w]


def inliers(res: jax.Array, threshold: jax.Array, rule: str,
            valid: jax.Array | None = None) -> jax.Array:
  """float32 [H, W] in {0, 1}: 1 where the rule calls the pixel static.

  `valid` (None, or float [H, W] in {0, 1}: the photo's pixels on a larger
  canvas) makes the pixels outside the photo count as outside the image:
  never inliers, and out of the patch rule's windows.
  """
  raw = (res < threshold).astype(jnp.float32)
  if valid is not None:
    raw = raw * valid
  neighbours = (_box3(raw) > 0.5).astype(jnp.float32)
  if rule == "sls":
    return jnp.maximum(raw, neighbours)
  if rule == "robustnerf":
    return _patch_verdict(neighbours, valid)
  raise ValueError(f"residual rule {rule!r} is not one of "
                   f"{', '.join(guidance_config.RESIDUAL_RULES)}")


def warmup_share(step: jax.Array, rate: float) -> jax.Array:
  """float32 [], a = exp(-rate floor((step + 1) / 1.5)): the chance that a
  pixel the map calls transient is still fitted at `step` (SpotLessSplats'
  schedule: the model first sees every pixel, then the map takes over)."""
  steps = jnp.floor((step.astype(jnp.float32) + 1.0) / 1.5)
  return jnp.exp(-rate * steps)


def sample_inliers(inlier: jax.Array, step: jax.Array, key: jax.Array,
                   rate: float) -> jax.Array:
  """float32 [H, W] in {0, 1}: Bernoulli(a + (1 - a) inlier) with a =
  warmup_share(step, rate); `inlier` itself when rate is 0."""
  if rate == 0:
    return inlier
  a = warmup_share(step, rate)
  keep = jax.random.bernoulli(key, a + (1.0 - a) * inlier)
  return keep.astype(inlier.dtype)
