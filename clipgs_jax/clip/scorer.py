"""The paper's view scorer: the frozen Flax CLIP tower on the rendered view.

Imported only by `guidance.make_scorer` when the config asks for CLIP.
"""

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from clipgs_jax import config as config_lib
from clipgs_jax import semantic
from clipgs_jax.clip import model
from clipgs_jax.clip import preprocess
from clipgs_jax.clip import weights


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


def make(sem: config_lib.SemanticConfig, *, weights_path: str | None = None,
         clip_params: tuple[model.ClipConfig, Any] | None = None
         ) -> ClipScorer:
  """Loads the tower (or takes `clip_params`) and embeds the prompts once.

  Args:
    sem: prompts and the variant (sem.clip_variant).
    weights_path: --clip_weights; unset falls back to $CLIPGS_CLIP_WEIGHTS,
      and neither set raises a ValueError that says how to give weights.
    clip_params: (ClipConfig, params) instead of a file (random weights
      for timing, tests).
  """
  if clip_params is None:
    config, params = weights.load(weights.resolve_weights_path(weights_path),
                                  sem.clip_variant)
  else:
    config, params = clip_params
  texts = model.TextEmbeddingCache(params, config)
  distractor = texts(sem.distractor_prompts)
  static = (texts(sem.static_prompts) if sem.static_prompts else
            jnp.zeros((0, distractor.shape[1]), jnp.float32))
  return ClipScorer(params=params, distractor=distractor, static=static,
                    config=config)
