"""Tests of the CLIP towers, weight import and preprocessing (no torch)."""

import dataclasses
import functools
import json
import os
import pathlib
import subprocess
import sys
from unittest import mock

from absl.testing import absltest
from absl.testing import parameterized
import chex
from flax import traverse_util
import jax
import jax.numpy as jnp
import ml_dtypes
import numpy as np

import clip_testutil
from clipgs_jax.clip import layouts
from clipgs_jax.clip import model
from clipgs_jax.clip import preprocess
from clipgs_jax.clip import tokenizer
from clipgs_jax.clip import weights

TINY = model.VARIANTS['tiny']
# Published parameter counts of OpenAI's checkpoints (e.g. keras-hub's CLIP
# presets list 151,277,313 for ViT-B/32; open_clip's tables give all three).
PARAM_COUNTS = {
    'ViT-B/32': 151_277_313,
    'ViT-B/16': 149_620_737,
    'ViT-L/14': 427_616_513,
}


@functools.cache
def tiny_params():
  # From numpy through the importer: no init to compile, and LayerNorm
  # scales and biases that are not 1 and 0.
  tensors = clip_testutil.random_openai_tensors(TINY)
  return weights.params_from_tensors(tensors)[1]


def tiny_images(n, seed=0):
  rng = np.random.default_rng(seed)
  return jnp.asarray(rng.normal(size=(n, 32, 32, 3)), jnp.float32)


class ShapesTest(parameterized.TestCase):

  @parameterized.parameters(*model.VARIANTS)
  def test_param_and_output_shapes(self, variant):
    c = model.VARIANTS[variant]
    shapes = model.param_shapes(c)  # eval_shape: no compute, no memory
    v, t = shapes['visual'], shapes['text']
    g = c.image_size // c.patch_size
    w, tw = c.vision_width, c.text_width
    self.assertEqual(v['conv1']['kernel'].shape,
                     (c.patch_size, c.patch_size, 3, w))
    self.assertEqual(v['positional_embedding'].shape, (g * g + 1, w))
    self.assertEqual(v['proj'].shape, (w, c.embed_dim))
    self.assertLen([k for k in v['transformer'] if 'resblocks' in k],
                   c.vision_layers)
    self.assertEqual(
        v['transformer']['resblocks_0']['attn']['in_proj']['kernel'].shape,
        (w, 3 * w))
    self.assertEqual(t['token_embedding']['embedding'].shape,
                     (c.vocab_size, tw))
    self.assertEqual(t['text_projection'].shape, (tw, c.embed_dim))
    self.assertLen(t['transformer'], c.text_layers)
    self.assertEqual(shapes['logit_scale'].shape, ())
    if variant in PARAM_COUNTS:
      count = sum(x.size for x in jax.tree.leaves(shapes))
      self.assertEqual(count, PARAM_COUNTS[variant])
    images = jax.ShapeDtypeStruct((3, c.image_size, c.image_size, 3),
                                  jnp.float32)
    tokens = jax.ShapeDtypeStruct((5, c.context_length), jnp.int32)
    out = jax.eval_shape(functools.partial(model.encode_image, config=c),
                         shapes, images)
    self.assertEqual((out.shape, out.dtype), ((3, c.embed_dim), jnp.float32))
    out = jax.eval_shape(functools.partial(model.encode_text, config=c),
                         shapes, tokens)
    self.assertEqual(out.shape, (5, c.embed_dim))

  def test_init_params(self):
    got = jax.eval_shape(functools.partial(model.init_params, TINY),
                         jax.random.key(0))
    chex.assert_trees_all_equal_shapes_and_dtypes(
        got, model.param_shapes(TINY))

  def test_heads_divide_widths(self):
    for c in model.VARIANTS.values():
      self.assertEqual(c.vision_width % c.vision_heads, 0)
      self.assertEqual(c.text_width % c.text_heads, 0)
      self.assertEqual(c.image_size % c.patch_size, 0)

  def test_wrong_image_size_rejected(self):
    with self.assertRaises(AssertionError):
      model.encode_image(tiny_params(), jnp.zeros((1, 30, 30, 3)),
                         config=TINY)


def _layer_norm(x, p):
  mu = x.mean(-1, keepdims=True)
  var = ((x - mu) ** 2).mean(-1, keepdims=True)
  return (x - mu) / np.sqrt(var + 1e-5) * p['scale'] + p['bias']


def _reference_block(x, p, heads, causal):
  """One residual block in float64 numpy, written from the CLIP paper."""
  b, l, w = x.shape
  d = w // heads
  h = _layer_norm(x, p['ln_1'])
  qkv = h @ p['attn']['in_proj']['kernel'] + p['attn']['in_proj']['bias']
  q, k, v = np.split(qkv, 3, axis=-1)
  split = lambda a: a.reshape(b, l, heads, d).transpose(0, 2, 1, 3)
  logits = split(q) @ split(k).transpose(0, 1, 3, 2) / np.sqrt(d)
  if causal:
    logits = np.where(np.tril(np.ones((l, l), bool)), logits, -np.inf)
  probs = np.exp(logits - logits.max(-1, keepdims=True))
  probs /= probs.sum(-1, keepdims=True)
  attn = (probs @ split(v)).transpose(0, 2, 1, 3).reshape(b, l, w)
  x = x + attn @ p['attn']['out_proj']['kernel'] + p['attn']['out_proj']['bias']
  h = _layer_norm(x, p['ln_2'])
  h = h @ p['mlp']['c_fc']['kernel'] + p['mlp']['c_fc']['bias']
  h = h / (1 + np.exp(-1.702 * h))  # QuickGELU
  return x + h @ p['mlp']['c_proj']['kernel'] + p['mlp']['c_proj']['bias']


class ModulesTest(parameterized.TestCase):

  def test_quick_gelu(self):
    x = jnp.asarray([-3.0, -1.0, 0.0, 0.5, 2.0])
    expected = np.asarray(x) / (1 + np.exp(-1.702 * np.asarray(x)))
    np.testing.assert_allclose(model.quick_gelu(x), expected, rtol=1e-6)

  @parameterized.parameters(False, True)
  def test_residual_block_against_numpy(self, causal):
    block = model.ResidualBlock(num_heads=4, causal=causal)
    rng = np.random.default_rng(1)
    # Variance 1e-5, the LayerNorm epsilon, so a wrong epsilon shows.
    x = (rng.normal(size=(2, 7, 16)) * 10**-2.5).astype(np.float32)
    params = jax.jit(block.init)(jax.random.key(2), x)['params']
    # Perturb every parameter so LayerNorm scales and biases are not 1 and 0
    # (in numpy: eager jax ops would compile once per shape).
    params = jax.tree.map(
        lambda a: (a + 0.3 * rng.normal(size=a.shape)).astype(np.float32),
        params)
    got = jax.jit(block.apply)({'params': params}, x)
    ref = _reference_block(
        np.asarray(x, np.float64),
        jax.tree.map(lambda a: np.asarray(a, np.float64), params), 4, causal)
    np.testing.assert_allclose(got, ref, atol=2e-5)

  def test_l2_normalize(self):
    x = jnp.asarray([[3.0, 4.0], [0.0, 0.0]])
    np.testing.assert_allclose(model.l2_normalize(x),
                               [[0.6, 0.8], [0.0, 0.0]], atol=1e-7)


class TinyForwardTest(parameterized.TestCase):

  def test_image_embeddings(self):
    images = tiny_images(3)
    out = model.encode_image(tiny_params(), images, config=TINY)
    chex.assert_shape(out, (3, TINY.embed_dim))
    chex.assert_tree_all_finite(out)
    np.testing.assert_allclose(jnp.linalg.norm(out, axis=-1), 1.0, rtol=1e-5)
    # Deterministic, and each image independent of the rest of its batch.
    again = model.encode_image(tiny_params(), images, config=TINY)
    np.testing.assert_array_equal(out, again)
    one = model.encode_image(tiny_params(), images[1:2], config=TINY)
    np.testing.assert_allclose(one[0], out[1], atol=1e-6)
    # The encoder is the normalised output of the module.
    raw, _ = jax.jit(model.Clip(TINY).apply)({'params': tiny_params()},
                                             images)
    np.testing.assert_allclose(out, model.l2_normalize(raw), atol=1e-6)
    self.assertGreater(float(jnp.abs(out[0] - out[1]).max()), 1e-3)

  def test_text_pools_at_end_token(self):
    tokens = tokenizer.tokenize(['a photo of a person', 'a photo of hands'])
    out = model.encode_text(tiny_params(), jnp.asarray(tokens), config=TINY)
    chex.assert_shape(out, (2, TINY.embed_dim))
    np.testing.assert_allclose(jnp.linalg.norm(out, axis=-1), 1.0, rtol=1e-5)
    self.assertGreater(float(jnp.abs(out[0] - out[1]).max()), 1e-3)
    # Causal attention: tokens after the end token change nothing.
    garbage = tokens.copy()
    garbage[:, 10:] = 1234
    same = model.encode_text(tiny_params(), jnp.asarray(garbage), config=TINY)
    np.testing.assert_allclose(same, out, atol=1e-6)
    # Rows cut short after the end token give the same embeddings too.
    short = model.encode_text(tiny_params(), jnp.asarray(tokens[:, :8]),
                              config=TINY)
    np.testing.assert_allclose(short, out, atol=1e-6)
    # The encoder is the normalised output of the module.
    _, raw = jax.jit(model.Clip(TINY).apply)({'params': tiny_params()},
                                             tokens=jnp.asarray(tokens))
    np.testing.assert_allclose(out, model.l2_normalize(raw), atol=1e-6)
    # A token before it does change the embedding.
    changed = tokens.copy()
    changed[:, 2] = 4000
    diff = model.encode_text(tiny_params(), jnp.asarray(changed), config=TINY)
    self.assertGreater(float(jnp.abs(diff - out).max()), 1e-3)

  def test_text_embedding_cache(self):
    cache = model.TextEmbeddingCache(tiny_params(), TINY)
    prompts = ['a photo of a person', 'a photo of a wall']
    first = cache(prompts)
    self.assertIs(cache(tuple(prompts)), first)  # served, not recomputed
    # Full 77-token rows give the same embeddings as the cache's trimmed ones.
    expected = model.encode_text(
        tiny_params(), jnp.asarray(tokenizer.tokenize(prompts)), config=TINY)
    np.testing.assert_allclose(first, expected, atol=1e-6)
    other = cache(prompts[::-1])
    np.testing.assert_allclose(other, first[::-1], atol=1e-6)


class WeightImportTest(parameterized.TestCase):

  def test_openai_mapping(self):
    sd = clip_testutil.random_openai_tensors(TINY)
    config, params = weights.params_from_tensors(sd)
    self.assertEqual(config, TINY)
    v = params['visual']
    # torch conv [out, in, h, w] -> flax [h, w, in, out];
    # torch Linear [out, in] -> flax Dense [in, out].
    np.testing.assert_array_equal(
        v['conv1']['kernel'][1, 2, 0, 5], sd['visual.conv1.weight'][5, 0, 1, 2])
    blk = v['transformer']['resblocks_1']
    np.testing.assert_array_equal(
        blk['attn']['in_proj']['kernel'],
        sd['visual.transformer.resblocks.1.attn.in_proj_weight'].T)
    np.testing.assert_array_equal(
        blk['ln_2']['scale'], sd['visual.transformer.resblocks.1.ln_2.weight'])
    np.testing.assert_array_equal(params['text']['text_projection'],
                                  sd['text_projection'])
    np.testing.assert_array_equal(v['proj'], sd['visual.proj'])
    self.assertEqual(v['proj'].dtype, jnp.float32)

  def test_hf_and_openai_layouts_agree(self):
    hf = clip_testutil.random_hf_tensors(TINY)
    _, from_hf = weights.params_from_tensors(hf)
    blk = from_hf['text']['transformer']['resblocks_0']['attn']['in_proj']
    p = 'text_model.encoder.layers.0.self_attn.'
    np.testing.assert_array_equal(
        blk['kernel'],
        np.concatenate([hf[p + f'{n}_proj.weight'] for n in 'qkv']).T)
    np.testing.assert_array_equal(from_hf['visual']['proj'],
                                  hf['visual_projection.weight'].T)

  @parameterized.parameters(*model.VARIANTS)
  def test_infer_variant(self, variant):
    c = model.VARIANTS[variant]
    self.assertEqual(layouts.infer_config(layouts.openai_shapes(c)), c)
    self.assertEqual(layouts.infer_config(layouts.hf_shapes(c)), c)

  def test_errors_list_every_problem(self):
    sd = clip_testutil.random_openai_tensors(TINY)
    del sd['visual.ln_post.bias']
    del sd['transformer.resblocks.1.mlp.c_proj.weight']
    sd['transformer.resblocks.0.mlp.c_fc.weight'] = np.zeros((5, 32))
    sd['visual.mystery'] = np.zeros(3)
    # Harmless extras, not reported.
    sd['input_resolution'] = np.asarray(32)
    sd['transformer.resblocks.0.attn_mask'] = np.zeros((77, 77))
    with self.assertRaises(ValueError) as cm:
      weights.params_from_tensors(sd, 'tiny', source='bad.pt')
    msg = str(cm.exception)
    self.assertIn('bad.pt (OpenAI names): 4 CLIP tensor problem(s)', msg)
    self.assertIn('missing:     visual.ln_post.bias (expected (64,))', msg)
    self.assertIn('missing:     transformer.resblocks.1.mlp.c_proj.weight '
                  '(expected (32, 128))', msg)
    self.assertIn('wrong shape: transformer.resblocks.0.mlp.c_fc.weight '
                  '(expected (128, 32), found (5, 32))', msg)
    self.assertIn('unexpected:  visual.mystery (found (3,))', msg)
    self.assertNotIn('input_resolution', msg)
    self.assertNotIn('attn_mask', msg)

  def test_hf_errors_use_hf_names(self):
    sd = clip_testutil.random_hf_tensors(TINY)
    sd['text_model.embeddings.position_ids'] = np.arange(77)[None]
    sd['vision_model.encoder.layers.0.self_attn.k_proj.bias'] = np.zeros(65)
    with self.assertRaisesRegex(
        ValueError, r'1 CLIP tensor problem.*\n.*wrong shape: vision_model'
        r'\.encoder\.layers\.0\.self_attn\.k_proj\.bias \(expected \(64,\), '
        r'found \(65,\)\)$'):
      weights.params_from_tensors(sd)

  def test_wrong_variant(self):
    sd = clip_testutil.random_openai_tensors(TINY)
    with self.assertRaisesRegex(ValueError, r'wrong shape: visual\.conv1\.'
                                r'weight \(expected \(768, 3, 32, 32\), '
                                r'found \(64, 3, 8, 8\)\)'):
      weights.params_from_tensors(sd, 'ViT-B/32')

  def test_uninferable_variants(self):
    sd = clip_testutil.random_openai_tensors(TINY)
    missing = dict(sd)
    del missing['visual.conv1.weight']
    with self.assertRaisesRegex(ValueError, r"missing: \['visual\.conv1"):
      weights.params_from_tensors(missing)
    # A whole top block gone: no known variant has one vision layer.
    shallow = {k: v for k, v in sd.items()
               if not k.startswith('visual.transformer.resblocks.1.')}
    with self.assertRaisesRegex(ValueError, 'vision_layers.: 1.*match no'):
      weights.params_from_tensors(shallow)
    with self.assertRaisesRegex(ValueError, 'no CLIP tensors'):
      weights.params_from_tensors({'foo': np.zeros(1)})

  def test_npz_round_trip(self):
    d = pathlib.Path(self.create_tempdir().full_path)
    weights.save_npz(d / 'tiny.npz', TINY, tiny_params())
    self.assertEqual(os.listdir(d), ['tiny.npz'])  # no temporary left over
    with np.load(d / 'tiny.npz') as f:
      self.assertIn('visual/conv1/kernel', f.files)
    with mock.patch.dict(sys.modules, {'torch': None}):  # torch not needed
      config, params = weights.load(d / 'tiny.npz')
    self.assertEqual(config, TINY)
    chex.assert_trees_all_equal(params, tiny_params())
    with self.assertRaisesRegex(ValueError, 'not the requested'):
      weights.load(d / 'tiny.npz', 'ViT-B/32')
    images = tiny_images(2)
    np.testing.assert_array_equal(
        model.encode_image(params, images, config=config),
        model.encode_image(tiny_params(), images, config=TINY))

  def test_convert_script(self):
    d = pathlib.Path(self.create_tempdir().full_path)
    sd = clip_testutil.random_hf_tensors(TINY)
    clip_testutil.write_safetensors(d / 'model.safetensors', sd)
    root = pathlib.Path(__file__).resolve().parents[1]
    result = subprocess.run(
        [sys.executable, str(root / 'experiments' / 'convert_clip.py'),
         f'--src={d}', f'--dst={d / "tiny.npz"}'],
        capture_output=True, text=True, check=False, timeout=120,
        env=dict(os.environ, JAX_PLATFORMS='cpu', PYTHONPATH=os.pathsep.join(
            [str(root), os.environ.get('PYTHONPATH', '')])))
    self.assertEqual(result.returncode, 0, result.stderr)
    self.assertEqual(json.loads(result.stdout)['variant'], 'tiny')
    _, converted = weights.load(d / 'tiny.npz')
    chex.assert_trees_all_equal(converted, weights.params_from_tensors(sd)[1])

  def test_npz_with_bad_tensor(self):
    d = pathlib.Path(self.create_tempdir().full_path)
    flat = traverse_util.flatten_dict(tiny_params(), sep='/')
    flat = {k: np.asarray(v) for k, v in flat.items()}
    flat['visual/proj'] = np.zeros((64, 31), np.float32)
    flat[weights.CONFIG_KEY] = np.asarray(
        json.dumps(dataclasses.asdict(TINY)))
    np.savez(d / 'bad.npz', **flat)
    with self.assertRaisesRegex(ValueError, r'visual/proj \(expected '
                                r'\(64, 32\), found \(64, 31\)\)'):
      weights.load(d / 'bad.npz')

  @parameterized.parameters(np.float16, ml_dtypes.bfloat16)
  def test_half_precision_safetensors(self, dtype):
    sd = clip_testutil.random_hf_tensors(TINY)
    sd = {k: v.astype(dtype) for k, v in sd.items()}
    sd['vision_model.embeddings.position_ids'] = np.arange(17)[None]
    path = pathlib.Path(self.create_tempdir().full_path) / 'model.safetensors'
    clip_testutil.write_safetensors(path, sd)
    config, params = weights.load(path.parent)  # the directory form
    self.assertEqual(config, TINY)
    chex.assert_trees_all_equal_dtypes(
        params, jax.tree.map(lambda x: jnp.zeros((), jnp.float32), params))
    np.testing.assert_array_equal(
        params['text']['ln_final']['scale'],
        sd['text_model.final_layer_norm.weight'].astype(np.float32))

  def test_torch_needed_for_pt(self):
    path = pathlib.Path(self.create_tempdir().full_path) / 'ViT-B-32.pt'
    path.write_bytes(b'not read')
    with mock.patch.dict(sys.modules, {'torch': None}):
      with self.assertRaisesRegex(ImportError, 'needs torch.*convert_clip.py'):
        weights.load(path)

  def test_unknown_suffix(self):
    with self.assertRaisesRegex(ValueError, 'unknown CLIP checkpoint type'):
      weights.read_tensors('weights.h5')


class ResolveWeightsPathTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    self.file = pathlib.Path(self.create_tempdir().create_file('w.npz')
                             .full_path)

  def test_flag_wins_over_environment(self):
    with mock.patch.dict(os.environ, {weights.ENV_VAR: '/nonexistent'}):
      self.assertEqual(weights.resolve_weights_path(str(self.file)), self.file)

  def test_environment(self):
    with mock.patch.dict(os.environ, {weights.ENV_VAR: str(self.file)}):
      self.assertEqual(weights.resolve_weights_path(''), self.file)
      self.assertEqual(weights.resolve_weights_path(None), self.file)

  def test_neither_names_both(self):
    with mock.patch.dict(os.environ, clear=True):
      with self.assertRaisesRegex(
          ValueError, '--clip_weights.*CLIPGS_CLIP_WEIGHTS.*Nothing is '
          'downloaded'):
        weights.resolve_weights_path(None)

  def test_missing_file_names_source(self):
    with mock.patch.dict(os.environ, {weights.ENV_VAR: '/no/such.pt'}):
      with self.assertRaisesRegex(FileNotFoundError, 'CLIPGS_CLIP_WEIGHTS'):
        weights.resolve_weights_path(None)


class PreprocessTest(parameterized.TestCase):

  @parameterized.product(mode=preprocess.MODES, hw=[(300, 400), (64, 48)])
  def test_constant_image(self, mode, hw):
    out = preprocess.preprocess(jnp.full(hw + (3,), 0.5), mode=mode)
    chex.assert_shape(out, (224, 224, 3))
    # (0.5 - mean) / std per channel, by hand:
    # (0.5 - 0.48145466) / 0.26862954 = 0.0690369
    # (0.5 - 0.4578275) / 0.26130258 = 0.1613934
    # (0.5 - 0.40821073) / 0.27577711 = 0.3328386
    np.testing.assert_allclose(
        out, np.broadcast_to([0.0690369, 0.1613934, 0.3328386], out.shape),
        atol=2e-6)

  def test_batched_and_jitted(self):
    images = jax.random.uniform(jax.random.key(0), (2, 120, 90, 3))
    eager = preprocess.preprocess(images, mode='center_crop', size=64)
    jitted = jax.jit(preprocess.preprocess, static_argnames=('mode', 'size'))
    chex.assert_shape(eager, (2, 64, 64, 3))
    np.testing.assert_allclose(
        jitted(images, mode='center_crop', size=64), eager, atol=1e-5)
    one = preprocess.preprocess(images[1], mode='center_crop', size=64)
    np.testing.assert_allclose(one, eager[1], atol=1e-6)

  def test_center_crop_geometry(self):
    # Shorter side 300 -> 224, longer 400 -> int(224 * 400 / 300) = 298,
    # then columns round((298 - 224) / 2) = 37 .. 261.
    self.assertEqual(preprocess._center_crop_size(300, 400, 224), (224, 298))
    self.assertEqual(preprocess._center_crop_size(400, 300, 224), (298, 224))
    ramp = jnp.broadcast_to(jnp.linspace(0.0, 1.0, 400)[None, :, None],
                            (300, 400, 3))
    resized = jax.image.resize(ramp, (224, 298, 3), 'bicubic', antialias=True)
    expected = preprocess.preprocess(resized[:, 37:261], mode='resize')
    np.testing.assert_allclose(
        preprocess.preprocess(ramp, mode='center_crop'), expected, atol=1e-6)

  def test_resize_matches_pil_bicubic(self):
    try:
      from PIL import Image  # pylint: disable=g-import-not-at-top
    except ImportError:
      self.skipTest('Pillow is not installed')
    rng = np.random.default_rng(0)
    gray = rng.uniform(size=(300, 400)).astype(np.float32)
    # PIL's float-mode bicubic: same Keys kernel, same antialiasing.
    ref = np.asarray(Image.fromarray(gray).resize(
        (224, 224), Image.Resampling.BICUBIC))
    out = preprocess.preprocess(np.repeat(gray[..., None], 3, -1))
    got = out[..., 0] * preprocess.STD[0] + preprocess.MEAN[0]
    np.testing.assert_allclose(got, np.clip(ref, 0.0, 1.0), atol=5e-5)

  @parameterized.parameters(1.0001, -0.01, np.nan, np.inf)
  def test_bad_values_rejected(self, value):
    image = np.full((8, 8, 3), 0.5, np.float32)
    image[3, 4, 1] = value
    with self.assertRaisesRegex(ValueError, r'\[0, 1\]|NaN'):
      preprocess.preprocess(image)

  def test_no_check_under_jit(self):
    image = jnp.full((8, 8, 3), 2.0)  # out of range, but traced
    out = jax.jit(preprocess.preprocess)(image)
    chex.assert_tree_all_finite(out)

  def test_bad_arguments(self):
    with self.assertRaisesRegex(ValueError, 'mode'):
      preprocess.preprocess(jnp.zeros((8, 8, 3)), mode='crop')
    with self.assertRaisesRegex(ValueError, 'RGB'):
      preprocess.preprocess(jnp.zeros((8, 8)))


if __name__ == '__main__':
  absltest.main()
