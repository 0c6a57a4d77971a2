"""Photometric losses: L1, SSIM and the 3DGS L1 + D-SSIM mix.

Conventions:
  * Images are float [..., H, W, C] with values nominally in [0, 1].
  * SSIM follows Wang et al. (2004): an 11x11 Gaussian window with sigma 1.5,
    C1 = (0.01 L)^2 and C2 = (0.03 L)^2 with dynamic range L = 1, computed
    per channel and averaged over pixels and channels.
  * padding="valid" keeps only windows that lie fully inside the image (the
    evaluation convention of tf.image.ssim and scikit-image); padding="same"
    zero-pads by 5 pixels so every pixel has a window, as 3DGS does in its
    training loss. Zero padding lowers SSIM near the border, so use "valid"
    for reported numbers.
  * D-SSIM here is 1 - SSIM (the 3DGS definition; some papers use
    (1 - SSIM) / 2). The training loss is
    (1 - lambda) * L1 + lambda * (1 - SSIM), with lambda = 0.2 in 3DGS.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

SSIM_WINDOW = 11         # window side in pixels (Wang et al.)
SSIM_SIGMA = 1.5         # Gaussian window standard deviation in pixels
SSIM_C1 = 0.01 ** 2      # (K1 L)^2, K1 = 0.01, L = 1: stabilises the mean term
SSIM_C2 = 0.03 ** 2      # (K2 L)^2, K2 = 0.03, L = 1: stabilises the var term
PADDINGS = ("valid", "same")


def l1(pred: jax.Array, target: jax.Array) -> jax.Array:
  """float [], mean absolute error over all elements."""
  return jnp.mean(jnp.abs(pred - target))


@functools.lru_cache(maxsize=None)
def _window_1d(size: int, sigma: float) -> np.ndarray:
  x = np.arange(size, dtype=np.float64) - (size - 1) / 2
  w = np.exp(-0.5 * (x / sigma) ** 2)
  return (w / w.sum()).astype(np.float32)


@functools.lru_cache(maxsize=None)
def _band(n: int, padding: str) -> np.ndarray:
  """float32 [n', n] matrix applying the 1D window along an axis of size n.

  Row i holds the window centred on input i; "same" truncates windows at
  the borders (zero padding), "valid" keeps only the n - 10 full ones.
  """
  w = _window_1d(SSIM_WINDOW, SSIM_SIGMA)
  half = SSIM_WINDOW // 2
  m = np.zeros((n, n + 2 * half), np.float32)
  for i in range(n):
    m[i, i:i + SSIM_WINDOW] = w
  m = m[:, half:half + n]                     # drop the zero-padding columns
  return m[half:n - half] if padding == "valid" else m


def _blur(x: jax.Array, padding: str) -> jax.Array:
  """Separable Gaussian filter of [N, H, W, C] images, per channel.

  Written as two matmuls with banded matrices: on CPU this is about 20x
  faster than a grouped convolution (4 ms vs 83 ms for SSIM and its
  gradient at 128x96), and exact in float32.
  """
  gh = jnp.asarray(_band(x.shape[1], padding), x.dtype)
  gw = jnp.asarray(_band(x.shape[2], padding), x.dtype)
  hi = jax.lax.Precision.HIGHEST
  x = jnp.einsum("ij,njkc->nikc", gh, x, precision=hi)
  return jnp.einsum("lk,nikc->nilc", gw, x, precision=hi)


def ssim_map(a: jax.Array, b: jax.Array, padding: str = "valid"
             ) -> jax.Array:
  """float [..., H', W', C] per-pixel SSIM (H' = H - 10 for "valid").

  Args:
    a, b: float [..., H, W, C] images of the same shape, range [0, 1].
    padding: "valid" or "same" (see the module docstring).
  """
  if padding not in PADDINGS:
    raise ValueError(f"losses.ssim: padding must be one of {PADDINGS}, got "
                     f"{padding!r}.")
  if a.shape != b.shape or a.ndim < 3:
    raise ValueError(f"losses.ssim: images must be [..., H, W, C] with equal "
                     f"shapes, got {a.shape} and {b.shape}.")
  if padding == "valid" and min(a.shape[-3:-1]) < SSIM_WINDOW:
    raise ValueError(f"losses.ssim: padding='valid' needs images of at least "
                     f"{SSIM_WINDOW}x{SSIM_WINDOW}, got {a.shape[-3:-1]}; "
                     "use padding='same'.")
  batch = a.shape[:-3]
  dtype = jnp.result_type(a, b, jnp.float32)
  a = a.reshape((-1,) + a.shape[-3:]).astype(dtype)
  b = b.reshape((-1,) + b.shape[-3:]).astype(dtype)
  mu_a, mu_b = _blur(a, padding), _blur(b, padding)
  # Windowed (co)variances as E[xy] - E[x]E[y], with the window's weights.
  var_a = _blur(a * a, padding) - mu_a * mu_a
  var_b = _blur(b * b, padding) - mu_b * mu_b
  cov = _blur(a * b, padding) - mu_a * mu_b
  num = (2 * mu_a * mu_b + SSIM_C1) * (2 * cov + SSIM_C2)
  den = (mu_a * mu_a + mu_b * mu_b + SSIM_C1) * (var_a + var_b + SSIM_C2)
  out = num / den
  return out.reshape(batch + out.shape[1:])


def ssim(a: jax.Array, b: jax.Array, padding: str = "valid") -> jax.Array:
  """float [...], SSIM averaged over pixels and channels of each image."""
  return jnp.mean(ssim_map(a, b, padding), axis=(-3, -2, -1))


def photometric(pred: jax.Array, target: jax.Array, lambda_dssim: float,
                weight: jax.Array | None = None,
                valid: jax.Array | None = None
                ) -> tuple[jax.Array, dict[str, jax.Array]]:
  """3DGS loss (1 - lambda) L1 + lambda (1 - SSIM), SSIM zero-padded "same".

  Args:
    pred, target: float [H, W, 3].
    lambda_dssim: the D-SSIM share.
    weight: None, or float [H, W] in [0, 1], per-pixel weights (loss
      masking: 1 - the transient map); both terms become weighted means,
      and where the weight is 0 neither term reads `target` nor sends a
      gradient to `pred`. None is the unweighted 3DGS loss, computed
      exactly as without the argument.
    valid: None, or float [H, W] in {0, 1}: the photo fills only the valid
      pixels of a larger canvas. Both images are 0 outside them, as the
      "same" SSIM zero-pads a photo at its border, and both terms are means
      over the valid pixels: the loss and its gradient are those of the
      photo on its own.
  Returns:
    float [] loss and a dict with its "l1" and "ssim" terms.
  """
  if weight is None and valid is None:
    l1_term = l1(pred, target)
    ssim_term = ssim(pred, target, padding="same")
  else:
    w = (jnp.ones(pred.shape[:-1], pred.dtype) if weight is None
         else weight)[..., None]
    if valid is not None:
      inside = valid[..., None]
      w = w * inside
    # A fully masked view has no pixel to fit: both terms are then 0 / eps
    # = 0 (SSIM term 1 - 0 adds a constant, no gradient).
    total = jnp.maximum(jnp.sum(w) * pred.shape[-1], 1e-6)
    l1_term = jnp.sum(w * jnp.abs(pred - target)) / total
    # SSIM at a kept pixel reads an 11x11 window that reaches into masked
    # pixels. Filling both images there with the (stop-gradient) render
    # makes the term blind to the photo under the mask and sends no
    # gradient into masked pixels; weighting the map alone does neither
    # (it pulled renders towards the transient at the mask's border).
    fill = jax.lax.stop_gradient(pred)
    pred_seen = w * pred + (1.0 - w) * fill
    target_seen = w * target + (1.0 - w) * fill
    if valid is not None:
      pred_seen, target_seen = pred_seen * inside, target_seen * inside
    ssim_term = jnp.sum(
        w * ssim_map(pred_seen, target_seen, padding="same")) / total
  loss = (1.0 - lambda_dssim) * l1_term + lambda_dssim * (1.0 - ssim_term)
  return loss, {"l1": l1_term, "ssim": ssim_term}
