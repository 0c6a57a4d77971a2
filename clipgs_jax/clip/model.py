"""OpenAI CLIP image and text towers as Flax linen modules."""

from collections.abc import Sequence
import dataclasses
import functools
import math

import chex
from flax import linen as nn
import jax
import jax.numpy as jnp

from clipgs_jax.clip import tokenizer

# torch.nn.LayerNorm's default, which every OpenAI CLIP model uses.
LAYER_NORM_EPS = 1e-5
# Keeps the division finite for an all-zero feature vector.
NORMALIZE_EPS = 1e-8
# CLIP's learned temperature starts at 1/0.07 and is stored as its log.
LOGIT_SCALE_INIT = math.log(1 / 0.07)


@dataclasses.dataclass(frozen=True)
class ClipConfig:
  """Shapes of one CLIP model; hashable, so jit can take it as static."""

  embed_dim: int = 512  # size of the joint image-text embedding
  image_size: int = 224  # input side in pixels
  patch_size: int = 32  # ViT patch side in pixels
  vision_width: int = 768  # ViT residual width
  vision_layers: int = 12  # ViT residual blocks
  vision_heads: int = 12  # ViT attention heads
  context_length: int = 77  # text tokens per prompt, padding included
  vocab_size: int = 49408  # BPE vocabulary with the two special tokens
  text_width: int = 512  # text transformer residual width
  text_layers: int = 12  # text transformer residual blocks
  text_heads: int = 8  # text transformer attention heads
  mlp_ratio: int = 4  # MLP hidden width over residual width

  @property
  def grid_size(self) -> int:
    """Patches per image side."""
    return self.image_size // self.patch_size


# Shapes from OpenAI's released checkpoints (clip/model.py build_model reads
# them back from the state dicts). "tiny" is ours, for fast tests: it keeps
# the real vocabulary and context so the real tokenizer feeds it.
VARIANTS = {
    'ViT-B/32': ClipConfig(),
    'ViT-B/16': ClipConfig(patch_size=16),
    'ViT-L/14': ClipConfig(
        embed_dim=768,
        patch_size=14,
        vision_width=1024,
        vision_layers=24,
        vision_heads=16,
        text_width=768,
        text_heads=12,
    ),
    'tiny': ClipConfig(
        embed_dim=32,
        image_size=32,
        patch_size=8,
        vision_width=64,
        vision_layers=2,
        vision_heads=2,
        text_width=32,
        text_layers=2,
        text_heads=2,
    ),
}
DEFAULT_VARIANT = 'ViT-B/32'


def get_config(variant: str | ClipConfig) -> ClipConfig:
  """Returns the config of a variant name, or the config itself."""
  if isinstance(variant, ClipConfig):
    return variant
  if variant not in VARIANTS:
    raise ValueError(
        f'Unknown CLIP variant {variant!r}; known: {sorted(VARIANTS)}.'
    )
  return VARIANTS[variant]


def variant_name(config: ClipConfig) -> str | None:
  """Returns the VARIANTS name of a config, or None for a custom one."""
  return next((n for n, c in VARIANTS.items() if c == config), None)


def quick_gelu(x: jax.Array) -> jax.Array:
  """The GELU approximation OpenAI trained CLIP with: x * sigmoid(1.702 x)."""
  return x * jax.nn.sigmoid(1.702 * x)


def layer_norm(name: str) -> nn.LayerNorm:
  # The two-pass variance: the CLIP residual stream has channels with large
  # means, where E[x^2] - E[x]^2 cancels badly in float32.
  return nn.LayerNorm(
      epsilon=LAYER_NORM_EPS, use_fast_variance=False, name=name
  )


class SelfAttention(nn.Module):
  """Multi-head self-attention with one fused q/k/v projection."""

  num_heads: int
  causal: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x: float [B, L, W]. Returns: float [B, L, W]."""
    b, l, w = x.shape
    # Fused like OpenAI's in_proj_weight: columns are q, then k, then v,
    # each head-major, so the checkpoint maps by a transpose alone.
    qkv = nn.Dense(3 * w, name='in_proj')(x)
    qkv = qkv.reshape(b, l, 3, self.num_heads, w // self.num_heads)
    q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]  # [B, L, H, D]
    out = jax.nn.dot_product_attention(q, k, v, is_causal=self.causal)
    return nn.Dense(w, name='out_proj')(out.reshape(b, l, w))


class Mlp(nn.Module):
  """Two-layer QuickGELU MLP of a residual block."""

  ratio: int = 4

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x: float [..., W]. Returns: float [..., W]."""
    w = x.shape[-1]
    x = quick_gelu(nn.Dense(self.ratio * w, name='c_fc')(x))
    return nn.Dense(w, name='c_proj')(x)


class ResidualBlock(nn.Module):
  """Pre-LayerNorm transformer block: attention, then MLP."""

  num_heads: int
  mlp_ratio: int = 4
  causal: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x: float [B, L, W]. Returns: float [B, L, W]."""
    attn = SelfAttention(self.num_heads, self.causal, name='attn')
    x = x + attn(layer_norm('ln_1')(x))
    return x + Mlp(self.mlp_ratio, name='mlp')(layer_norm('ln_2')(x))


class Transformer(nn.Module):
  """A stack of residual blocks named resblocks_0, resblocks_1, ..."""

  num_layers: int
  num_heads: int
  mlp_ratio: int = 4
  causal: bool = False

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:
    """Args: x: float [B, L, W]. Returns: float [B, L, W]."""
    for i in range(self.num_layers):
      x = ResidualBlock(
          self.num_heads, self.mlp_ratio, self.causal, name=f'resblocks_{i}'
      )(x)
    return x


class VisionTransformer(nn.Module):
  """CLIP ViT: patches, class token, learned positions, pooled class token."""

  config: ClipConfig

  @nn.compact
  def __call__(self, images: jax.Array) -> jax.Array:
    """Embeds normalised images.

    Args:
      images: float [B, S, S, 3], S = config.image_size, CLIP-normalised.

    Returns:
      float [B, E], unnormalised image features.
    """
    c = self.config
    chex.assert_shape(images, (None, c.image_size, c.image_size, 3))
    w = c.vision_width
    init = nn.initializers.normal(w**-0.5)
    x = nn.Conv(
        w,
        (c.patch_size, c.patch_size),
        strides=(c.patch_size, c.patch_size),
        padding='VALID',
        use_bias=False,
        name='conv1',
    )(images)  # [B, G, G, W]
    b = x.shape[0]
    # Row-major over (row, column), the order of OpenAI's flatten(2).
    x = x.reshape(b, c.grid_size**2, w)  # [B, G*G, W]
    cls = self.param('class_embedding', init, (w,))
    x = jnp.concatenate(
        [jnp.broadcast_to(cls.astype(x.dtype), (b, 1, w)), x], axis=1
    )  # [B, G*G+1, W]
    x = x + self.param('positional_embedding', init, (c.grid_size**2 + 1, w))
    x = layer_norm('ln_pre')(x)
    x = Transformer(
        c.vision_layers, c.vision_heads, c.mlp_ratio, name='transformer'
    )(x)
    x = layer_norm('ln_post')(x[:, 0])  # [B, W]
    return x @ self.param('proj', init, (w, c.embed_dim))  # [B, E]


class TextTransformer(nn.Module):
  """CLIP text tower: causal transformer pooled at the end-of-text token."""

  config: ClipConfig

  @nn.compact
  def __call__(self, tokens: jax.Array) -> jax.Array:
    """Embeds token rows.

    Args:
      tokens: int [P, T], T <= context_length, rows from tokenizer.tokenize.

    Returns:
      float [P, E], unnormalised text features.
    """
    c = self.config
    chex.assert_rank(tokens, 2)
    w = c.text_width
    num_tokens = tokens.shape[1]
    if num_tokens > c.context_length:
      raise ValueError(
          f'Token rows of length {num_tokens} exceed the context length '
          f'{c.context_length}.'
      )
    x = nn.Embed(
        c.vocab_size,
        w,
        embedding_init=nn.initializers.normal(0.02),
        name='token_embedding',
    )(tokens)  # [P, T, W]
    pos = self.param(
        'positional_embedding',
        nn.initializers.normal(0.01),
        (c.context_length, w),
    )
    x = x + pos[:num_tokens]
    x = Transformer(
        c.text_layers, c.text_heads, c.mlp_ratio, causal=True,
        name='transformer',
    )(x)
    x = layer_norm('ln_final')(x)
    # The end token has the largest id, so argmax finds it (OpenAI's rule);
    # the causal mask makes the padding after it irrelevant.
    eot = jnp.argmax(tokens, axis=-1)  # [P]
    x = x[jnp.arange(x.shape[0]), eot]  # [P, W]
    proj = self.param(
        'text_projection', nn.initializers.normal(w**-0.5), (w, c.embed_dim)
    )
    return x @ proj  # [P, E]


class Clip(nn.Module):
  """Both CLIP towers and the log-space logit scale."""

  config: ClipConfig

  @nn.compact
  def __call__(
      self, images: jax.Array | None = None, tokens: jax.Array | None = None
  ) -> tuple[jax.Array | None, jax.Array | None]:
    """Runs the towers whose inputs are given.

    Args:
      images: float [B, S, S, 3] CLIP-normalised images, or None.
      tokens: int [P, T] token rows, or None.

    Returns:
      (float [B, E] or None, float [P, E] or None), unnormalised features.
    """
    # Stored as a log so that training it kept the scale positive; here it
    # is frozen, and kept only so checkpoints round-trip.
    self.param(
        'logit_scale', nn.initializers.constant(LOGIT_SCALE_INIT), ()
    )
    image_features = text_features = None
    if images is not None:
      image_features = VisionTransformer(self.config, name='visual')(images)
    if tokens is not None:
      text_features = TextTransformer(self.config, name='text')(tokens)
    return image_features, text_features


def _dummy_inputs(config: ClipConfig) -> tuple[jax.Array, jax.Array]:
  images = jnp.zeros((1, config.image_size, config.image_size, 3))
  tokens = jnp.zeros((1, config.context_length), jnp.int32)
  return images, tokens


def init_params(config: ClipConfig, key: jax.Array) -> dict:
  """Returns random parameters, a nested dict of float32 arrays."""
  images, tokens = _dummy_inputs(config)
  # Jitted: op-by-op initialisation dispatches thousands of small ops.
  return jax.jit(Clip(config).init)(key, images, tokens)['params']


def param_shapes(config: ClipConfig) -> dict:
  """Returns the parameter tree of jax.ShapeDtypeStruct, without compute."""
  images, tokens = _dummy_inputs(config)
  variables = jax.eval_shape(
      Clip(config).init, jax.random.key(0), images, tokens
  )
  return variables['params']


def l2_normalize(x: jax.Array) -> jax.Array:
  """Divides the last axis by (its L2 norm + 1e-8)."""
  return x / (jnp.linalg.norm(x, axis=-1, keepdims=True) + NORMALIZE_EPS)


@functools.partial(jax.jit, static_argnames='config')
def encode_image(
    params: dict, images: jax.Array, *, config: ClipConfig
) -> jax.Array:
  """Embeds preprocessed images.

  Args:
    params: parameter tree of Clip(config).
    images: float [B, S, S, 3], output of preprocess.preprocess.
    config: the model's shapes (static: a new config recompiles).

  Returns:
    float32 [B, E], unit-norm image embeddings.
  """
  # The towers are frozen: no gradient may reach their weights.
  params = jax.lax.stop_gradient(params)
  features, _ = Clip(config).apply({'params': params}, images=images)
  return l2_normalize(features)


@functools.partial(jax.jit, static_argnames='config')
def encode_text(
    params: dict, tokens: jax.Array, *, config: ClipConfig
) -> jax.Array:
  """Embeds token rows.

  Args:
    params: parameter tree of Clip(config).
    tokens: int [P, T], rows from tokenizer.tokenize.
    config: the model's shapes (static: a new config recompiles).

  Returns:
    float32 [P, E], unit-norm text embeddings.
  """
  params = jax.lax.stop_gradient(params)  # frozen, as in encode_image
  _, features = Clip(config).apply({'params': params}, tokens=tokens)
  return l2_normalize(features)


class TextEmbeddingCache:
  """Prompt-set embeddings for one set of frozen weights, each made once.

  Prompt embeddings never change during a run, so each tuple of prompts is
  tokenized and encoded on first use and served from a dict afterwards. The
  object owns its params: a cache keyed by id(params) would go stale if the
  params were freed and the id reused.
  """

  def __init__(self, params: dict, config: ClipConfig):
    """Args: params: parameter tree of Clip(config). config: its shapes."""
    self._params = params
    self._config = config
    self._cache = {}

  def __call__(self, prompts: Sequence[str]) -> jax.Array:
    """Returns float32 [P, E], unit-norm embeddings of the prompts in order."""
    key = tuple(prompts)
    if key not in self._cache:
      tokens = tokenizer.tokenize(key, self._config.context_length)
      # Under the causal mask nothing after the last end token reaches the
      # pooled features, so those columns are dropped: 77 -> 7 tokens for
      # the paper's prompts, 11x less work, same embeddings.
      tokens = tokens[:, : int(tokens.argmax(axis=-1).max()) + 1]
      self._cache[key] = encode_text(
          self._params, jnp.asarray(tokens), config=self._config
      )
    return self._cache[key]
