"""Tests for densify: row alignment, clone/split/prune, growth, no retrace."""

import dataclasses
import chex
import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest

from clipgs_jax import config
from clipgs_jax import densify
from clipgs_jax import gaussians
from clipgs_jax import optim
from clipgs_jax import sh
from clipgs_jax import state as state_lib
from clipgs_jax import train
from clipgs_jax.render import project

CFG = config.Config(
    gaussians=config.GaussiansConfig(sh_degree=1),
    densify=config.DensifyConfig(opacity_reset_every=1000),
    scene_extent=1.0)
SMALL = np.log(0.005)      # max scale 0.005 <= percent_dense 0.01: clone
LARGE = np.log(0.05)       # > 0.01: split; < max_world_size 0.1: kept


def _first(x):
  """Index of the first element of every row of a [C, ...] array."""
  return (slice(None),) + (0,) * (x.ndim - 1)


def _tag_state(state, tags):
  """Writes tags [C] into sh_dc[:, 0], the first element of every Adam
  moment row and both semantic statistics (0 means 'untagged')."""
  tags = jnp.asarray(tags, jnp.float32)
  params = state.params.replace(sh_dc=state.params.sh_dc.at[:, 0].set(tags))
  opt_state = state_lib.map_rows(state.opt_state, state.capacity,
                                 lambda x: x.at[_first(x)].set(tags))
  return state.replace(
      params=params, opt_state=opt_state,
      semantic=state_lib.SemanticStats(acc=tags, weight=tags + 0.0,
                                       n=tags + 0.0))


def _row_leaves(state):
  """All per-row moment leaves of the state as host arrays."""
  leaves = jax.tree.leaves(jax.device_get(state.opt_state))
  return [x for x in leaves if state_lib.is_row_leaf(x, state.capacity)]


def _make_state(capacity, num_alive, rng):
  params, alive = gaussians.empty(capacity, 1)
  params = params.replace(
      means=jnp.asarray(rng.normal(size=(capacity, 3)), jnp.float32),
      quats=jnp.asarray(rng.normal(size=(capacity, 4)), jnp.float32),
      opacity_logits=jnp.zeros((capacity,), jnp.float32))
  alive = alive.at[:num_alive].set(True)
  state = train.init_state(CFG, params, alive)
  return state.replace(step=jnp.int32(600))


def _drive(state, rng):
  """Random scales, opacities and gradient statistics for one cycle."""
  c = state.capacity
  kind = rng.integers(0, 4, c)   # 0 quiet, 1 clone, 2 split, 3 faint
  log_scales = np.where((kind == 2)[:, None], LARGE, SMALL)
  log_scales = log_scales + rng.uniform(-0.1, 0.1, (c, 3))
  logits = np.where(kind == 3, -8.0, 0.0)            # sigmoid(-8) < 0.005
  grad = np.where((kind == 1) | (kind == 2), 5e-4, 1e-4)
  params = state.params.replace(
      log_scales=jnp.asarray(log_scales, jnp.float32),
      opacity_logits=jnp.asarray(logits, jnp.float32))
  stats = state_lib.DensifyStats(
      grad_accum=jnp.asarray(grad * 2, jnp.float32),
      denom=jnp.full((c,), 2.0, jnp.float32),
      max_radius=jnp.ones((c,), jnp.float32))
  return state.replace(params=params, densify=stats)


class RowAlignmentTest(absltest.TestCase):

  def test_rows_stay_aligned_over_cycles(self):
    rng = np.random.default_rng(0)
    state = _make_state(48, 12, rng)
    tags = np.zeros(48)
    tags[:12] = np.arange(1, 13)
    next_tag = 13
    state = _tag_state(state, tags)
    def densify_fn(state, key):
      return densify.densify(state, key, cfg=CFG)
    # One trace per capacity: the growth at cycle 4 is the only retrace.
    fn = jax.jit(chex.assert_max_traces(densify_fn, n=2))
    totals = dict(num_cloned=0, num_split=0, num_pruned=0, num_unplaced=0)
    for cycle in range(8):
      if cycle == 4:                                   # growth mid-run
        state = state_lib.resize(state, 2 * state.capacity)
      state = _drive(state, rng)
      before = jax.device_get(state)
      before_moments = _row_leaves(state)
      state, info = fn(state, jax.random.key(cycle))
      info = {k: int(v) for k, v in info.items()}
      for k in totals:
        totals[k] += info[k]
      after = jax.device_get(state)
      moments = _row_leaves(state)
      c = after.alive.shape[0]
      self.assertEqual(
          after.alive.sum(), before.alive.sum() + info["num_cloned"]
          + info["num_split"] - info["num_pruned"])
      chex.assert_trees_all_equal(after.densify,
                                  state_lib.DensifyStats.zeros(c))
      tag_of = {int(t): r for r, t in enumerate(before.params.sh_dc[:, 0])
                if before.alive[r]}
      num_new = 0
      for r in range(c):
        row_moments = [m[r] for m in moments]
        if not after.alive[r]:
          self.assertTrue(all(np.all(m == 0) for m in row_moments))
          self.assertEqual(after.semantic.acc[r], 0)
          continue
        tag = after.params.sh_dc[r, 0]
        self.assertIn(int(tag), tag_of, "an alive row lost its identity")
        if row_moments[0].flat[0] != 0:          # untouched row
          self.assertTrue(before.alive[r])
          for m, m0 in zip(row_moments, before_moments):
            np.testing.assert_array_equal(m, m0[r])
            self.assertEqual(m.flat[0], tag)
          self.assertEqual(after.semantic.acc[r], tag)
          self.assertEqual(after.semantic.n[r], tag)
          self.assertEqual(after.semantic.weight[r], tag)
          chex.assert_trees_all_equal(
              jax.tree.map(lambda x: x[r], after.params),
              jax.tree.map(lambda x: x[r], before.params))
        else:                                     # a clone or split child
          num_new += 1
          self.assertTrue(all(np.all(m == 0) for m in row_moments))
          self.assertEqual(after.semantic.acc[r], 0)
          self.assertEqual(after.semantic.weight[r], 0)
          self.assertEqual(after.semantic.n[r], 0)
          parent = tag_of[int(tag)]
          self.assertTrue(r == parent or not before.alive[r])
          p0 = jax.tree.map(lambda x: x[parent], before.params)
          p1 = jax.tree.map(lambda x: x[r], after.params)
          for field in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
            np.testing.assert_array_equal(getattr(p1, field),
                                          getattr(p0, field))
          if np.max(p0.log_scales) <= np.log(0.01):   # clone: exact copy
            np.testing.assert_array_equal(p1.means, p0.means)
            np.testing.assert_array_equal(p1.log_scales, p0.log_scales)
          else:                                      # split child
            np.testing.assert_allclose(p1.log_scales,
                                       p0.log_scales - np.log(1.6),
                                       rtol=1e-6)
            offset = np.abs(p1.means - p0.means)
            self.assertTrue(
                0 < offset.max() < 6 * np.exp(p0.log_scales).max())
      self.assertEqual(num_new, info["num_cloned"] + 2 * info["num_split"])
      # Give new rows fresh tags so the next cycle can tell them apart.
      tags = np.where(after.alive, np.asarray(after.params.sh_dc[:, 0]), 0.0)
      new_rows = after.alive & (moments[0][_first(moments[0])] == 0)
      tags[new_rows] = np.arange(next_tag, next_tag + new_rows.sum())
      next_tag += int(new_rows.sum())
      state = _tag_state(state, tags)
    # Every mechanism was exercised, including running out of slots.
    for k, v in totals.items():
      self.assertGreater(v, 0, k)


class DensifyTest(absltest.TestCase):

  def test_full_capacity_serves_largest_gradients(self):
    rng = np.random.default_rng(1)
    state = _make_state(10, 7, rng)          # 3 free slots
    grad = np.array([3, 9, 5, 8, 1, 7, 6, 0, 0, 0], np.float32) * 1e-4
    state = state.replace(
        params=state.params.replace(
            log_scales=jnp.full((10, 3), SMALL, jnp.float32)),
        densify=state_lib.DensifyStats(
            grad_accum=jnp.asarray(grad), denom=jnp.ones((10,)),
            max_radius=jnp.zeros((10,))))
    requests, free = densify.count_requests(state, cfg=CFG)
    self.assertEqual((int(requests), int(free)), (6, 3))   # >= 2e-4: 6 rows
    new, info = densify.densify(state, jax.random.key(0), cfg=CFG)
    self.assertEqual(int(info["num_cloned"]), 3)
    self.assertEqual(int(info["num_unplaced"]), 3)
    # Rows 1, 3, 5 (gradients 9, 8, 7) are copied into slots 7, 8, 9.
    np.testing.assert_array_equal(new.params.means[7:],
                                  state.params.means[np.array([1, 3, 5])])
    self.assertTrue(np.all(new.alive))

  def test_prune_rules(self):
    rng = np.random.default_rng(2)
    state = _make_state(6, 6, rng)
    log_scales = np.full((6, 3), SMALL, np.float32)
    log_scales[1] = np.log(0.2)                 # > 0.1 x extent: too big
    logits = np.zeros(6, np.float32)
    logits[0] = -6.0                             # opacity 0.0025 < 0.005
    radius = np.array([0, 0, 25.0, 0, 0, 0], np.float32)  # > 20 pixels
    state = state.replace(
        params=state.params.replace(log_scales=jnp.asarray(log_scales),
                                    opacity_logits=jnp.asarray(logits)),
        densify=state_lib.DensifyStats(jnp.zeros(6), jnp.zeros(6),
                                       jnp.asarray(radius)))
    early, info = densify.densify(state.replace(step=jnp.int32(900)),
                                  jax.random.key(0), cfg=CFG)
    np.testing.assert_array_equal(early.alive, [0, 1, 1, 1, 1, 1])
    self.assertEqual(int(info["num_pruned"]), 1)
    late, _ = densify.densify(state.replace(step=jnp.int32(1100)),
                              jax.random.key(0), cfg=CFG)
    np.testing.assert_array_equal(late.alive, [0, 0, 0, 1, 1, 1])

  def test_reset_opacity(self):
    state = _make_state(4, 4, np.random.default_rng(4))
    logits = jnp.array([-8.0, -3.0, 0.0, 4.0])
    state = _tag_state(state.replace(
        params=state.params.replace(opacity_logits=logits)), np.ones(4))
    new = densify.reset_opacity(state, cfg=CFG)
    opac = jax.nn.sigmoid(new.params.opacity_logits)
    np.testing.assert_allclose(opac, [jax.nn.sigmoid(-8.0), 0.01, 0.01, 0.01],
                               rtol=1e-5)
    mu, nu = optim.moments(new.opt_state, "opacity_logits")
    self.assertTrue(np.all(mu == 0) and np.all(nu == 0))
    np.testing.assert_array_equal(
        optim.moments(new.opt_state, "means")[0][:, 0], 1.0)


class StatisticsTest(absltest.TestCase):

  def test_accumulate_in_ndc_units(self):
    stats = state_lib.DensifyStats.zeros(3)
    g = jnp.array([[3e-6, 0.0], [0.0, 1e-6], [5.0, 5.0]])
    seen = jnp.array([True, True, False])
    stats = densify.accumulate(stats, g, seen, jnp.array([4.0, 2.0, 9.0]),
                               width=100, height=40)
    # d/d ndc = d/d pixel * size / 2: 3e-6 * 50 = 1.5e-4, 1e-6 * 20 = 2e-5.
    np.testing.assert_allclose(stats.grad_accum, [1.5e-4, 2e-5, 0],
                               rtol=1e-6)
    np.testing.assert_array_equal(stats.denom, [1, 1, 0])
    np.testing.assert_array_equal(stats.max_radius, [4, 2, 0])
    stats = densify.accumulate(stats, g, seen, jnp.array([1.0, 3.0, 9.0]),
                               width=100, height=40)
    np.testing.assert_array_equal(stats.denom, [2, 2, 0])
    np.testing.assert_array_equal(stats.max_radius, [4, 3, 0])

  def test_screen_radius_is_three_sigma(self):
    # Covariance [[9, 2], [2, 4]] has eigenvalues 6.5 +- sqrt(2.5^2 + 4):
    # the largest is 9.7016, so the radius is 3 sqrt(9.7016) = 9.3442.
    cov = np.array([[9.0, 2.0], [2.0, 4.0]])
    inv = np.linalg.inv(cov)
    proj = project.Projected(
        means2d=jnp.zeros((2, 2)),
        conics=jnp.array([[inv[0, 0], inv[0, 1], inv[1, 1]]] * 2),
        depths=jnp.ones(2), colors=jnp.zeros((2, 3)), opacities=jnp.ones(2),
        extents=jnp.ones((2, 2)), valid=jnp.array([True, False]))
    np.testing.assert_allclose(densify.screen_radius(proj), [9.3442, 0],
                               rtol=1e-4)

  def test_on_screen(self):
    proj = project.Projected(
        means2d=jnp.array([[-5.0, 10], [-5.0, 10], [50, 50], [10, 10]]),
        conics=jnp.zeros((4, 3)), depths=jnp.ones(4),
        colors=jnp.zeros((4, 3)), opacities=jnp.ones(4),
        extents=jnp.array([[6.0, 6], [4, 4], [3, 3], [3, 3]]),
        valid=jnp.array([True, True, True, False]))
    np.testing.assert_array_equal(densify.on_screen(proj, 48, 32),
                                  [True, False, False, False])


class ScheduleTest(absltest.TestCase):

  def test_due(self):
    cfg = dataclasses.replace(CFG, train=config.TrainConfig(steps=7000))
    self.assertEqual(densify.due(500, cfg), (False, False))   # > start only
    self.assertEqual(densify.due(600, cfg), (True, False))
    self.assertEqual(densify.due(650, cfg), (False, False))
    self.assertEqual(densify.due(1000, cfg), (True, True))
    short = dataclasses.replace(cfg, train=config.TrainConfig(steps=1000))
    self.assertEqual(densify.due(1000, short), (False, False))  # last step
    late = dataclasses.replace(cfg, train=config.TrainConfig(steps=30000))
    self.assertEqual(densify.due(15000, late), (False, False))  # >= stop
    self.assertEqual(densify.due(14900, late), (True, False))

  def test_sh_degree(self):
    got = [int(sh.active_degree(s, CFG.densify.sh_degree_every,
                                CFG.gaussians.sh_degree))
           for s in (0, 999, 1000, 2500, 9000)]
    self.assertEqual(got, [0, 0, 1, 1, 1])     # capped at sh_degree 1


if __name__ == "__main__":
  absltest.main()
