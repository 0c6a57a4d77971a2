"""Tests for guidance: schedule, scorers, prune bookkeeping, the wired step."""

import dataclasses
import functools

import chex
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from clipgs_jax import config
from clipgs_jax import densify
from clipgs_jax import guidance
from clipgs_jax import guidance_config
from clipgs_jax import sharding
from clipgs_jax import state as state_lib
from clipgs_jax import step
from clipgs_jax import train
from test_densify import CFG as DENSIFY_CFG  # pylint: disable=g-bad-import-order
from test_densify import _drive, _make_state, _row_leaves, _tag_state  # pylint: disable=g-bad-import-order
from test_train import CompileCounter, TEST_CFG, synthetic_scene  # pylint: disable=g-bad-import-order

ORACLE = guidance_config.SemanticConfig(scorer="oracle")


@flax.struct.dataclass
class _NanScorer:
  """A broken image-level scorer: NaN for every view."""

  def score(self, image, view):
    del image, view
    return {k: jnp.float32(jnp.nan) for k in guidance.SCORE_KEYS}


def _cfg(**semantic_fields):
  """The oracle config; the prune guard is lifted (tests of eq. 13 itself;
  the guard has its own tests)."""
  semantic_fields.setdefault("max_prune_fraction", 1.0)
  return dataclasses.replace(
      DENSIFY_CFG, semantic=dataclasses.replace(ORACLE, **semantic_fields))


def _state_with_stats(acc, n, opacity, alive):
  """A 4..8-row state whose semantic stats and opacities are given."""
  c = len(acc)
  state = _make_state(c, c, np.random.default_rng(0))
  logits = np.log(np.asarray(opacity) / (1 - np.asarray(opacity)))
  return state.replace(
      alive=jnp.asarray(alive),
      params=state.params.replace(
          opacity_logits=jnp.asarray(logits, jnp.float32)),
      semantic=state_lib.SemanticStats(acc=jnp.asarray(acc, jnp.float32),
                                       weight=jnp.asarray(n, jnp.float32),
                                       n=jnp.asarray(n, jnp.float32)))


class ScheduleTest(parameterized.TestCase):

  def test_scores_due(self):
    sem = guidance_config.SemanticConfig(accumulate_start=5, score_every=3)
    due = [bool(guidance.scores_due(jnp.int32(s), sem)) for s in range(12)]
    # Steps 5, 8, 11 score; nothing before accumulate_start.
    self.assertEqual([s for s, d in enumerate(due) if d], [5, 8, 11])

  def test_prune_due(self):
    cfg = config.Config(
        train=config.TrainConfig(steps=20_000),
        semantic=guidance_config.SemanticConfig(scorer="oracle"))
    due = [s for s in range(20_001) if guidance.prune_due(s, cfg)]
    # From 5000 every 1000; never after the last step (as densify.due).
    self.assertEqual(due, list(range(5000, 20_000, 1000)))
    off = dataclasses.replace(cfg, semantic=guidance_config.SemanticConfig())
    self.assertFalse(any(guidance.prune_due(s, off) for s in range(20_001)))
    # The opacity-loss-only ablation never prunes.
    reg_only = dataclasses.replace(cfg,
                                   semantic=guidance_config.SemanticConfig(
                                       scorer="oracle", prune=False))
    self.assertFalse(any(guidance.prune_due(s, reg_only)
                         for s in range(20_001)))

  def test_reset_quiet(self):
    # Resets after 3000 and 6000 finished steps (not at 9000 = steps).
    cfg = config.Config(train=config.TrainConfig(steps=9000),
                        densify=config.DensifyConfig(opacity_reset_every=3000),
                        semantic=guidance_config.SemanticConfig(
                            scorer="oracle",
                            reg_start=0,
                            prune_start=250,
                            prune_every=250,
                            reset_quiet=500))
    due = [s for s in range(9001) if guidance.prune_due(s, cfg)]
    # The prune right before a reset stays; 3250, 3500 and 6250, 6500 go.
    expected = [s for s in range(250, 9000, 250)
                if s not in (3250, 3500, 6250, 6500)]
    self.assertEqual(due, expected)
    logits = jnp.zeros(4)
    stats = state_lib.SemanticStats(acc=jnp.ones(4), weight=jnp.ones(4),
                                    n=jnp.ones(4))
    alive = jnp.ones(4, bool)
    loss = jax.jit(lambda step: guidance.opacity_regularizer(
        stats, logits, alive, step, cfg))
    on = [s for s in (2999, 3000, 3499, 3500, 5999, 6000, 6499, 6500, 8999)
          if float(loss(jnp.int32(s))) > 0]
    self.assertEqual(on, [2999, 3500, 5999, 6500, 8999])
    paper = dataclasses.replace(
        cfg, semantic=dataclasses.replace(cfg.semantic, reset_quiet=0))
    self.assertEqual([s for s in range(9001) if guidance.prune_due(s, paper)],
                     list(range(250, 9000, 250)))

  def test_scaled_schedule(self):
    sem = guidance_config.SemanticConfig().scaled_to(2000)
    # 500/2000/5000/1000 of 20k steps -> one tenth.
    self.assertEqual((sem.accumulate_start, sem.reg_start, sem.prune_start,
                      sem.prune_every), (50, 200, 500, 100))
    # The warm-up's rate grows as the run shrinks: the same share at the
    # same fraction of the run (0.024 exactly at the table's 2,500 steps).
    rc = guidance_config.ResidualConfig()
    self.assertAlmostEqual(rc.scaled_to(2000).warmup, 0.03)
    self.assertEqual(rc.scaled_to(2500).warmup, 0.024)
    # The residual map's start scales like the other starts; 0 stays 0.
    self.assertEqual(
        guidance_config.ResidualConfig(start=5000).scaled_to(2000).start, 500)
    self.assertEqual(
        guidance_config.ResidualConfig(start=0).scaled_to(2000).start, 0)
    # The early uniformity gate ends at a step, whatever the run's length.
    self.assertEqual(rc.scaled_to(2500).uniform_until, 1250)
    self.assertEqual(rc.scaled_to(7000).uniform_until, 1250)
    # Config.scaled_to scales both sections.
    both = config.Config().scaled_to(2000)
    self.assertEqual((both.semantic, both.residual),
                     (sem, rc.scaled_to(2000)))


class ScorerTest(absltest.TestCase):

  def test_oracle(self):
    masks = np.zeros((2, 4, 5), bool)
    masks[1, :2, :] = True                      # 10 of 20 pixels: f = 0.5
    scorer = guidance.OracleScorer(masks=jnp.asarray(masks), saturation=0.25)
    image = jnp.zeros((4, 5, 3))
    clean = scorer.score(image, jnp.int32(0))
    self.assertEqual(float(clean["s_hat_d"]), 0.5)   # clean view: neutral
    self.assertTrue(np.isnan(clean["s_hat_s"]))       # no static score
    # f / saturation = 2 -> capped at 1 -> s_hat_d = 0.5 + 0.5 = 1.
    self.assertEqual(float(scorer.score(image, jnp.int32(1))["s_hat_d"]), 1.0)

  def test_oracle_needs_masks(self):
    scene = synthetic_scene(num=8, size=8, num_train=2, num_test=1)
    with self.assertRaisesRegex(ValueError, "masks/"):
      guidance.make_scorer(config.Config(semantic=ORACLE), scene)

  def test_off_imports_nothing(self):
    self.assertIsNone(guidance.make_scorer(config.Config(), None))

  def test_pixel_oracle_maps_are_the_masks(self):
    scene = _masked_scene()
    scorer = guidance.make_scorer(
        config.Config(semantic=guidance_config.SemanticConfig(
            scorer="oracle", evidence="pixel")), scene)
    self.assertIsInstance(scorer, guidance.PixelMapScorer)
    np.testing.assert_array_equal(scorer.score_map(jnp.int32(2)),
                                  scene.train.masks[2].astype(np.float32))

  def test_uniform_control_spreads_the_masks_mean(self):
    scene = _masked_scene()
    uniform = config.Config(semantic=guidance_config.SemanticConfig(
        scorer="uniform", evidence="pixel"))
    scorer = guidance.make_scorer(uniform, scene)
    fraction = np.mean(scene.train.masks)
    self.assertGreater(fraction, 0.0)
    for view in range(scene.train.masks.shape[0]):
      np.testing.assert_allclose(scorer.score_map(jnp.int32(view)),
                                 np.full(scene.train.masks.shape[1:],
                                         fraction), rtol=1e-6)
    no_masks = synthetic_scene(num=8, size=8, num_train=2, num_test=1)
    with self.assertRaisesRegex(ValueError, "'uniform' reads ground-truth"):
      guidance.make_scorer(uniform, no_masks)

  def test_score_and_accumulate(self):
    sem = guidance_config.SemanticConfig(scorer="oracle",
                                         accumulate_start=3,
                                         score_every=2,
                                         beta=0.1)
    masks = np.zeros((1, 2, 2), bool)
    masks[0, 0, 0] = True                       # f = 0.25
    scorer = guidance.OracleScorer(masks=jnp.asarray(masks), saturation=0.5)
    stats = state_lib.SemanticStats.zeros(3)
    visible = jnp.array([True, False, True])
    image = jnp.zeros((2, 2, 3))
    fn = jax.jit(guidance.score_and_accumulate, static_argnums=(7,))
    # Step 2: before accumulate_start -> unchanged, not scored.
    out, scores = fn(stats, image, visible, None, jnp.int32(0), jnp.int32(2),
                     scorer, sem)
    chex.assert_trees_all_equal(out, stats)
    self.assertFalse(scores["scored"])
    # Step 3: s_hat_d = 0.5 + 0.5 * 0.25 / 0.5 = 0.75; gain 0.1 * 0.25.
    out, scores = fn(stats, image, visible, None, jnp.int32(0), jnp.int32(3),
                     scorer, sem)
    self.assertTrue(scores["scored"])
    self.assertAlmostEqual(float(scores["s_hat_d"]), 0.75, places=6)
    np.testing.assert_allclose(out.acc, [0.025, 0.0, 0.025], rtol=1e-6)
    np.testing.assert_array_equal(out.n, [1, 0, 1])
    # Step 4: off cadence (score_every 2) -> unchanged.
    out4, _ = fn(out, image, visible, None, jnp.int32(0), jnp.int32(4),
                 scorer, sem)
    chex.assert_trees_all_equal(out4, out)


class PruneTest(parameterized.TestCase):

  def test_prune_by_condition(self):
    cfg = _cfg(tau=0.015, n_min=10.0, alpha_min=0.1, beta=0.1)
    # s_j = acc / n: 0.0205 (> tau), 0.0105, 0 (n = 0), 0.0105, 0.03 (dead).
    acc = [0.205, 0.105, 0.0, 0.0525, 0.3]
    n = [10.0, 10.0, 0.0, 5.0, 10.0]
    opacity = [0.5, 0.05, 0.05, 0.5, 0.5]
    alive = [True, True, True, True, False]
    state = _state_with_stats(acc, n, opacity, alive)
    before = jax.device_get(state.params)
    state, info = guidance.prune(state, cfg=cfg)
    # The parameters stay, pruned rows included: fit gathers the removed
    # rows after the prune (loop.semantic_prune).
    chex.assert_trees_all_equal(state.params, before)
    # Row 0: semantic. Row 2: n = 0 < 10 and alpha 0.05 < 0.1: visibility.
    # Row 1: n = 10 is not < 10. Row 3: alpha 0.5. Row 4 was dead.
    np.testing.assert_array_equal(state.alive, [False, True, False, True,
                                                False])
    self.assertEqual(int(info["num_pruned_semantic"]), 1)
    self.assertEqual(int(info["num_pruned_visibility"]), 1)
    self.assertEqual(int(info["num_alive_before"]), 4)
    # Pruned rows' statistics and moments are cleared; others kept.
    np.testing.assert_allclose(state.semantic.acc,
                               [0, 0.105, 0, 0.0525, 0.3])
    np.testing.assert_allclose(state.semantic.n, [0, 10, 0, 5, 10])
    for leaf in _row_leaves(state):
      self.assertTrue(np.all(leaf[0] == 0) and np.all(leaf[2] == 0))
    # Histogram over alive rows before the prune: bins of width 0.001 on
    # [0, 0.05]; s = 0.0205, 0.0105, 0, 0.0105 -> bins 20, 10, 0, 10.
    hist = np.asarray(info["histogram"])
    self.assertEqual(hist.sum(), 4)
    self.assertEqual(hist[10], 2)
    self.assertEqual(hist[0], 1)
    self.assertEqual(hist[20], 1)

  def test_spared_rows_stay_out_of_the_semantic_clause(self):
    cfg = _cfg(tau=0.015, n_min=10.0, alpha_min=0.1, beta=0.1)
    # Rows 0 and 1 are over tau; row 2 is rarely seen and faint.
    state = _state_with_stats([0.205, 0.3, 0.0], [10.0, 10.0, 0.0],
                              [0.5, 0.5, 0.05], [True, True, True])
    semantic_rows, _ = guidance.prune_candidates(state, cfg)
    np.testing.assert_array_equal(semantic_rows, [True, True, False])
    state, info = guidance.prune(state, jnp.asarray([True, False, False]),
                                 cfg=cfg)
    np.testing.assert_array_equal(state.alive, [True, False, False])
    self.assertEqual(int(info["num_pruned_semantic"]), 1)
    self.assertEqual(int(info["num_pruned_visibility"]), 1)

  @parameterized.parameters((0.0, 2), (1.0, 0))
  def test_tau_edges(self, tau, expected):
    cfg = _cfg(tau=tau, n_min=0.0)
    # s_j = 0.05 (the maximum, beta / 2), 0.001, and 0 (never seen).
    state = _state_with_stats([0.5, 0.01, 0.0, 0.0], [10, 10, 0, 0],
                              [0.5] * 4, [True, True, True, False])
    _, info = guidance.prune(state, cfg=cfg)
    # tau = 0 prunes every alive row with s_j > 0 (rows 0 and 1; s_j = 0
    # is not > 0); tau = 1 prunes none: s_j <= beta / 2 < 1.
    self.assertEqual(int(info["num_pruned_semantic"]), expected)

  def test_rows_stay_aligned_over_densify_and_prune_cycles(self):
    cfg = _cfg(tau=0.5, n_min=3.0, alpha_min=0.1)
    rng = np.random.default_rng(1)
    state = _make_state(64, 16, rng)
    tags = np.zeros(64)
    tags[:16] = np.arange(1, 17)
    state = _tag_state(state, tags)
    def aligned_prune(s):
      return guidance.prune(s, cfg=cfg)
    def aligned_densify(s, k):
      return densify.densify(s, k, cfg=cfg)
    # Fixed capacity: each compiles once over all cycles.
    chex.clear_trace_counter()
    prune_fn = jax.jit(chex.assert_max_traces(aligned_prune, n=1))
    densify_fn = jax.jit(chex.assert_max_traces(aligned_densify, n=1))
    next_tag = 17
    pruned = 0
    for cycle in range(6):
      state, _ = densify_fn(_drive(state, rng), jax.random.key(cycle))
      # Tag new rows; statistics s_j = tag / n chosen so some rows cross tau
      # (n = 1: s = tag > 0.5) and others are rarely seen (n = 2 < 3).
      host = jax.device_get(state)
      tags = np.where(host.alive, host.params.sh_dc[:, 0], 0.0)
      new = host.alive & (tags == 0)
      tags[new] = np.arange(next_tag, next_tag + new.sum())
      next_tag += int(new.sum())
      state = _tag_state(state, tags)
      n = np.where(rng.random(64) < 0.2, 1.0, 2.0 * tags)
      acc = np.where(n == 1.0, tags, 0.0)
      n = jnp.asarray(np.where(host.alive, n, 0.0), jnp.float32)
      state = state.replace(semantic=state_lib.SemanticStats(
          acc=jnp.asarray(acc, jnp.float32), weight=n, n=n))
      before = jax.device_get(state)
      state, info = prune_fn(state)
      after = jax.device_get(state)
      pruned += int(info["num_pruned_semantic"])
      removed = before.alive & ~after.alive
      self.assertEqual(removed.sum(), int(info["num_pruned_semantic"])
                       + int(info["num_pruned_visibility"]))
      # Survivors keep params, statistics and moments of the same row.
      kept = after.alive
      np.testing.assert_array_equal(after.params.sh_dc[kept],
                                    before.params.sh_dc[kept])
      np.testing.assert_array_equal(after.semantic.acc[kept],
                                    before.semantic.acc[kept])
      for m0, m1 in zip(_row_leaves(before), _row_leaves(after)):
        np.testing.assert_array_equal(m1[kept], m0[kept])
        self.assertTrue(np.all(m1[removed] == 0))
      self.assertTrue(np.all(after.semantic.acc[~after.alive] == 0))
      self.assertTrue(np.all(after.semantic.n[~after.alive] == 0))
    self.assertGreater(pruned, 0)


def _one_step(cfg, scene, state, scorer=None):
  """(metrics, state after) of one train step from a copy of `state` (the
  step donates its state; the caller keeps its own)."""
  step_fn, lanes, copy, scorer = step.for_scene(
      cfg, scene, jax.tree.map(jnp.copy, state), scorer)
  after, metrics = step_fn(copy, lanes, scorer)
  return after, metrics


def _masked_scene():
  """The synthetic scene with a transient mask on half its training views."""
  scene = synthetic_scene()
  masks = np.zeros(scene.train.images.shape[:3], bool)
  masks[::2, :8, :8] = True                     # 64 / 1024 px = 1/16
  return dataclasses.replace(
      scene, train=dataclasses.replace(scene.train, masks=masks))


class WiredStepTest(absltest.TestCase):

  def test_off_is_the_vanilla_step(self):
    scene = synthetic_scene()
    cfg = train.resolve(TEST_CFG, scene)
    mesh = sharding.make_mesh(1)
    state = sharding.replicate(train.initial_state(cfg, scene), mesh)
    lanes, _ = sharding.lanes_of(scene, 1, mesh)
    def lowered(c, scorer=None):
      return jax.jit(functools.partial(
          step.train_step, cfg=c, mesh=mesh, vmap_lanes=False)).lower(
              state, lanes, scorer).as_text()
    vanilla = lowered(cfg)
    # Guidance off, whatever its other fields: the same program.
    for sem, pixel in ((guidance_config.SemanticConfig(tau=0.3, beta=0.5),
                        guidance_config.PixelConfig()),
                       (guidance_config.SemanticConfig(evidence="pixel"),
                        guidance_config.PixelConfig(tau_p=0.2,
                                                    loss_masking=True))):
      self.assertEqual(lowered(dataclasses.replace(cfg, semantic=sem,
                                                   pixel=pixel)), vanilla)
    with self.assertRaisesRegex(ValueError, "takes no"):
      lowered(cfg, guidance.OracleScorer(
          masks=jnp.zeros((1, 8, 32, 32), bool), saturation=0.1))

  def _pixel_step(self,
                  map_value,
                  pixel=guidance_config.PixelConfig(),
                  **semantic_fields):
    """One scored step of the pixel-evidence train step with a constant
    map; returns (state before, state after, metrics)."""
    scene = synthetic_scene()
    sem = guidance_config.SemanticConfig(scorer="oracle",
                                         evidence="pixel",
                                         accumulate_start=0,
                                         **semantic_fields)
    cfg = train.resolve(dataclasses.replace(TEST_CFG, semantic=sem,
                                            pixel=pixel), scene)
    state = train.initial_state(cfg, scene)
    maps = jnp.full(scene.train.images.shape[:3], map_value, jnp.float32)
    after, metrics = _one_step(cfg, scene, state,
                               guidance.PixelMapScorer(maps))
    return state, after, metrics

  def test_pixel_step_accumulates_the_map(self):
    _, after, metrics = self._pixel_step(
        0.25, guidance_config.PixelConfig(agreement=False))
    stats = after.semantic
    seen = np.asarray(stats.weight) > 0
    self.assertGreater(seen.sum(), 10)
    # Every pixel is 1/4 transient, so every contributing Gaussian's
    # probability is 1/4, and n counts the one view.
    np.testing.assert_allclose(np.asarray(stats.acc)[seen],
                               0.25 * np.asarray(stats.weight)[seen],
                               rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(stats.n), seen.astype(float))
    self.assertAlmostEqual(float(metrics["map_mean"][0]), 0.25, places=6)

  def test_agreement_weights_the_map(self):
    _, raw, _ = self._pixel_step(0.25,
                                 guidance_config.PixelConfig(agreement=False))
    _, weighted, _ = self._pixel_step(0.25)
    # The second pass renders the same splats: the weight on static pixels,
    # sum w (1 - m), is unchanged; transient weight counts only where the
    # step-0 render reproduces the photo, in numerator and denominator.
    acc_raw, w_raw = (np.asarray(raw.semantic.acc),
                      np.asarray(raw.semantic.weight))
    acc, w = (np.asarray(weighted.semantic.acc),
              np.asarray(weighted.semantic.weight))
    np.testing.assert_allclose(w - acc, w_raw - acc_raw, rtol=1e-5,
                               atol=1e-5)
    np.testing.assert_array_equal(weighted.semantic.n, raw.semantic.n)
    self.assertTrue(np.all(acc <= acc_raw + 1e-6))
    self.assertLess(acc.sum(), acc_raw.sum())
    self.assertGreater(acc.sum(), 0.0)

  def test_loss_masking_ignores_masked_pixels(self):
    # A fully transient map with loss masking: no pixel is fitted, so the
    # colours do not move (the opacity loss touches opacities only).
    before, after, _ = self._pixel_step(
        1.0, guidance_config.PixelConfig(loss_masking=True), reg_start=10_000)
    np.testing.assert_array_equal(np.asarray(after.params.sh_dc),
                                  np.asarray(before.params.sh_dc))
    _, moved, _ = self._pixel_step(1.0, reg_start=10_000)
    self.assertFalse(np.array_equal(np.asarray(moved.params.sh_dc),
                                    np.asarray(before.params.sh_dc)))

  def test_oracle_fit(self):
    step.make_train_step.cache_clear()
    guidance.make_prune.cache_clear()
    scene = _masked_scene()
    sem = guidance_config.SemanticConfig(
        scorer="oracle", accumulate_start=10, reg_start=20, prune_start=40,
        prune_every=20, tau=0.02, oracle_saturation=0.125)
    cfg = train.resolve(dataclasses.replace(TEST_CFG, semantic=sem), scene)
    scorer = guidance.make_scorer(cfg, scene)
    workdir = self.create_tempdir().full_path
    with CompileCounter() as compiles:
      result = train.fit(cfg, scene, workdir, scorer=scorer, progress=False)
    # Every step from 10 on scored its view with the oracle formula:
    # masked views f = 1/16, f / 0.125 = 0.5 -> 0.75; clean views 0.5.
    self.assertEqual([s["step"] for s in result.scores], list(range(10, 120)))
    for s in result.scores:
      self.assertAlmostEqual(s["s_hat_d"], 0.75 if s["view"] % 2 == 0
                             else 0.5, places=6)
      self.assertIsNone(s["s_hat_s"])
    # Prunes after 40, 60, 80, 100 (not after the last step, 120).
    self.assertEqual([e["step"] for e in result.prune_events],
                     [40, 60, 80, 100])
    for e in result.prune_events:
      self.assertEqual(sum(e["histogram"]), e["num_alive_before"])
    self.assertEqual(compiles.count("train_step"), 1, compiles.names)
    self.assertEqual(compiles.count("prune"), 1, compiles.names)
    self.assertGreater(result.curve[-1]["test_psnr"],
                       result.curve[0]["test_psnr"] + 3.0)
    # The logs survive a resume from the final checkpoint.
    again = train.fit(cfg, scene, workdir, scorer=scorer, resume=True,
                      progress=False)
    self.assertEqual(again.scores, result.scores)
    self.assertEqual(again.prune_events, result.prune_events)
    # That the oracle never imports CLIP is test_clip_scorer.py's check, in a
    # fresh interpreter: other test files in this process import it.

  def _fully_cluttered_fit(self, **semantic_fields):
    # Every view cluttered and tau = 0: every scored Gaussian exceeds tau,
    # the situation of a fully cluttered benchmark (BUILD_NOTES.md,
    # "Semantic guidance"),
    # where the paper's rule deleted the whole scene.
    scene = _masked_scene()
    scene = dataclasses.replace(scene, train=dataclasses.replace(
        scene.train, masks=np.ones_like(scene.train.masks)))
    sem = guidance_config.SemanticConfig(
        scorer="oracle", accumulate_start=0, reg_start=0, prune_start=20,
        prune_every=20, tau=0.0, **semantic_fields)
    cfg = dataclasses.replace(TEST_CFG, semantic=sem,
                              train=dataclasses.replace(TEST_CFG.train,
                                                        steps=21))
    return train.fit(train.resolve(cfg, scene), scene,
                     self.create_tempdir().full_path,
                     scorer=guidance.make_scorer(cfg, scene), progress=False)

  def test_guard_refuses_a_prune_that_deletes_the_scene(self):
    with self.assertLogs("clipgs_jax.loop", "WARNING") as logs:
      result = self._fully_cluttered_fit()
    event, = result.prune_events
    self.assertTrue(event["guarded"])
    self.assertEqual(event["num_pruned_semantic"], 0)
    self.assertGreater(event["num_refused"], 0.5 * event["num_alive_before"])
    self.assertEqual(int(result.state.alive.sum()),
                     event["num_alive_before"])
    self.assertIn("REFUSED", "\n".join(logs.output))
    summary = guidance.summarize(result.prune_events,
                                 int(result.state.alive.sum()),
                                 result.state.semantic)
    self.assertEqual(summary["num_refused_prune_events"], 1)
    self.assertEqual(summary["refused_prune_steps"], [20])
    self.assertIsNotNone(result.pruned)
    self.assertEqual(len(result.pruned.means), 0)

  def test_guard_lifted_reproduces_the_paper(self):
    result = self._fully_cluttered_fit(max_prune_fraction=1.0)
    event, = result.prune_events
    self.assertFalse(event["guarded"])
    self.assertGreater(event["num_pruned_semantic"],
                       0.5 * event["num_alive_before"])
    self.assertEqual(len(result.pruned.means), event["num_pruned_semantic"])

  def test_fit_checks_the_scorer(self):
    scene = _masked_scene()
    cfg = dataclasses.replace(TEST_CFG, semantic=ORACLE)
    with self.assertRaisesRegex(ValueError, "needs a"):
      train.fit(cfg, scene, self.create_tempdir().full_path, progress=False)


  def test_a_nan_score_stops_the_run(self):
    # Steps 0 and 1 do not score (their placeholders are never checked);
    # step 2 scores NaN, which the log at step 4 reports with its step.
    sem = dataclasses.replace(ORACLE, accumulate_start=2)
    cfg = dataclasses.replace(TEST_CFG, semantic=sem, train=dataclasses.replace(
        TEST_CFG.train, steps=4, log_every=4, eval_every=0))
    scene = _masked_scene()
    with self.assertRaisesRegex(
        FloatingPointError, r"non-finite s_hat_d at step 2; the 'oracle' "
        r"scorer returned it for training view \d"):
      train.fit(train.resolve(cfg, scene), scene,
                self.create_tempdir().full_path, scorer=_NanScorer(),
                progress=False)


if __name__ == "__main__":
  absltest.main()
