"""Test-set evaluation of a Gaussian model: renders and image metrics."""

import functools
from typing import Any, Iterator

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config as config_lib
from clipgs_jax import gaussians
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import rasterize
from clipgs_jax.data import scene as scene_lib


@functools.lru_cache(maxsize=None)
def _render_fn(render_cfg: config_lib.RenderConfig):
  def fn(params, alive, cam, bg, degree):
    out = rasterize.render(params, alive, cam, bg, render_cfg, degree)
    return jnp.clip(out.image, 0.0, 1.0), out.alpha, out.num_overflow
  return jax.jit(fn)


def renders(params: gaussians.GaussianParams, alive, views,
            cfg: config_lib.Config) -> Iterator[tuple[jax.Array, ...]]:
  """Renders each view of `views` with all SH bands on cfg.train.background.

  Yields:
    (float32 [H, W, 3] colour clipped to [0, 1], float32 [H, W] alpha,
    int32 [] tile-list entries dropped) per view, in order.
  """
  render = _render_fn(cfg.render)
  bg = jnp.asarray(cfg.train.background, jnp.float32)
  degree = jnp.asarray(params.sh_degree, jnp.int32)
  cams = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), views.cameras)
  for i in range(len(views.images)):
    yield render(params, alive, scene_lib.camera_at(cams, i), bg, degree)


@functools.lru_cache(maxsize=None)
def _metrics_fn(lpips_net: str | None):
  if lpips_net is None:
    return jax.jit(lambda a, b: metrics_lib.image_metrics(a, b, None))
  # LPIPS has its own jit; the rest is cheap.
  return functools.partial(metrics_lib.image_metrics, lpips_net=lpips_net)


def evaluate(params: gaussians.GaussianParams, alive, views,
             cfg: config_lib.Config, *, lpips_net: str | None = None,
             psnr_only: bool = False, keep_images: bool = False
             ) -> dict[str, Any]:
  """Renders every view of `views` and scores it against its image.

  All SH bands are used and the background is cfg.train.background.
  Renders are clipped to [0, 1] before scoring.

  Returns:
    dict with per-image lists "psnr" (and "ssim", "lpips" unless
    psnr_only), their means "mean/<name>", and "images" (float32
    [V, H, W, 3] numpy) when keep_images.
  """
  per_image: dict[str, list[float]] = {"psnr": []}
  if not psnr_only:
    per_image["ssim"] = []
    if lpips_net is not None:
      per_image["lpips"] = []
  images = []
  for i, (pred, _, _) in enumerate(renders(params, alive, views, cfg)):
    target = jnp.asarray(views.images[i], jnp.float32)
    if psnr_only:
      values = {"psnr": metrics_lib.psnr(pred, target)}
    else:
      values = _metrics_fn(lpips_net)(pred[None], target[None])
    for name in per_image:
      per_image[name].append(float(np.asarray(values[name]).reshape(())))
    if keep_images:
      images.append(np.asarray(pred))
  result: dict[str, Any] = dict(per_image)
  for name, vals in per_image.items():
    result[f"mean/{name}"] = float(np.mean(vals)) if vals else float("nan")
  if keep_images:
    result["images"] = (np.stack(images) if images else
                        np.zeros((0, views.cameras.height,
                                  views.cameras.width, 3), np.float32))
  return result
