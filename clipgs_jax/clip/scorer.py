"""View scorers on the frozen Flax CLIP tower: image-level and per-pixel.

`ClipScorer` is the paper's (one score per view); `DenseClipScorer` gives a
per-pixel p(distractor) map from per-patch embeddings (clip/dense.py).
Imported only by `guidance.make_scorer` when the config asks for CLIP.
"""

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from clipgs_jax import config as config_lib
from clipgs_jax import guidance_config
from clipgs_jax import semantic
from clipgs_jax.clip import dense
from clipgs_jax.clip import model
from clipgs_jax.clip import preprocess


@flax.struct.dataclass
class ClipScorer:
  """Scores a rendered view against the distractor and static prompts.

  Attributes:
    params: frozen CLIP parameters (used under stop_gradient).
    distractor: float32 [P, E], unit-norm embeddings of the prompts D.
    static: float32 [Q, E], of the prompts S; Q = 0 logs NaN for s_hat_s.
    config: the tower's shapes (static).
  """
  params: Any
  distractor: jax.Array
  static: jax.Array
  config: model.ClipConfig = flax.struct.field(pytree_node=False)

  def score(self, image: jax.Array, view: jax.Array) -> dict[str, jax.Array]:
    """Eqs. 5-7 on float [H, W, 3] in [0, 1], resized to the tower's
    input (224x224 for every OpenAI ViT)."""
    del view
    x = preprocess.preprocess(jax.lax.stop_gradient(image)[None],
                              mode="resize", size=self.config.image_size)
    feature = model.encode_image(self.params, x, config=self.config)[0]
    s_hat_s = (semantic.normalized_max_cosine(feature, self.static)
               if self.static.shape[0] else jnp.float32(jnp.nan))
    return {"s_hat_d": semantic.normalized_max_cosine(feature,
                                                      self.distractor),
            "s_hat_s": s_hat_s}


def make(sem: guidance_config.SemanticConfig,
         clip_params: tuple[model.ClipConfig, Any]) -> ClipScorer:
  """The image-level scorer of the tower, its prompts embedded once.

  Args:
    sem: the prompts.
    clip_params: (ClipConfig, params): weights.load's (guidance.make_scorer
      loads them once for either scorer), or random weights for timing and
      tests.
  """
  config, params = clip_params
  texts = model.TextEmbeddingCache(params, config)
  distractor = texts(sem.distractor_prompts)
  static = (texts(sem.static_prompts) if sem.static_prompts else
            jnp.zeros((0, distractor.shape[1]), jnp.float32))
  return ClipScorer(params=params, distractor=distractor, static=static,
                    config=config)


# The dense scorer's default input side: 448 = 2 x 224 gives ViT-B/32 a
# 14 x 14 patch grid (7 x 7 at CLIP's own 224) for about 4x the cost.
DENSE_INPUT_SIZE = 448


@flax.struct.dataclass
class DenseClipScorer:
  """Per-pixel p(distractor) of a rendered view from per-patch CLIP.

  Attributes:
    params: frozen CLIP parameters (used under stop_gradient).
    distractor: float32 [P, E], unit-norm embeddings of the prompts D.
    static: float32 [Q, E], of the prompts S; Q >= 1 (make_dense checks).
    logit_scale: float32 [], exp of the checkpoint's log scale (100 for
      OpenAI's ViT-B/32), the temperature of the prompt softmax.
    config: the tower's shapes (static).
    input_size: side of the square CLIP input in pixels (static); the
      patch grid is input_size // patch_size per side.
    readout: one of dense.READOUTS (static).
  """
  params: Any
  distractor: jax.Array
  static: jax.Array
  logit_scale: jax.Array
  config: model.ClipConfig = flax.struct.field(pytree_node=False)
  input_size: int = flax.struct.field(pytree_node=False,
                                      default=DENSE_INPUT_SIZE)
  readout: str = flax.struct.field(pytree_node=False,
                                   default=dense.DEFAULT_READOUT)

  @property
  def grid(self) -> int:
    """Patches per side of the CLIP input."""
    return self.input_size // self.config.patch_size

  def patch_probabilities(self, image: jax.Array) -> jax.Array:
    """p(distractor) per patch of float [H, W, 3] in [0, 1].

    The view is squashed to input_size x input_size as ClipScorer squashes
    it to 224 (nothing cropped). Returns float32 [g, g], g = self.grid.
    """
    x = preprocess.preprocess(jax.lax.stop_gradient(image)[None],
                              mode="resize", size=self.input_size)
    features = dense.encode_dense(self.params, x, config=self.config,
                                  readout=self.readout)[0]  # [g, g, E]
    return dense.distractor_probability(features, self.distractor,
                                        self.static, self.logit_scale)

  def score_map(self, image: jax.Array, view: jax.Array) -> jax.Array:
    """Per-pixel p(distractor) of a render.

    Args:
      image: float [H, W, 3] in [0, 1], the rendered view (no gradient
        flows back through it).
      view: int32 [], the view index (unused; the oracle scorers need it).

    Returns:
      float32 [H, W] in [0, 1]: the patch map, bilinearly upsampled.
    """
    del view
    h, w = image.shape[0], image.shape[1]
    return dense.upsample(self.patch_probabilities(image), h, w)


def make_dense(sem: guidance_config.SemanticConfig,
               clip_params: tuple[model.ClipConfig, Any],
               *,
               input_size: int = DENSE_INPUT_SIZE,
               readout: str = dense.DEFAULT_READOUT) -> DenseClipScorer:
  """The dense scorer of the tower, its prompts embedded once.

  Args:
    sem: the prompts.
    clip_params: (ClipConfig, params), as `make`'s.
    input_size: side of the CLIP input, a multiple of the patch size
      (448: a 14 x 14 grid for ViT-B/32).
    readout: one of dense.READOUTS.

  Raises:
    ValueError: no distractor or no static prompts (with S empty the
      softmax gives p(distractor) = 1 everywhere), a bad input_size or
      readout.
  """
  if not sem.distractor_prompts or not sem.static_prompts:
    raise ValueError(
        "The dense CLIP scorer needs both distractor_prompts (D) and "
        "static_prompts (S): p(distractor) is a softmax over D and S, so "
        "with S empty it is 1 at every pixel and with D empty it is 0. Got "
        f"D={tuple(sem.distractor_prompts)}, "
        f"S={tuple(sem.static_prompts)}; give at least one of each.")
  dense.check_readout(readout)
  config, params = clip_params
  dense.check_input_size(input_size, config)
  texts = model.TextEmbeddingCache(params, config)
  return DenseClipScorer(
      params=params, distractor=texts(sem.distractor_prompts),
      static=texts(sem.static_prompts),
      logit_scale=jnp.exp(jnp.asarray(params["logit_scale"], jnp.float32)),
      config=config, input_size=input_size, readout=readout)
