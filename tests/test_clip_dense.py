"""Dense (per-patch) CLIP readouts and the per-pixel scorer, against torch."""

import dataclasses
import time

from absl.testing import absltest
from absl.testing import parameterized
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clip_testutil
from clipgs_jax import guidance_config
from clipgs_jax.clip import dense
from clipgs_jax.clip import model
from clipgs_jax.clip import preprocess
from clipgs_jax.clip import scorer
from clipgs_jax.clip import tokenizer
from clipgs_jax.clip import weights

torch = pytest.importorskip(
    'torch', reason='the dense parity tests need torch (pip install .[test])')
transformers = pytest.importorskip(
    'transformers', reason='the dense parity tests need transformers')

TOLERANCE = 1e-4  # max abs difference allowed in float32
TINY = model.VARIANTS['tiny']
SEM = guidance_config.SemanticConfig(scorer='clip')  # the paper's 5 + 3 prompts
RENDER_HW = (40, 56)  # not square, so a transposed map would show


def hf_config(c):
  """transformers.CLIPConfig with the shapes of our ClipConfig c."""
  return transformers.CLIPConfig(
      text_config=dict(
          hidden_size=c.text_width,
          intermediate_size=c.mlp_ratio * c.text_width,
          num_hidden_layers=c.text_layers, num_attention_heads=c.text_heads,
          max_position_embeddings=c.context_length, vocab_size=c.vocab_size,
          hidden_act='quick_gelu', projection_dim=c.embed_dim,
          # Pools at the first end token, where OpenAI's argmax lands.
          bos_token_id=tokenizer.START_OF_TEXT,
          eos_token_id=tokenizer.END_OF_TEXT),
      vision_config=dict(
          hidden_size=c.vision_width,
          intermediate_size=c.mlp_ratio * c.vision_width,
          num_hidden_layers=c.vision_layers,
          num_attention_heads=c.vision_heads, image_size=c.image_size,
          patch_size=c.patch_size, hidden_act='quick_gelu',
          projection_dim=c.embed_dim),
      projection_dim=c.embed_dim)


def torch_patch_features(hf, pixels, readout):
  """The readouts, written from transformers' CLIPModel modules.

  Args:
    hf: transformers.CLIPModel.
    pixels: float32 [B, S, S, 3] numpy, CLIP-normalised.
    readout: 'maskclip' or 'clearclip'.

  Returns:
    float32 [B, g*g, E] numpy, unit-norm patch embeddings, row-major.
  """
  vm = hf.vision_model
  with torch.no_grad():
    pv = torch.from_numpy(np.array(pixels.transpose(0, 3, 1, 2)))
    # transformers' own position interpolation (bicubic, torch).
    x = vm.pre_layrnorm(vm.embeddings(pv, interpolate_pos_encoding=True))
    *body, last = vm.encoder.layers
    for layer in body:
      x = layer(x, attention_mask=None)
    attn = last.self_attn
    h = last.layer_norm1(x)
    b, l, w = h.shape
    split = lambda t: t.view(b, l, attn.num_heads, -1).transpose(1, 2)
    v = split(attn.v_proj(h))  # [B, heads, L, D]
    if readout == 'maskclip':
      # q.k attention dropped: each token keeps its own value; the residual
      # and the MLP of the block stay.
      x = x + attn.out_proj(v.transpose(1, 2).reshape(b, l, w))
      x = x + last.mlp(last.layer_norm2(x))
    else:
      # Query-query attention, then out_proj; no residual, no MLP.
      q = split(attn.q_proj(h))
      weights_qq = torch.softmax(q @ q.transpose(-1, -2) * attn.scale, -1)
      x = attn.out_proj((weights_qq @ v).transpose(1, 2).reshape(b, l, w))
    f = hf.visual_projection(vm.post_layernorm(x[:, 1:]))
    return torch.nn.functional.normalize(f, dim=-1).numpy()


def torch_score_map(hf, pixels, readout, prompts, num_distractor, hw):
  """Per-pixel p(distractor), float32 [H, W] numpy, for pixels [1, S, S, 3]."""
  f = torch.from_numpy(torch_patch_features(hf, pixels, readout)[0])
  with torch.no_grad():
    t = hf.get_text_features(input_ids=torch.from_numpy(
        tokenizer.tokenize(prompts).astype(np.int64)))
    t = torch.nn.functional.normalize(getattr(t, 'pooler_output', t), dim=-1)
    p = torch.softmax(hf.logit_scale.exp() * f @ t.T, dim=-1)
    p = p[:, :num_distractor].sum(-1)  # [g*g]
    g = int(round(p.shape[0] ** 0.5))
    up = torch.nn.functional.interpolate(
        p.reshape(1, 1, g, g), size=hw, mode='bilinear', align_corners=False)
  return up[0, 0].numpy()


def ours_from_hf(hf, variant):
  tensors = {n: t.detach().numpy() for n, t in hf.state_dict().items()}
  return weights.params_from_tensors(tensors, variant)


def random_render(seed=0, hw=RENDER_HW):
  rng = np.random.default_rng(seed)
  return rng.uniform(size=hw + (3,)).astype(np.float32)


class InterpolationTest(parameterized.TestCase):

  @parameterized.parameters((7, 14), (4, 6), (7, 10), (7, 5), (3, 3))
  def test_matrix_matches_torch_bicubic(self, n_in, n_out):
    grid = np.random.default_rng(0).normal(size=(1, 5, n_in, n_in))
    expected = torch.nn.functional.interpolate(
        torch.from_numpy(grid), size=(n_out, n_out), mode='bicubic',
        align_corners=False).numpy()
    m = dense.interpolation_matrix(n_in, n_out)
    got = np.einsum('ai,bj,nwij->nwab', m, m, grid)
    np.testing.assert_allclose(got, expected, atol=1e-12, rtol=0)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=1e-12)

  def test_identity_at_training_grid(self):
    np.testing.assert_array_equal(dense.interpolation_matrix(7, 7), np.eye(7))
    pos = jnp.arange(50 * 3, dtype=jnp.float32).reshape(50, 3)
    self.assertIs(dense.resize_positions(pos, 7), pos)

  def test_class_row_kept(self):
    pos = jax.random.normal(jax.random.key(0), (17, 8))  # 4 x 4 grid + class
    out = dense.resize_positions(pos, 6)
    chex.assert_shape(out, (37, 8))
    np.testing.assert_array_equal(out[0], pos[0])

  def test_not_square(self):
    with self.assertRaisesRegex(ValueError, 'square grid'):
      dense.resize_positions(jnp.zeros((11, 4)), 4)


class ReadoutTest(parameterized.TestCase):

  def test_maskclip_reads_every_visual_parameter(self):
    # The readouts apply to the checkpoint's own 'visual' tree; MaskCLIP
    # uses all of it, ClearCLIP all but the last block's ln_2 and MLP.
    shapes = model.param_shapes(TINY)['visual']
    images = jnp.zeros((1, 48, 48, 3))
    for readout in dense.READOUTS:
      got = jax.eval_shape(dense.DenseVisionTransformer(TINY, readout).init,
                           jax.random.key(0), images)['params']
      expected = jax.tree.map(lambda x: x.shape, shapes)
      if readout == 'clearclip':
        last = expected['transformer'][f'resblocks_{TINY.vision_layers - 1}']
        del last['ln_2'], last['mlp']
      self.assertEqual(jax.tree.map(lambda x: x.shape, got), expected)

  def test_distractor_probability(self):
    rng = np.random.default_rng(0)
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)
    f, d, s = (unit(rng.normal(size=n)).astype(np.float32)
               for n in ((3, 4, 8), (5, 8), (2, 8)))
    for scale in (1.0, 100.0):
      logits = scale * f.astype(np.float64) @ np.concatenate([d, s]).T
      e = np.exp(logits - logits.max(-1, keepdims=True))
      expected = e[..., :5].sum(-1) / e.sum(-1)
      got = dense.distractor_probability(f, d, s, jnp.float32(scale))
      # float32 cosines carry ~1e-7 error; x100 in the logits, and
      # dp = p (1 - p) dlogit <= 2.5e-6.
      np.testing.assert_allclose(got, expected, atol=1e-5, rtol=0)
    # A patch equal to a distractor prompt at CLIP's scale: p -> 1, finite.
    p = dense.distractor_probability(d[:1], d, s, jnp.float32(100.0))
    self.assertGreater(float(p[0]), 0.5)

  def test_upsample_keeps_orientation(self):
    probs = jnp.zeros((4, 4)).at[0, 3].set(1.0)  # top-right patch
    up = dense.upsample(probs, 40, 56)
    chex.assert_shape(up, (40, 56))
    self.assertEqual(np.unravel_index(int(jnp.argmax(up)), up.shape)[0], 0)
    self.assertGreater(int(jnp.argmax(up[0])), 40)
    np.testing.assert_allclose(dense.upsample(jnp.full((4, 4), 0.3), 9, 13),
                               0.3, atol=1e-7)


class TinyParityTest(parameterized.TestCase):
  """Tiny config: our readouts vs the torch reference on random weights."""

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    cls.hf = clip_testutil.random_hf_model(hf_config(TINY), seed=1)
    cls.config, cls.params = ours_from_hf(cls.hf, 'tiny')
    cls.image = random_render()

  @parameterized.parameters(('maskclip', 32), ('maskclip', 48),
                            ('clearclip', 48), ('clearclip', 64))
  def test_score_map(self, readout, input_size):
    s = scorer.make_dense(SEM, clip_params=(self.config, self.params),
                          input_size=input_size, readout=readout)
    pixels = np.asarray(preprocess.preprocess(self.image[None],
                                              size=input_size))
    grid = input_size // TINY.patch_size
    features = dense.encode_dense(self.params, jnp.asarray(pixels),
                                  config=self.config, readout=readout)
    chex.assert_shape(features, (1, grid, grid, TINY.embed_dim))
    np.testing.assert_allclose(
        features.reshape(1, grid * grid, -1),
        torch_patch_features(self.hf, pixels, readout), atol=TOLERANCE,
        rtol=0)
    got = jax.jit(s.score_map)(jnp.asarray(self.image), jnp.int32(0))
    prompts = SEM.distractor_prompts + SEM.static_prompts
    expected = torch_score_map(self.hf, pixels, readout, prompts,
                               len(SEM.distractor_prompts), RENDER_HW)
    chex.assert_shape(got, RENDER_HW)
    self.assertEqual(got.dtype, jnp.float32)
    np.testing.assert_allclose(got, expected, atol=TOLERANCE, rtol=0)
    # Random weights still give a map that varies over the image.
    self.assertGreater(float(np.ptp(expected)), 1e-3)


class ScorerTest(parameterized.TestCase):

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    cls.clip_params = (TINY, model.init_params(TINY, jax.random.key(0)))

  def test_in_cond_range_and_no_gradient(self):
    s = scorer.make_dense(SEM, clip_params=self.clip_params, input_size=48)
    self.assertEqual(s.grid, 6)

    @jax.jit
    def f(sc, image, on):
      return jax.lax.cond(on, lambda: sc.score_map(image, jnp.int32(3)),
                          lambda: jnp.zeros(image.shape[:2], jnp.float32))

    image = jnp.asarray(random_render(1))
    m = f(s, image, jnp.bool_(True))
    chex.assert_shape(m, RENDER_HW)
    chex.assert_tree_all_finite(m)
    self.assertGreaterEqual(float(m.min()), 0.0)
    self.assertLessEqual(float(m.max()), 1.0)
    np.testing.assert_array_equal(f(s, image, jnp.bool_(False)), 0.0)
    grad = jax.grad(lambda im: s.score_map(im, jnp.int32(0)).sum())(image)
    np.testing.assert_array_equal(grad, 0.0)

  def test_logit_scale_is_exp_of_stored(self):
    s = scorer.make_dense(SEM, clip_params=self.clip_params, input_size=32)
    self.assertAlmostEqual(float(s.logit_scale), 1 / 0.07, places=4)
    self.assertEqual(s.readout, dense.DEFAULT_READOUT)
    self.assertEqual(scorer.DENSE_INPUT_SIZE, 448)

  @parameterized.named_parameters(
      ('no_static', dict(static_prompts=()), 'static_prompts'),
      ('no_distractor', dict(distractor_prompts=()), 'distractor_prompts'))
  def test_degenerate_prompts_rejected(self, change, message):
    sem = dataclasses.replace(SEM, **change)
    with self.assertRaisesRegex(ValueError, message):
      scorer.make_dense(sem, clip_params=self.clip_params, input_size=32)

  def test_bad_arguments(self):
    with self.assertRaisesRegex(ValueError, 'multiple of the patch size 8'):
      scorer.make_dense(SEM, clip_params=self.clip_params, input_size=50)
    with self.assertRaisesRegex(ValueError, 'Unknown dense readout'):
      scorer.make_dense(SEM, clip_params=self.clip_params, readout='sclip')

  def test_image_level_scorer_unchanged(self):
    s = scorer.make(SEM, clip_params=self.clip_params)
    out = s.score(jnp.asarray(random_render(2)), jnp.int32(0))
    self.assertEqual(set(out), {'s_hat_d', 's_hat_s'})


class ViTB32ParityTest(parameterized.TestCase):
  """Real ViT-B/32 shapes at the default 448 input (14 x 14 grid)."""

  def test_default_readout_at_448(self):
    start = time.perf_counter()
    b32 = model.VARIANTS['ViT-B/32']
    hf = clip_testutil.random_hf_model(hf_config(b32), seed=0)
    config, params = ours_from_hf(hf, 'ViT-B/32')
    s = scorer.make_dense(SEM, clip_params=(config, params))
    self.assertEqual(s.grid, 14)
    image = random_render(3, (60, 80))
    pixels = np.asarray(preprocess.preprocess(image[None], size=448))
    got = s.score_map(jnp.asarray(image), jnp.int32(0))
    # Random B/32 maps are nearly flat (range ~3e-3), so the features are
    # compared too (same compiled encoder as inside score_map).
    features = dense.encode_dense(params, jnp.asarray(pixels), config=config,
                                  readout=s.readout)
    np.testing.assert_allclose(
        features.reshape(1, 14 * 14, -1),
        torch_patch_features(hf, pixels, s.readout), atol=TOLERANCE, rtol=0)
    expected = torch_score_map(
        hf, pixels, s.readout, SEM.distractor_prompts + SEM.static_prompts,
        len(SEM.distractor_prompts), (60, 80))
    np.testing.assert_allclose(got, expected, atol=TOLERANCE, rtol=0)
    print(f'ViT-B/32 dense parity: {time.perf_counter() - start:.1f} s')


if __name__ == '__main__':
  absltest.main()
