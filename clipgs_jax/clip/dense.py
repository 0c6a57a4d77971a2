"""Training-free per-patch CLIP embeddings from the frozen ViT image tower.

Two published readouts of the last residual block, both without training:

  'maskclip'  (Zhou, Loy, Dai, ECCV 2022, arXiv:2112.01071): the query-key
      attention of the last block is dropped, so each token keeps only its
      own value vector (through out_proj); the residual path and the MLP of
      the block are kept as they are.
  'clearclip' (Lan et al., ECCV 2024, arXiv:2407.12442): the last block's
      output is its attention branch alone, with query-query attention; the
      residual connection and the MLP are dropped.

Each patch token then goes through ln_post and the projection, as the class
token does in the image-level encoder. Inputs larger than the training size
use bicubic-interpolated patch position embeddings.
"""

import functools
import math

import chex
from flax import linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax.clip import model

READOUTS = ('maskclip', 'clearclip')
# ClearCLIP: same cost as MaskCLIP, and its ablations trace MaskCLIP's noisy
# maps to the residual path it keeps (BUILD_NOTES.md, "CLIP tower").
DEFAULT_READOUT = 'clearclip'
# Keys' cubic convolution parameter of torch's bicubic interpolate, which
# transformers' CLIPVisionEmbeddings.interpolate_pos_encoding calls; using
# the same kernel keeps our interpolated positions equal to theirs.
CUBIC_A = -0.75


def _cubic(x: np.ndarray) -> np.ndarray:
  """Keys' cubic convolution kernel with a = CUBIC_A, on float64 [...]."""
  x, a = np.abs(x), CUBIC_A
  near = ((a + 2) * x - (a + 3)) * x * x + 1  # |x| <= 1
  far = ((a * x - 5 * a) * x + 8 * a) * x - 4 * a  # 1 < |x| < 2
  return np.where(x <= 1, near, np.where(x < 2, far, 0.0))


def interpolation_matrix(n_in: int, n_out: int) -> np.ndarray:
  """Rows that resample n_in samples to n_out, bicubic, half-pixel centres.

  The convention of torch's `interpolate(mode='bicubic',
  align_corners=False)` with an output size: source coordinate
  (i + 0.5) * n_in / n_out - 0.5, four taps, indices clamped to the border.
  n_in == n_out gives the identity exactly.

  Returns:
    float64 [n_out, n_in]; rows sum to 1.
  """
  src = (np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5
  base = np.floor(src)
  t = src - base
  m = np.zeros((n_out, n_in))
  for offset in (-1, 0, 1, 2):
    idx = np.clip(base + offset, 0, n_in - 1).astype(int)
    np.add.at(m, (np.arange(n_out), idx), _cubic(t - offset))
  return m


def resize_positions(positions: jax.Array, grid: int) -> jax.Array:
  """Position embeddings of a grid x grid patch layout.

  Args:
    positions: float [G*G + 1, W], the class token's row, then the patch
      rows in row-major order over a G x G grid.
    grid: int, patches per side of the new layout.

  Returns:
    float [grid*grid + 1, W]; the class row unchanged, the patch rows
    resampled separably with `interpolation_matrix`.
  """
  n, w = positions.shape
  old = math.isqrt(n - 1)
  if old * old != n - 1:
    raise ValueError(f'{n - 1} patch positions do not form a square grid.')
  if grid == old:
    return positions
  m = jnp.asarray(interpolation_matrix(old, grid), positions.dtype)
  patches = positions[1:].reshape(old, old, w)
  patches = jnp.einsum('ai,bj,ijw->abw', m, m, patches,
                       precision=jax.lax.Precision.HIGHEST)  # [g, g, W]
  return jnp.concatenate([positions[:1], patches.reshape(grid * grid, w)])


class ReadoutAttention(nn.Module):
  """The last block's attention, rewired by a dense readout.

  Same parameters as model.SelfAttention (fused in_proj, out_proj).
  """

  num_heads: int
  readout: str

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x: float [B, L, W]. Returns: float [B, L, W]."""
    b, l, w = x.shape
    qkv = nn.Dense(3 * w, name='in_proj')(x)
    qkv = qkv.reshape(b, l, 3, self.num_heads, w // self.num_heads)
    q, v = qkv[:, :, 0], qkv[:, :, 2]  # [B, L, H, D]
    if self.readout == 'maskclip':
      out = v  # attention weights replaced by the identity
    else:  # 'clearclip': queries attend to queries, scale 1/sqrt(D)
      out = jax.nn.dot_product_attention(q, q, v)
    return nn.Dense(w, name='out_proj')(out.reshape(b, l, w))


class ReadoutBlock(nn.Module):
  """The last residual block under a dense readout (params as ResidualBlock)."""

  num_heads: int
  mlp_ratio: int
  readout: str

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x: float [B, L, W]. Returns: float [B, L, W]."""
    attn = ReadoutAttention(self.num_heads, self.readout, name='attn')(
        model.layer_norm('ln_1')(x))
    if self.readout == 'clearclip':
      return attn  # no residual, no MLP
    x = x + attn
    return x + model.Mlp(self.mlp_ratio, name='mlp')(
        model.layer_norm('ln_2')(x))


class ReadoutTransformer(nn.Module):
  """model.Transformer with its last block replaced by a ReadoutBlock."""

  num_layers: int
  num_heads: int
  mlp_ratio: int
  readout: str

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x: float [B, L, W]. Returns: float [B, L, W]."""
    for i in range(self.num_layers - 1):
      x = model.ResidualBlock(self.num_heads, self.mlp_ratio,
                              name=f'resblocks_{i}')(x)
    last = f'resblocks_{self.num_layers - 1}'
    return ReadoutBlock(self.num_heads, self.mlp_ratio, self.readout,
                        name=last)(x)


class DenseVisionTransformer(nn.Module):
  """The CLIP ViT read out per patch; applied to the params' 'visual' tree."""

  config: model.ClipConfig
  readout: str = DEFAULT_READOUT

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    """Embeds every patch of normalised images.

    Args:
      images: float [B, S, S, 3], CLIP-normalised; S a multiple of the
        patch size, any size (positions are interpolated when S differs
        from config.image_size).

    Returns:
      float [B, g, g, E], g = S // patch_size, unnormalised patch features
      in the joint embedding space, rows and columns as in the image.
    """
    c = self.config
    chex.assert_rank(images, 4)
    b, s = images.shape[0], images.shape[1]
    chex.assert_shape(images, (b, s, s, 3))
    grid, w = s // c.patch_size, c.vision_width
    init = nn.initializers.normal(w**-0.5)
    x = nn.Conv(w, (c.patch_size, c.patch_size),
                strides=(c.patch_size, c.patch_size), padding='VALID',
                use_bias=False, name='conv1')(images)  # [B, g, g, W]
    x = x.reshape(b, grid * grid, w)  # row-major, as model.VisionTransformer
    cls = self.param('class_embedding', init, (w,))
    x = jnp.concatenate(
        [jnp.broadcast_to(cls.astype(x.dtype), (b, 1, w)), x], axis=1
    )  # [B, g*g+1, W]
    positions = self.param('positional_embedding', init,
                           (c.grid_size**2 + 1, w))
    x = x + resize_positions(positions, grid)
    x = model.layer_norm('ln_pre')(x)
    x = ReadoutTransformer(c.vision_layers, c.vision_heads, c.mlp_ratio,
                           self.readout, name='transformer')(x)
    x = model.layer_norm('ln_post')(x[:, 1:])  # [B, g*g, W], class dropped
    x = x @ self.param('proj', init, (w, c.embed_dim))  # [B, g*g, E]
    return x.reshape(b, grid, grid, c.embed_dim)


def check_input_size(input_size: int, config: model.ClipConfig) -> int:
  """Returns the patch grid side of an input size, or raises ValueError."""
  if input_size < config.patch_size or input_size % config.patch_size:
    raise ValueError(
        f'input_size={input_size} must be a positive multiple of the patch '
        f'size {config.patch_size} (e.g. {14 * config.patch_size} for a '
        f'14x14 grid).')
  return input_size // config.patch_size


def check_readout(readout: str) -> None:
  """Raises ValueError for a readout name not in READOUTS."""
  if readout not in READOUTS:
    raise ValueError(f'Unknown dense readout {readout!r}; use one of '
                     f'{READOUTS}.')


@functools.partial(jax.jit, static_argnames=('config', 'readout'))
def encode_dense(params: dict, images: jax.Array, *, config: model.ClipConfig,
                 readout: str = DEFAULT_READOUT) -> jax.Array:
  """Unit-norm per-patch embeddings of preprocessed images.

  Args:
    params: parameter tree of model.Clip(config) (frozen: stop_gradient).
    images: float [B, S, S, 3], preprocess.preprocess(..., size=S).
    config: the model's shapes (static).
    readout: one of READOUTS (static).

  Returns:
    float32 [B, g, g, E], g = S // patch_size.
  """
  check_readout(readout)
  check_input_size(images.shape[1], config)
  params = jax.lax.stop_gradient(params)
  features = DenseVisionTransformer(config, readout).apply(
      {'params': params['visual']}, images)
  return model.l2_normalize(features)


def distractor_probability(features: jax.Array, distractor: jax.Array,
                           static: jax.Array, logit_scale: jax.Array
                           ) -> jax.Array:
  """p(distractor) per feature: softmax over D and S prompts, summed over D.

  Args:
    features: float [..., E], unit-norm patch embeddings.
    distractor: float [P, E], unit-norm embeddings of the prompts D.
    static: float [Q, E], of the prompts S; Q >= 1 (Q = 0 gives 1).
    logit_scale: float [], the multiplier of the cosines (CLIP's exp'd
      scale, 100 for OpenAI's ViT-B/32).

  Returns:
    float32 [...] in [0, 1].
  """
  logits_d = logit_scale * features @ distractor.T  # [..., P]
  logits_s = logit_scale * features @ static.T  # [..., Q]
  # log sum_D exp - log sum_{D+S} exp: exact, and no overflow at scale 100.
  lse_d = jax.nn.logsumexp(logits_d, axis=-1)
  lse_all = jnp.logaddexp(lse_d, jax.nn.logsumexp(logits_s, axis=-1))
  return jnp.exp(lse_d - lse_all)


def upsample(probs: jax.Array, height: int, width: int) -> jax.Array:
  """Bilinear resize of a patch map to the render, half-pixel centres.

  For upsampling this is torch's `interpolate(mode='bilinear',
  align_corners=False)`: at the border the nearest patch value is held.

  Args:
    probs: float [g, g], values in [0, 1].
    height: int, render rows.
    width: int, render columns.

  Returns:
    float32 [height, width] in [0, 1].
  """
  out = jax.image.resize(probs, (height, width), method='bilinear')
  # Convex weights keep [0, 1] up to rounding; the clip makes it exact.
  return jnp.clip(out, 0.0, 1.0)
