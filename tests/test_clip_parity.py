"""Parity of the Flax CLIP towers with PyTorch on identical random weights."""

import functools
import pathlib
import re
import shutil
import tempfile
import warnings

from absl.testing import absltest
from absl.testing import parameterized
import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import clip_testutil
from clipgs_jax.clip import model
from clipgs_jax.clip import tokenizer
from clipgs_jax.clip import weights

torch = pytest.importorskip(
    'torch', reason='the parity tests need torch (pip install .[test])')
transformers = pytest.importorskip(
    'transformers', reason='the parity tests need transformers')

PROMPTS = (
    'a photo of a person', 'a photo of people', 'a photo of pedestrians',
    'a photo of hands', 'a photo of a balloon', 'a photo of a building',
    'a photo of a wall', 'a photo of furniture',
    'a much longer prompt, with punctuation and 3 digits: 1 2 3!',
)
TOLERANCE = 1e-4  # max abs difference allowed in float32


def b32_hf_config():
  """transformers.CLIPConfig of OpenAI's ViT-B/32."""
  return transformers.CLIPConfig(
      text_config=dict(
          hidden_size=512, intermediate_size=2048, num_hidden_layers=12,
          num_attention_heads=8, max_position_embeddings=77,
          vocab_size=49408, hidden_act='quick_gelu', projection_dim=512,
          # Pooling then uses the first end token, which is where OpenAI's
          # argmax lands.
          bos_token_id=tokenizer.START_OF_TEXT,
          eos_token_id=tokenizer.END_OF_TEXT,
      ),
      vision_config=dict(
          hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
          num_attention_heads=12, image_size=224, patch_size=32,
          hidden_act='quick_gelu', projection_dim=512,
      ),
      projection_dim=512,
  )


# transformers CLIPModel names -> OpenAI names, written out independently of
# clipgs_jax.clip.weights so that the two mappings check each other.
_HF_TO_OPENAI = {
    'vision_model.embeddings.patch_embedding.weight': 'visual.conv1.weight',
    'vision_model.embeddings.class_embedding': 'visual.class_embedding',
    'vision_model.embeddings.position_embedding.weight':
        'visual.positional_embedding',
    'vision_model.pre_layrnorm.weight': 'visual.ln_pre.weight',
    'vision_model.pre_layrnorm.bias': 'visual.ln_pre.bias',
    'vision_model.post_layernorm.weight': 'visual.ln_post.weight',
    'vision_model.post_layernorm.bias': 'visual.ln_post.bias',
    'text_model.embeddings.token_embedding.weight': 'token_embedding.weight',
    'text_model.embeddings.position_embedding.weight': 'positional_embedding',
    'text_model.final_layer_norm.weight': 'ln_final.weight',
    'text_model.final_layer_norm.bias': 'ln_final.bias',
    'logit_scale': 'logit_scale',
}
_HF_BLOCK_TO_OPENAI = {
    'layer_norm1': 'ln_1', 'layer_norm2': 'ln_2',
    'self_attn.out_proj': 'attn.out_proj',
    'mlp.fc1': 'mlp.c_fc', 'mlp.fc2': 'mlp.c_proj',
}


def openai_state_dict(hf_state):
  """Returns OpenAI's state dict layout of transformers CLIPModel tensors.

  q/k/v are concatenated into in_proj_weight/bias; the two projections are
  transposed, as OpenAI applies them as x @ W.
  """
  out, fused = {}, {}
  for name, t in hf_state.items():
    m = re.fullmatch(
        r'(vision|text)_model\.encoder\.layers\.(\d+)\.(.+)\.(weight|bias)',
        name)
    if m:
      tower, i, module, kind = m.groups()
      prefix = ('visual.' if tower == 'vision' else '') + (
          f'transformer.resblocks.{i}.')
      if module in ('self_attn.q_proj', 'self_attn.k_proj',
                    'self_attn.v_proj'):
        fused.setdefault((prefix, kind), {})[module[-6]] = t
      else:
        out[prefix + _HF_BLOCK_TO_OPENAI[module] + '.' + kind] = t
    elif name in _HF_TO_OPENAI:
      out[_HF_TO_OPENAI[name]] = t
    elif name == 'visual_projection.weight':
      out['visual.proj'] = t.T.contiguous()
    elif name == 'text_projection.weight':
      out['text_projection'] = t.T.contiguous()
    elif not name.endswith('position_ids'):
      raise AssertionError(f'unmapped transformers tensor {name}')
  for (prefix, kind), qkv in fused.items():
    out[prefix + f'attn.in_proj_{kind}'] = torch.cat(
        [qkv['q'], qkv['k'], qkv['v']], dim=0)
  # The three int scalars that OpenAI's own .pt files carry.
  out['input_resolution'] = torch.tensor(224)
  out['context_length'] = torch.tensor(77)
  out['vocab_size'] = torch.tensor(49408)
  return out


def _features(output):
  # transformers 5 returns a model output with the projected pooler_output;
  # older versions return the tensor itself.
  return getattr(output, 'pooler_output', output).detach().numpy()


@functools.partial(jax.jit, static_argnames='config')
def raw_features(params, images, tokens, config):
  return model.Clip(config).apply({'params': params}, images, tokens)


class ViTB32ParityTest(parameterized.TestCase):
  """One random ViT-B/32, saved in both layouts, run by torch and by us."""

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    hf = clip_testutil.random_hf_model(b32_hf_config(), seed=0)
    rng = np.random.default_rng(0)
    cls.images = rng.normal(size=(2, 224, 224, 3)).astype(np.float32)
    cls.tokens = tokenizer.tokenize(PROMPTS)
    with torch.no_grad():
      cls.ref_image = _features(hf.get_image_features(
          pixel_values=torch.from_numpy(cls.images.transpose(0, 3, 1, 2))))
      cls.ref_text = _features(hf.get_text_features(
          input_ids=torch.from_numpy(cls.tokens.astype(np.int64))))
    cls.ref_logit_scale = float(hf.logit_scale.detach())
    cls.loaded = {}
    cls.dir = pathlib.Path(tempfile.mkdtemp())
    hf.save_pretrained(cls.dir / 'hf')
    cls.pt_path = cls.dir / 'ViT-B-32.pt'
    torch.save(openai_state_dict(hf.state_dict()), cls.pt_path)

  @classmethod
  def tearDownClass(cls):
    shutil.rmtree(cls.dir)
    super().tearDownClass()

  def _check(self, config, params):
    self.assertEqual(config, model.VARIANTS['ViT-B/32'])
    image, text = raw_features(params, jnp.asarray(self.images),
                               jnp.asarray(self.tokens), config)
    self.assertLessEqual(float(np.abs(image - self.ref_image).max()),
                         TOLERANCE)
    self.assertLessEqual(float(np.abs(text - self.ref_text).max()), TOLERANCE)
    # Normalised as encode_image/encode_text do (tested against this on the
    # tiny variant; not recompiled here at full size to save time).
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)
    np.testing.assert_allclose(model.l2_normalize(image),
                               unit(self.ref_image), atol=TOLERANCE, rtol=0)
    np.testing.assert_allclose(model.l2_normalize(text),
                               unit(self.ref_text), atol=TOLERANCE, rtol=0)
    self.assertAlmostEqual(float(params['logit_scale']),
                           self.ref_logit_scale, places=6)

  @classmethod
  def _load(cls, kind):
    # Each file is loaded once for the whole class.
    if kind not in cls.loaded:
      path = cls.dir / 'hf' / 'model.safetensors' if kind == 'hf' else (
          cls.pt_path)
      cls.loaded[kind] = weights.load(path)
    return cls.loaded[kind]

  def test_hugging_face_safetensors(self):
    self._check(*self._load('hf'))

  def test_openai_state_dict(self):
    config, params = self._load('openai')
    self._check(config, params)
    # Both importers build the very same tree.
    chex.assert_trees_all_equal(params, self._load('hf')[1])


def _torchscript_module(state):
  """A scripted torch module whose state_dict is `state`."""

  class Node(torch.nn.Module):

    def forward(self, x: torch.Tensor) -> torch.Tensor:
      return x

  root = Node()
  for name, value in state.items():
    *path, leaf = name.split('.')
    node = root
    for part in path:
      if not hasattr(node, part):
        node.add_module(part, Node())
      node = getattr(node, part)
    node.register_parameter(leaf, torch.nn.Parameter(value))
  with warnings.catch_warnings():
    # Writing TorchScript is deprecated, but OpenAI's files are TorchScript.
    warnings.simplefilter('ignore', DeprecationWarning)
    return torch.jit.script(root)


class TorchFileTest(parameterized.TestCase):
  """The tiny variant through the two torch file kinds and dtypes."""

  def test_torchscript_archive(self):
    sd = clip_testutil.random_openai_tensors(model.VARIANTS['tiny'])
    path = pathlib.Path(self.create_tempdir().full_path) / 'tiny.pt'
    _torchscript_module(
        {k: torch.from_numpy(v) for k, v in sd.items()}).save(str(path))
    config, params = weights.load(path)
    _, expected = weights.params_from_tensors(sd)
    self.assertEqual(config, model.VARIANTS['tiny'])
    chex.assert_trees_all_equal(params, expected)

  @parameterized.parameters('float16', 'bfloat16')
  def test_half_precision_state_dict(self, dtype):
    sd = clip_testutil.random_openai_tensors(model.VARIANTS['tiny'])
    half = {k: torch.from_numpy(v).to(getattr(torch, dtype))
            for k, v in sd.items()}
    path = pathlib.Path(self.create_tempdir().full_path) / 'tiny.pt'
    torch.save(half, path)
    _, params = weights.load(path)
    _, expected = weights.params_from_tensors(
        {k: v.float().numpy() for k, v in half.items()})
    chex.assert_trees_all_equal(params, expected)
    self.assertEqual(params['visual']['proj'].dtype, jnp.float32)


if __name__ == '__main__':
  absltest.main()
