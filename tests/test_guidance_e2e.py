"""End to end on the embedded default scene: ORACLE-PIXEL prunes transients.

Every training view of the scene is cluttered by objects that stay put for
3-6 shots, and 19 % of its sparse points lie on them (transients.json,
`transient_points`), as structure from motion would triangulate them. The
Gaussians initialised from those points fit the transients, so a short run
with pixel evidence must prune many of them and (almost) no static ones.
Densify is off so that a row's fate is the semantic prune's alone. (The image-level
rule cannot do this here: with every view cluttered it scores every
Gaussian alike, BUILD_NOTES "Transient benchmark"; the prune guard then
refuses it.)
"""

import json
import os

import jax
import numpy as np
from absl.testing import absltest

from clipgs_jax import config
from clipgs_jax import guidance
from clipgs_jax import guidance_config
from clipgs_jax import train
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib

STEPS = 300


class PixelOracleEndToEndTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    # 300 training steps: worth XLA's optimisations (conftest turns them off
    # to make the many small test programs compile fast): ~4x faster here.
    saved = jax.config.read("jax_disable_most_optimizations")
    jax.config.update("jax_disable_most_optimizations", False)
    self.addCleanup(jax.config.update, "jax_disable_most_optimizations",
                    saved)

  def test_pixel_oracle_prunes_the_transient_points(self):
    path = default_scene.ensure_default_scene()
    scene = scene_lib.load_scene(path, downscale=2)
    with open(os.path.join(path, "transients.json")) as f:
      on_transient = np.zeros(len(scene.points), bool)
      on_transient[json.load(f)["transient_points"]] = True
    sem = guidance_config.SemanticConfig(scorer="oracle",
                                         evidence="pixel",
                                         n_min=0.0).scaled_to(STEPS)
    cfg = config.Config(
        densify=config.DensifyConfig(start=STEPS),    # never densifies
        train=config.TrainConfig(steps=STEPS, eval_every=0,
                                 checkpoint_every=0, log_every=100),
        semantic=sem)
    result = train.fit(train.resolve(cfg, scene), scene,
                       self.create_tempdir().full_path,
                       scorer=guidance.make_scorer(cfg, scene),
                       progress=False)
    # Rows 0..P-1 are the sparse points, in order (initialize.initialize).
    alive = np.asarray(result.state.alive)[:len(scene.points)]
    transient_pruned = 1.0 - alive[on_transient].mean()
    static_pruned = 1.0 - alive[~on_transient].mean()
    out = {"transient_pruned": transient_pruned,
           "static_pruned": static_pruned,
           "test_psnr": result.curve[-1]["test_psnr"]}
    # Measured 2026-11-22 (BUILD_NOTES "Localized evidence"): 22.6 % of the
    # transient rows pruned and 0.0 % of the static rows. Agreement-weighted
    # evidence is conservative at 300 steps (a transient counts only where
    # the render already reproduces it); it must never hit the static scene.
    self.assertGreater(transient_pruned, 0.15, out)
    self.assertLess(static_pruned, 0.01, out)
    self.assertFalse(any(e["guarded"] for e in result.prune_events), out)


if __name__ == "__main__":
  absltest.main()
