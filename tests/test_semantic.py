"""Semantic guidance equations on hand-computed examples."""

from absl.testing import parameterized
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import semantic
from clipgs_jax import state as state_lib


def _stats(acc, n, weight=None):
  """Statistics; weight defaults to n (visibility weighting)."""
  n = jnp.asarray(n, jnp.float32)
  return state_lib.SemanticStats(
      acc=jnp.asarray(acc, jnp.float32),
      weight=n if weight is None else jnp.asarray(weight, jnp.float32), n=n)


class ScoreTest(parameterized.TestCase):

  def test_view_score(self):
    image = jnp.array([1.0, 0.0, 0.0])
    prompts = jnp.array([[0.6, 0.8, 0.0], [-1.0, 0.0, 0.0], [0.2, 0.0, 0.98]])
    # cosines 0.6, -1.0, 0.2 -> max 0.6 -> (0.6 + 1) / 2 = 0.8
    self.assertAlmostEqual(
        float(semantic.normalized_max_cosine(image, prompts)), 0.8, places=6)
    # Opposite vectors: cos = -1 -> 0.
    self.assertAlmostEqual(float(semantic.normalized_max_cosine(
        image, -image[None])), 0.0, places=6)

  def test_view_score_needs_prompts(self):
    with self.assertRaisesRegex(ValueError, "at least one prompt"):
      semantic.normalized_max_cosine(jnp.ones(3), jnp.zeros((0, 3)))


class AccumulateTest(parameterized.TestCase):

  def test_hand_computed(self):
    stats = _stats([0.0, 0.01, 0.0], [0.0, 2.0, 5.0])
    visible = jnp.array([True, True, False])
    out = semantic.accumulate(stats, visible, jnp.float32(0.7), beta=0.1)
    # gain = 0.1 * (0.7 - 0.5) = 0.02 for visible rows only.
    np.testing.assert_allclose(out.acc, [0.02, 0.03, 0.0], rtol=1e-6)
    np.testing.assert_allclose(out.n, [1.0, 3.0, 5.0])
    np.testing.assert_allclose(out.weight, out.n)

  def test_contribution_weighted(self):
    stats = _stats([0.0, 0.01, 0.0], [0.0, 1.0, 4.0],
                   weight=[0.0, 2.0, 7.0])
    visible = jnp.array([True, True, False])
    weight = jnp.array([30.0, 0.5, 0.0])   # blending-weight sums in the view
    out = semantic.accumulate(stats, visible, jnp.float32(0.7), beta=0.1,
                              weight=weight)
    # gain 0.02: acc = [0 + 30 * 0.02, 0.01 + 0.5 * 0.02, 0] = [0.6, 0.02,
    # 0]; weight = [30, 2.5, 7]; s_j = acc / weight = [0.02, 0.008, 0]; n
    # still counts views: [1, 2, 4].
    np.testing.assert_allclose(out.acc, [0.6, 0.02, 0.0], rtol=1e-6)
    np.testing.assert_allclose(out.weight, [30.0, 2.5, 7.0])
    np.testing.assert_allclose(out.n, [1.0, 2.0, 4.0])
    np.testing.assert_allclose(semantic.normalized_scores(out),
                               [0.02, 0.008, 0.0], rtol=1e-6)

  @parameterized.named_parameters(("zero", 0.0, 0.0), ("neutral", 0.5, 0.0),
                                  ("one", 1.0, 0.05))
  def test_extreme_scores(self, score, gain):
    out = semantic.accumulate(_stats([0.0], [0.0]), jnp.array([True]),
                              jnp.float32(score), beta=0.1)
    # Below 0.5 adds nothing but still counts the view.
    np.testing.assert_allclose(out.acc, [gain], rtol=1e-6)
    np.testing.assert_allclose(out.n, [1.0])

  @parameterized.named_parameters(("nan", np.nan), ("above_one", 1.5),
                                  ("negative", -0.1))
  def test_bad_score_rejected(self, score):
    with self.assertRaisesRegex(ValueError, "s_hat_d must be"):
      semantic.accumulate(_stats([0.0], [0.0]), jnp.array([True]),
                          jnp.float32(score), beta=0.1)

  def test_nan_under_jit_leaves_stats(self):
    f = jax.jit(lambda s: semantic.accumulate(
        _stats([0.1], [2.0]), jnp.array([True]), s, beta=0.1))
    out = f(jnp.float32(np.nan))
    np.testing.assert_allclose(out.acc, [0.1])
    np.testing.assert_allclose(out.weight, [2.0])
    np.testing.assert_allclose(out.n, [2.0])


class NormalizeLossPruneTest(parameterized.TestCase):

  def test_n_zero_guard(self):
    s = semantic.normalized_scores(_stats([0.0, 0.03, 0.5], [0.0, 2.0, 0.0]))
    # acc / n = 0.015 where n > 0; 0 where n = 0 (no NaN from 0 / 0).
    np.testing.assert_allclose(s, [0.0, 0.015, 0.0], rtol=1e-6)

  def test_opacity_loss(self):
    stats = _stats([0.02, 0.04, 1.0], [1.0, 2.0, 1.0])
    logits = jnp.array([0.0, 0.0, 0.0])            # alpha = 0.5 each
    alive = jnp.array([True, True, False])
    loss = semantic.opacity_loss(stats, logits, alive, weight=0.01)
    # s = [0.02, 0.02, dead]; mean over alive of s * 0.5 = 0.01; * 0.01.
    self.assertAlmostEqual(float(loss), 1e-4, places=9)
    # Gradient flows to opacities only, through alpha' = 0.25.
    g = jax.grad(lambda l: semantic.opacity_loss(stats, l, alive, 0.01))(
        logits)
    np.testing.assert_allclose(g, [0.01 * 0.02 * 0.25 / 2] * 2 + [0.0],
                               rtol=1e-5)

  def test_prune_hand_computed(self):
    stats = _stats([0.04, 0.0, 0.0, 0.04, 0.0], [2.0, 3.0, 20.0, 2.0, 3.0])
    alpha = jnp.array([0.9, 0.05, 0.05, 0.9, 0.5])
    logits = jnp.log(alpha / (1 - alpha))
    alive = jnp.array([True, True, True, False, True])
    sem, vis = semantic.prune_masks(stats, logits, alive, tau=0.015,
                                    n_min=10, alpha_min=0.1)
    # row 0: s = 0.02 > tau; row 1: few views and faint; row 2: faint but
    # seen 20 times; row 3: dead; row 4: few views but opaque.
    np.testing.assert_array_equal(sem, [True, False, False, False, False])
    np.testing.assert_array_equal(vis, [False, True, False, False, False])

  @parameterized.named_parameters(("tau_zero", 0.0, [True, True, False]),
                                  ("tau_one", 1.0, [False, False, False]))
  def test_tau_limits(self, tau, expected):
    stats = _stats([1e-6, 0.5, 0.0], [1.0, 1.0, 1.0])
    sem, _ = semantic.prune_masks(stats, jnp.zeros(3), jnp.ones(3, bool),
                                  tau=tau, n_min=0, alpha_min=0.0)
    np.testing.assert_array_equal(sem, expected)

  def test_oracle_score(self):
    mask = jnp.zeros((10, 10), bool)
    self.assertEqual(float(semantic.oracle_score(mask, 0.1)), 0.5)
    # 5 % transient with saturation 10 % -> 0.5 + 0.5 * 0.5 = 0.75.
    self.assertAlmostEqual(float(semantic.oracle_score(
        mask.at[:5, 0].set(True), 0.1)), 0.75, places=6)
    self.assertEqual(float(semantic.oracle_score(mask.at[:].set(True), 0.1)),
                     1.0)
    with self.assertRaisesRegex(ValueError, "saturation"):
      semantic.oracle_score(mask, 0.0)

  def test_prune_counts_views_not_weight(self):
    # Contribution weighting: a faint row with a large pixel-weight sum but
    # few views is still "rarely seen" (n counts views, not weight).
    stats = _stats([0.0, 0.0], [3.0, 30.0], weight=[500.0, 0.2])
    logits = jnp.full((2,), -3.0)                        # alpha ~ 0.05
    _, vis = semantic.prune_masks(stats, logits, jnp.ones(2, bool),
                                  tau=0.015, n_min=10, alpha_min=0.1)
    np.testing.assert_array_equal(vis, [True, False])

  def test_rare_clause_can_need_evidence(self):
    # Three faint, rarely seen rows: no evidence, a little, unseen. The
    # paper's clause prunes all three; under rare_needs_evidence only the
    # row with some light on transient pixels (s_j > 0) goes.
    stats = _stats([0.0, 0.1, 0.0], [3.0, 3.0, 0.0], weight=[4.0, 4.0, 0.0])
    logits = jnp.full((3,), -3.0)                        # alpha ~ 0.05
    kwargs = dict(tau=0.5, n_min=10, alpha_min=0.1)
    _, vis = semantic.prune_masks(stats, logits, jnp.ones(3, bool), **kwargs)
    np.testing.assert_array_equal(vis, [True, True, True])
    _, vis = semantic.prune_masks(stats, logits, jnp.ones(3, bool),
                                  rare_needs_evidence=True, **kwargs)
    np.testing.assert_array_equal(vis, [False, True, False])

  def test_pixel_evidence_is_a_probability(self):
    stats = state_lib.SemanticStats.zeros(3)
    # Row 0 lies fully on transient pixels, row 1 half, row 2 unseen.
    evidence = jnp.array([2.0, 0.5, 0.0])
    contribution = jnp.array([2.0, 1.0, 0.0])
    visible = contribution > 0
    for _ in range(2):
      stats = semantic.accumulate_pixel(stats, evidence, contribution,
                                        visible, jnp.bool_(True))
    # A step that does not score leaves everything unchanged.
    stats = semantic.accumulate_pixel(stats, evidence, contribution, visible,
                                      jnp.bool_(False))
    np.testing.assert_allclose(semantic.normalized_scores(stats),
                               [1.0, 0.5, 0.0])
    np.testing.assert_allclose(stats.weight, [4.0, 2.0, 0.0])
    np.testing.assert_allclose(stats.n, [2.0, 2.0, 0.0])

  def test_agreement(self):
    photo = jnp.zeros((1, 4, 3))
    render = photo.at[0, 1].set(0.05).at[0, 2].set(0.1).at[0, 3].set(0.5)
    # Mean colour error 0, 0.05, 0.1, 0.5 against tolerance 0.1.
    np.testing.assert_allclose(semantic.agreement(render, photo),
                               [[1.0, 0.5, 0.0, 0.0]], atol=1e-6)

  def test_min_weight_keeps_thin_evidence(self):
    # s = 1 on both rows, but row 1 has under one pixel of evidence.
    stats = _stats([3.0, 0.4], [3.0, 1.0], weight=[3.0, 0.4])
    sem, _ = semantic.prune_masks(
        stats, jnp.zeros(2), jnp.ones(2, bool), tau=0.5, n_min=0,
        alpha_min=0.0, min_weight=semantic.MIN_EVIDENCE_WEIGHT)
    np.testing.assert_array_equal(sem, [True, False])

  @parameterized.named_parameters(
      ("half_refused", 0.5, [True] * 3 + [False] * 3, True),
      ("half_allowed", 0.5, [True] * 2 + [False] * 4, False),
      ("lifted", 1.0, [True] * 6, False))
  def test_guard_prune(self, max_fraction, wanted, guarded):
    alive = jnp.ones(6, bool).at[5].set(False)       # 5 alive rows
    sem = jnp.asarray(wanted) & alive
    vis = jnp.zeros(6, bool)
    # 3 of 5 > 0.5 is refused; 2 of 5 passes; 1.0 never refuses.
    out_sem, out_vis, out_guarded = semantic.guard_prune(
        sem, vis, alive, max_fraction)
    self.assertEqual(bool(out_guarded), guarded)
    np.testing.assert_array_equal(out_sem, sem & (not guarded))
    self.assertFalse(bool(out_vis.any()))

  def test_three_float32_per_slot(self):
    self.assertEqual(semantic.state_bytes(state_lib.SemanticStats.zeros(1000)),
                     12000)
