"""Tests for the CLIP scorer wired through guidance, and its lazy import."""

import dataclasses
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from clipgs_jax import config
from clipgs_jax import guidance
from clipgs_jax import guidance_config
from clipgs_jax import step
from clipgs_jax import train
from test_train import TEST_CFG, synthetic_scene  # pylint: disable=g-bad-import-order


class ClipScorerTest(absltest.TestCase):
  """The paper's scorer on random "tiny" weights (shapes, not semantics)."""

  def setUp(self):
    super().setUp()
    from clipgs_jax.clip import model  # pylint: disable=g-import-not-at-top
    self.model = model
    self.clip_config = model.get_config("tiny")
    self.params = model.init_params(self.clip_config, jax.random.key(0))
    self.sem = guidance_config.SemanticConfig(scorer="clip",
                                              clip_variant="tiny",
                                              accumulate_start=0)
    self.scorer = guidance.make_scorer(
        config.Config(semantic=self.sem), None,
        clip_params=(self.clip_config, self.params))

  def test_scores_are_the_towers_cosines(self):
    from clipgs_jax.clip import preprocess  # pylint: disable=g-import-not-at-top
    image = jax.random.uniform(jax.random.key(1), (24, 40, 3))
    got = self.scorer.score(image, jnp.int32(0))
    feature = self.model.encode_image(
        self.params, preprocess.preprocess(image[None], size=32),
        config=self.clip_config)[0]
    texts = self.model.TextEmbeddingCache(self.params, self.clip_config)
    for key, prompts in (("s_hat_d", self.sem.distractor_prompts),
                         ("s_hat_s", self.sem.static_prompts)):
      cos = np.asarray(texts(prompts) @ feature)
      np.testing.assert_allclose(got[key], (cos.max() + 1) / 2, rtol=1e-5)

  def test_step_scores_and_accumulates(self):
    scene = synthetic_scene()
    cfg = train.resolve(dataclasses.replace(TEST_CFG, semantic=self.sem),
                        scene)
    state = train.initial_state(cfg, scene)
    step_fn, lanes, state, scorer = step.for_scene(cfg, scene, state,
                                                   self.scorer)
    state, metrics = step_fn(state, lanes, scorer)
    s_hat_d = float(metrics["s_hat_d"][0])
    self.assertTrue(0.0 <= s_hat_d <= 1.0)
    seen = np.asarray(state.semantic.n) > 0
    self.assertGreater(seen.sum(), 0)
    np.testing.assert_allclose(
        np.asarray(state.semantic.acc)[seen],
        0.1 * max(0.0, s_hat_d - 0.5), rtol=1e-5)


  def test_dense_maps_of_the_training_views(self):
    from clipgs_jax.clip import scorer as clip_scorer  # pylint: disable=g-import-not-at-top
    scene = synthetic_scene()
    sem = dataclasses.replace(self.sem, evidence="pixel",
                              dense_input_size=64)     # 8x8 tiny patches
    clip_params = (self.clip_config, self.params)
    scorer = guidance.make_scorer(config.Config(semantic=sem), scene,
                                  clip_params=clip_params)
    self.assertIsInstance(scorer, guidance.PixelMapScorer)
    self.assertEqual(scorer.maps.shape, scene.train.images.shape[:3])
    self.assertTrue(bool(jnp.all((scorer.maps >= 0) & (scorer.maps <= 1))))
    # Each map is the dense scorer's map of that training photo.
    dense = clip_scorer.make_dense(sem, clip_params=clip_params,
                                   input_size=64)
    np.testing.assert_allclose(
        scorer.score_map(jnp.int32(3)),
        dense.score_map(jnp.asarray(scene.train.images[3]), jnp.int32(3)),
        atol=1e-6)


class NoClipImportTest(absltest.TestCase):

  def test_off_and_oracle_never_import_clip(self):
    # A fresh interpreter: other tests in this process import CLIP.
    code = textwrap.dedent("""
        import sys
        from clipgs_jax import config, guidance, guidance_config, train
        from clipgs_jax.data import default_scene, scene
        s = scene.load_scene(default_scene.ensure_default_scene(),
                             downscale=4)
        for sem in (guidance_config.SemanticConfig(),
                    guidance_config.SemanticConfig(scorer="oracle"),
                    guidance_config.SemanticConfig(scorer="oracle",
                                                   evidence="pixel")):
          guidance.make_scorer(config.Config(semantic=sem), s)
        clip = [m for m in sys.modules if m.startswith("clipgs_jax.clip")]
        assert not clip, clip
        """)
    subprocess.run([sys.executable, "-c", code], check=True,
                   cwd=os.path.dirname(os.path.dirname(__file__)))


if __name__ == "__main__":
  absltest.main()
