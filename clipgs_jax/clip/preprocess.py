"""Resizing and normalisation of rendered images for the CLIP image tower."""

import jax
import jax.numpy as jnp
import numpy as np

# Per-channel RGB statistics of CLIP's training images (OpenAI clip.py).
MEAN = (0.48145466, 0.4578275, 0.40821073)
STD = (0.26862954, 0.26130258, 0.27577711)
IMAGE_SIZE = 224
# 'resize': squash the whole render to size x size (the CLIP-GS recipe:
# nothing of the view is cropped away). 'center_crop': CLIP's own
# preprocessing, shorter side to size, then the central square.
MODES = ('resize', 'center_crop')


def check_images(images: jax.typing.ArrayLike) -> None:
  """Rejects images that are not finite or not in [0, 1].

  A host-side check: under jit the values are unknown and nothing is done.

  Args:
    images: float [..., H, W, 3], RGB in [0, 1].

  Raises:
    ValueError: an element is NaN, infinite or outside [0, 1].
  """
  if isinstance(images, jax.core.Tracer):
    return
  x = np.asarray(images)
  if x.ndim < 3 or x.shape[-1] != 3:
    raise ValueError(f'CLIP needs RGB images [..., H, W, 3], got {x.shape}.')
  bad = ~np.isfinite(x)
  if bad.any():
    raise ValueError(
        f'CLIP input images hold {int(bad.sum())} NaN or infinite values.'
    )
  lo, hi = float(x.min()), float(x.max())
  if lo < 0.0 or hi > 1.0:
    raise ValueError(
        f'CLIP input images must lie in [0, 1]; found values in '
        f'[{lo:.6g}, {hi:.6g}].'
    )


def _center_crop_size(h: int, w: int, size: int) -> tuple[int, int]:
  """Returns (height, width) with the shorter side scaled to size."""
  # Truncation, as torchvision's Resize(int) computes the longer side.
  if h <= w:
    return size, int(size * w / h)
  return int(size * h / w), size


def preprocess(
    images: jax.typing.ArrayLike,
    mode: str = 'resize',
    size: int = IMAGE_SIZE,
) -> jax.Array:
  """Resizes and normalises images for model.encode_image; jit-able.

  Bicubic with antialiasing (Keys a = -0.5, the kernel of PIL's bicubic,
  which CLIP's own preprocessing used), then clipped to [0, 1] as PIL's
  8-bit output is, then normalised with MEAN and STD.

  Args:
    images: float [..., H, W, 3] in [0, 1]; checked when concrete.
    mode: 'resize' (whole image to size x size, aspect ratio not kept) or
      'center_crop' (shorter side to size, then the central square).
    size: int, output side; 224 for every OpenAI ViT-B and ViT-L/14.

  Returns:
    float32 [..., size, size, 3], CLIP-normalised.
  """
  if mode not in MODES:
    raise ValueError(f'Unknown preprocessing mode {mode!r}; use one of '
                     f'{MODES}.')
  check_images(images)
  x = jnp.asarray(images, jnp.float32)
  batch, (h, w) = x.shape[:-3], x.shape[-3:-1]
  if mode == 'resize':
    out_h, out_w = size, size
  else:
    out_h, out_w = _center_crop_size(h, w, size)
  if (out_h, out_w) != (h, w):
    x = jax.image.resize(
        x, batch + (out_h, out_w, 3), method='bicubic', antialias=True
    )  # [..., out_h, out_w, 3]
  if mode == 'center_crop':
    # Python's round, as torchvision's CenterCrop places the window.
    top = int(round((out_h - size) / 2.0))
    left = int(round((out_w - size) / 2.0))
    x = x[..., top : top + size, left : left + size, :]  # [..., size, size, 3]
  x = jnp.clip(x, 0.0, 1.0)
  return (x - jnp.asarray(MEAN)) / jnp.asarray(STD)
