"""Per-Gaussian evidence from a per-pixel map, blended in the same pass."""

import collections
import re

from absl.testing import parameterized
import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config
from clipgs_jax.render import project
from clipgs_jax.render import rasterize
import rasterize_ref
import synthetic

CFG = config.RenderConfig(tile_budget=256, chunk_size=8)
BG = jnp.array([0.1, 0.2, 0.3])
FIELDS = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


def _map(h, w, seed=0):
  return jnp.asarray(np.random.default_rng(seed).uniform(size=(h, w)),
                     jnp.float32)


def _scene(n, seed, degree=1):
  params = synthetic.random_params(n, seed=seed, degree=degree)
  alive = jnp.asarray(np.random.default_rng(seed).uniform(size=n) < 0.9)
  return params, alive


def _op_counts(text):
  """Histogram of StableHLO op names in a lowered program."""
  return collections.Counter(re.findall(r"stablehlo\.(\w+)", text))


class EvidenceForwardTest(parameterized.TestCase):

  @parameterized.named_parameters(
      ("odd_size", (37, 29), 0), ("one_tile", (16, 16), 1),
      ("wide", (48, 20), 2))
  def test_matches_reference(self, size, seed):
    cam = synthetic.front_camera(*size)
    params, alive = _scene(120, seed)
    emap = _map(size[1], size[0], seed)
    render = jax.jit(lambda p, a, m: rasterize.render(
        p, a, cam, BG, CFG, evidence_map=m))
    out = render(params, alive, emap)
    ref = rasterize_ref.render_ref(params, alive, cam, BG, evidence_map=emap)
    self.assertEqual(int(out.num_overflow), 0)
    self.assertGreater(float(jnp.max(ref["evidence"])), 0.1)
    np.testing.assert_allclose(out.evidence, ref["evidence"], rtol=1e-5,
                               atol=1e-5)
    # The map changes nothing else.
    plain = jax.jit(lambda p, a: rasterize.render(p, a, cam, BG, CFG))(
        params, alive)
    self.assertIsNone(plain.evidence)
    # Two programs, compiled apart: XLA may fuse (and round) the shared
    # arithmetic differently, so equal up to float32 rounding. Depth is a
    # ratio sum(w z) / alpha, whose rounding grows where alpha is small: it
    # gets the tolerance it has against the reference (found at 1.0e-5
    # relative on 11 pixels once the blend loops were unrolled;
    # BUILD_NOTES.md, "Rasterizer").
    for field in ("image", "alpha", "contribution"):
      np.testing.assert_allclose(getattr(out, field), getattr(plain, field),
                                 rtol=1e-6, atol=1e-6, err_msg=field)
    np.testing.assert_allclose(out.depth, plain.depth, rtol=1e-5, atol=1e-4)

  def test_constant_maps(self):
    cam = synthetic.front_camera(37, 29)
    params, alive = _scene(60, 4)
    render = jax.jit(lambda m: rasterize.render(params, alive, cam, BG, CFG,
                                                evidence_map=m))
    ones = render(jnp.ones((29, 37)))
    np.testing.assert_allclose(ones.evidence, ones.contribution, rtol=1e-6)
    np.testing.assert_array_equal(render(jnp.zeros((29, 37))).evidence, 0.0)

  def test_autodiff_blend_matches(self):
    cam = synthetic.front_camera(40, 24)
    params, alive = _scene(60, 3)
    emap = _map(24, 40, 3)
    cfg = config.RenderConfig(tile_budget=64, chunk_size=8)
    proj = project.project(params, alive, cam, near=cfg.near, sh_degree=1)
    fast = rasterize.rasterize(proj, cam, BG, cfg, evidence_map=emap)
    auto = rasterize.rasterize(proj, cam, BG, cfg, custom_vjp=False,
                               evidence_map=emap)
    np.testing.assert_allclose(auto.evidence, fast.evidence, rtol=1e-6,
                               atol=1e-7)


class EvidenceGradientTest(parameterized.TestCase):

  def test_gradients_unchanged_and_none_into_map(self):
    cam = synthetic.front_camera(37, 29)
    params, alive = _scene(80, 0)
    rng = np.random.default_rng(1)
    wi = jnp.asarray(rng.normal(size=(29, 37, 3)), jnp.float32)
    wa = jnp.asarray(rng.normal(size=(29, 37)), jnp.float32)
    wd = jnp.asarray(rng.normal(size=(29, 37)), jnp.float32)

    def loss(p, m):
      out = rasterize.render(p, alive, cam, BG, CFG, evidence_map=m)
      value = (jnp.sum(out.image * wi) + jnp.sum(out.alpha * wa)
               + 0.1 * jnp.sum(out.depth * wd))
      # Evidence is an output without a gradient: adding it changes nothing.
      return value + (0.0 if m is None else jnp.sum(out.evidence))

    plain = jax.jit(jax.grad(lambda p: loss(p, None)))(params)
    g_params, g_map = jax.jit(jax.grad(loss, argnums=(0, 1)))(
        params, _map(29, 37))
    for field in FIELDS:
      ref = getattr(plain, field)
      np.testing.assert_allclose(getattr(g_params, field), ref, rtol=1e-6,
                                 atol=1e-6 * float(jnp.max(jnp.abs(ref))),
                                 err_msg=field)
    np.testing.assert_array_equal(g_map, 0.0)


class NoMapProgramTest(parameterized.TestCase):

  def test_no_map_traces_the_plain_program(self):
    cam = synthetic.front_camera(37, 29)
    params, alive = _scene(50, 0)
    plain = jax.jit(lambda p, a: rasterize.render(p, a, cam, BG, CFG)).lower(
        params, alive).as_text()
    explicit = jax.jit(lambda p, a: rasterize.render(
        p, a, cam, BG, CFG, evidence_map=None)).lower(params, alive).as_text()
    with_map = jax.jit(lambda p, a, m: rasterize.render(
        p, a, cam, BG, CFG, evidence_map=m)).lower(
            params, alive, _map(29, 37)).as_text()
    self.assertEqual(explicit, plain)
    extra = _op_counts(with_map) - _op_counts(plain)
    missing = _op_counts(plain) - _op_counts(with_map)
    # The map adds its own accumulation (the weight x map products, their
    # per-entry store and the scatter-add into [C]) and removes nothing; a
    # None path that ran the map code on a stand-in map (e.g. zeros) would
    # show no difference here.
    self.assertEqual(missing, collections.Counter())
    self.assertGreaterEqual(extra["scatter"], 2)
    self.assertGreaterEqual(extra["multiply"], 1)


class EvidenceBadInputTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    self.cam = synthetic.front_camera(37, 29)
    self.params, self.alive = _scene(5, 0)

  def test_wrong_shape(self):
    with self.assertRaisesRegex(ValueError, r"evidence_map must be .*\[29, "
                                r"37\].*resize"):
      rasterize.render(self.params, self.alive, self.cam, BG,
                       evidence_map=jnp.zeros((37, 29)))

  def test_integer_map(self):
    with self.assertRaisesRegex(ValueError, "evidence_map must be floating"):
      rasterize.render(self.params, self.alive, self.cam, BG,
                       evidence_map=jnp.zeros((29, 37), jnp.int32))


class EvidenceProbeTest(parameterized.TestCase):
  """The evidence of a map known only after the render, from the backward
  pass: the probe channel's gradient equals the forward-pass evidence."""

  @parameterized.named_parameters(("custom_vjp", True), ("autodiff", False))
  def test_probe_gradient_is_evidence(self, custom_vjp):
    cam = synthetic.front_camera(37, 29)
    params, alive = _scene(120, 5)
    emap = _map(29, 37, 5)
    proj = project.project(params, alive, cam, near=CFG.near, sh_degree=1)

    def loss(means2d, probe):
      out = rasterize.rasterize(proj.replace(means2d=means2d), cam, BG, CFG,
                                custom_vjp=custom_vjp, probe=probe)
      return jnp.sum(out.image ** 2) + jnp.sum(emap * out.probe_image), out

    probe = jnp.zeros((120,), jnp.float32)
    (value, out), (g_means, g_probe) = jax.jit(jax.value_and_grad(
        loss, argnums=(0, 1), has_aux=True))(proj.means2d, probe)
    np.testing.assert_array_equal(out.probe_image, 0.0)
    forward = rasterize.rasterize(proj, cam, BG, CFG, custom_vjp=custom_vjp,
                                  evidence_map=emap)
    self.assertGreater(float(jnp.max(forward.evidence)), 0.1)
    np.testing.assert_allclose(g_probe, forward.evidence, rtol=1e-5,
                               atol=1e-6)
    # The probe term adds nothing to the loss or to any other gradient (up
    # to float32 rounding: four channels are summed in another order).
    plain = lambda m: jnp.sum(rasterize.rasterize(
        proj.replace(means2d=m), cam, BG, CFG,
        custom_vjp=custom_vjp).image ** 2)
    plain_value, plain_grad = jax.jit(jax.value_and_grad(plain))(proj.means2d)
    np.testing.assert_allclose(value, plain_value, rtol=1e-6)
    np.testing.assert_allclose(g_means, plain_grad, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(out.image, forward.image, rtol=1e-6,
                               atol=1e-6)

  def test_probe_shape_error(self):
    cam = synthetic.front_camera(16, 16)
    params, alive = _scene(20, 0)
    proj = project.project(params, alive, cam, near=CFG.near, sh_degree=1)
    with self.assertRaisesRegex(ValueError, "probe must be float"):
      rasterize.rasterize(proj, cam, BG, CFG, probe=jnp.zeros((3,)))
