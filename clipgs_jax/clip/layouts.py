"""CLIP checkpoint layouts: tensor names and shapes, renaming, checks."""

from collections.abc import Callable, Mapping
import dataclasses
import functools
import math
import re

from flax import traverse_util
import numpy as np

from clipgs_jax.clip import model

# Buffers some exporters save next to the weights; they carry no weights.
# OpenAI's .pt holds three int scalars that its build_model deletes.
_HARMLESS_OPENAI = re.compile(
    r'^(input_resolution|context_length|vocab_size)$|(^|\.)attn_mask$'
)
_HARMLESS_HF = re.compile(r'(^|\.)position_ids$')


# --------------------------------------------------------------------------
# Expected tensors of each layout.


def _openai_block_shapes(prefix: str, width: int, layers: int, ratio: int):
  shapes = {}
  for i in range(layers):
    p = f'{prefix}.{i}.'
    shapes.update({
        p + 'ln_1.weight': (width,),
        p + 'ln_1.bias': (width,),
        p + 'attn.in_proj_weight': (3 * width, width),
        p + 'attn.in_proj_bias': (3 * width,),
        p + 'attn.out_proj.weight': (width, width),
        p + 'attn.out_proj.bias': (width,),
        p + 'ln_2.weight': (width,),
        p + 'ln_2.bias': (width,),
        p + 'mlp.c_fc.weight': (ratio * width, width),
        p + 'mlp.c_fc.bias': (ratio * width,),
        p + 'mlp.c_proj.weight': (width, ratio * width),
        p + 'mlp.c_proj.bias': (width,),
    })
  return shapes


def openai_shapes(config: model.ClipConfig) -> dict[str, tuple[int, ...]]:
  """Returns name -> shape of every tensor in an OpenAI CLIP state dict."""
  c = config
  vw, tw, p = c.vision_width, c.text_width, c.patch_size
  shapes = {
      'visual.conv1.weight': (vw, 3, p, p),
      'visual.class_embedding': (vw,),
      'visual.positional_embedding': (c.grid_size**2 + 1, vw),
      'visual.ln_pre.weight': (vw,),
      'visual.ln_pre.bias': (vw,),
  }
  shapes.update(_openai_block_shapes(
      'visual.transformer.resblocks', vw, c.vision_layers, c.mlp_ratio))
  shapes.update({
      'visual.ln_post.weight': (vw,),
      'visual.ln_post.bias': (vw,),
      'visual.proj': (vw, c.embed_dim),
      'token_embedding.weight': (c.vocab_size, tw),
      'positional_embedding': (c.context_length, tw),
  })
  shapes.update(_openai_block_shapes(
      'transformer.resblocks', tw, c.text_layers, c.mlp_ratio))
  shapes.update({
      'ln_final.weight': (tw,),
      'ln_final.bias': (tw,),
      'text_projection': (tw, c.embed_dim),
      'logit_scale': (),
  })
  return shapes


def _hf_block_shapes(prefix: str, width: int, layers: int, ratio: int):
  shapes = {}
  for i in range(layers):
    p = f'{prefix}.{i}.'
    for norm in ('layer_norm1', 'layer_norm2'):
      shapes[p + norm + '.weight'] = (width,)
      shapes[p + norm + '.bias'] = (width,)
    for proj in ('q_proj', 'k_proj', 'v_proj', 'out_proj'):
      shapes[p + f'self_attn.{proj}.weight'] = (width, width)
      shapes[p + f'self_attn.{proj}.bias'] = (width,)
    shapes.update({
        p + 'mlp.fc1.weight': (ratio * width, width),
        p + 'mlp.fc1.bias': (ratio * width,),
        p + 'mlp.fc2.weight': (width, ratio * width),
        p + 'mlp.fc2.bias': (width,),
    })
  return shapes


def hf_shapes(config: model.ClipConfig) -> dict[str, tuple[int, ...]]:
  """Returns name -> shape of every tensor of a transformers CLIPModel."""
  c = config
  vw, tw, p = c.vision_width, c.text_width, c.patch_size
  v, t = 'vision_model.', 'text_model.'
  shapes = {
      v + 'embeddings.patch_embedding.weight': (vw, 3, p, p),
      v + 'embeddings.class_embedding': (vw,),
      v + 'embeddings.position_embedding.weight': (c.grid_size**2 + 1, vw),
      v + 'pre_layrnorm.weight': (vw,),  # sic, as transformers names it
      v + 'pre_layrnorm.bias': (vw,),
      v + 'post_layernorm.weight': (vw,),
      v + 'post_layernorm.bias': (vw,),
      'visual_projection.weight': (c.embed_dim, vw),
      t + 'embeddings.token_embedding.weight': (c.vocab_size, tw),
      t + 'embeddings.position_embedding.weight': (c.context_length, tw),
      t + 'final_layer_norm.weight': (tw,),
      t + 'final_layer_norm.bias': (tw,),
      'text_projection.weight': (c.embed_dim, tw),
      'logit_scale': (),
  }
  shapes.update(_hf_block_shapes(
      v + 'encoder.layers', vw, c.vision_layers, c.mlp_ratio))
  shapes.update(_hf_block_shapes(
      t + 'encoder.layers', tw, c.text_layers, c.mlp_ratio))
  return shapes


def flat_shapes(config: model.ClipConfig) -> dict[str, tuple[int, ...]]:
  """Returns '/'-joined name -> shape of our parameter tree."""
  return dict(_flat_shapes(config))


@functools.cache  # tracing the whole model takes about a second
def _flat_shapes(config: model.ClipConfig) -> tuple[tuple[str, tuple], ...]:
  flat = traverse_util.flatten_dict(model.param_shapes(config), sep='/')
  return tuple((k, tuple(v.shape)) for k, v in flat.items())


# --------------------------------------------------------------------------
# Layout conversion. Our tree mirrors OpenAI's names, so Hugging Face
# tensors are first renamed (and q/k/v fused) into OpenAI's layout.


def hf_to_openai(
    tensors: Mapping[str, np.ndarray], config: model.ClipConfig
) -> dict[str, np.ndarray]:
  """Rewrites checked transformers CLIPModel tensors in OpenAI's layout."""
  out = {}

  def blocks(src: str, dst: str, layers: int):
    for i in range(layers):
      s, d = f'{src}.{i}.', f'{dst}.{i}.'
      qkv = ('q_proj', 'k_proj', 'v_proj')
      for kind in ('weight', 'bias'):
        out[d + f'attn.in_proj_{kind}'] = np.concatenate(
            [tensors[s + f'self_attn.{n}.{kind}'] for n in qkv], axis=0
        )
        out[d + f'attn.out_proj.{kind}'] = tensors[
            s + f'self_attn.out_proj.{kind}']
        out[d + f'ln_1.{kind}'] = tensors[s + f'layer_norm1.{kind}']
        out[d + f'ln_2.{kind}'] = tensors[s + f'layer_norm2.{kind}']
        out[d + f'mlp.c_fc.{kind}'] = tensors[s + f'mlp.fc1.{kind}']
        out[d + f'mlp.c_proj.{kind}'] = tensors[s + f'mlp.fc2.{kind}']

  v, t = 'vision_model.', 'text_model.'
  out['visual.conv1.weight'] = tensors[v + 'embeddings.patch_embedding.weight']
  out['visual.class_embedding'] = tensors[v + 'embeddings.class_embedding']
  out['visual.positional_embedding'] = tensors[
      v + 'embeddings.position_embedding.weight']
  blocks(v + 'encoder.layers', 'visual.transformer.resblocks',
         config.vision_layers)
  out['token_embedding.weight'] = tensors[
      t + 'embeddings.token_embedding.weight']
  out['positional_embedding'] = tensors[
      t + 'embeddings.position_embedding.weight']
  blocks(t + 'encoder.layers', 'transformer.resblocks', config.text_layers)
  for kind in ('weight', 'bias'):
    out[f'visual.ln_pre.{kind}'] = tensors[v + f'pre_layrnorm.{kind}']
    out[f'visual.ln_post.{kind}'] = tensors[v + f'post_layernorm.{kind}']
    out[f'ln_final.{kind}'] = tensors[t + f'final_layer_norm.{kind}']
  # torch Linear weights are [out, in]; OpenAI stores these two as [in, out].
  out['visual.proj'] = tensors['visual_projection.weight'].T
  out['text_projection'] = tensors['text_projection.weight'].T
  out['logit_scale'] = tensors['logit_scale']
  return out


def openai_to_flat(
    tensors: Mapping[str, np.ndarray], config: model.ClipConfig
) -> dict[str, np.ndarray]:
  """Maps checked OpenAI-layout tensors to our '/'-keyed parameters."""
  out = {}

  def blocks(src: str, dst: str, layers: int):
    for i in range(layers):
      s, d = f'{src}.{i}.', f'{dst}/resblocks_{i}/'
      for norm in ('ln_1', 'ln_2'):
        out[d + f'{norm}/scale'] = tensors[s + f'{norm}.weight']
        out[d + f'{norm}/bias'] = tensors[s + f'{norm}.bias']
      # torch Linear weights are [out, in]; flax Dense kernels [in, out].
      out[d + 'attn/in_proj/kernel'] = tensors[s + 'attn.in_proj_weight'].T
      out[d + 'attn/in_proj/bias'] = tensors[s + 'attn.in_proj_bias']
      for src_name, dst_name in (('attn.out_proj', 'attn/out_proj'),
                                 ('mlp.c_fc', 'mlp/c_fc'),
                                 ('mlp.c_proj', 'mlp/c_proj')):
        out[d + dst_name + '/kernel'] = tensors[s + src_name + '.weight'].T
        out[d + dst_name + '/bias'] = tensors[s + src_name + '.bias']

  def norm(src: str, dst: str):
    out[dst + '/scale'] = tensors[src + '.weight']
    out[dst + '/bias'] = tensors[src + '.bias']

  # torch convolutions are [out, in, h, w]; flax kernels are [h, w, in, out].
  out['visual/conv1/kernel'] = tensors['visual.conv1.weight'].transpose(
      2, 3, 1, 0)
  out['visual/class_embedding'] = tensors['visual.class_embedding']
  out['visual/positional_embedding'] = tensors['visual.positional_embedding']
  norm('visual.ln_pre', 'visual/ln_pre')
  blocks('visual.transformer.resblocks', 'visual/transformer',
         config.vision_layers)
  norm('visual.ln_post', 'visual/ln_post')
  out['visual/proj'] = tensors['visual.proj']
  out['text/token_embedding/embedding'] = tensors['token_embedding.weight']
  out['text/positional_embedding'] = tensors['positional_embedding']
  blocks('transformer.resblocks', 'text/transformer', config.text_layers)
  norm('ln_final', 'text/ln_final')
  out['text/text_projection'] = tensors['text_projection']
  out['logit_scale'] = tensors['logit_scale']
  return out


# --------------------------------------------------------------------------
# Layout detection, variant inference and checking.


@dataclasses.dataclass(frozen=True)
class Layout:
  """How one checkpoint layout names things."""

  name: str  # for messages
  expected: Callable[[model.ClipConfig], dict[str, tuple[int, ...]]]
  harmless: Callable[[str], bool]
  # ClipConfig field -> (tensor name, axis) whose size gives the field.
  probes: dict[str, tuple[str, int]]
  vision_blocks: str  # prefix of the numbered vision blocks
  text_blocks: str  # prefix of the numbered text blocks


OPENAI = Layout(
    name='OpenAI',
    expected=openai_shapes,
    harmless=lambda n: bool(_HARMLESS_OPENAI.search(n)),
    probes={
        'vision_width': ('visual.conv1.weight', 0),
        'patch_size': ('visual.conv1.weight', 3),
        'num_positions': ('visual.positional_embedding', 0),
        'embed_dim': ('text_projection', 1),
        'context_length': ('positional_embedding', 0),
        'vocab_size': ('token_embedding.weight', 0),
        'text_width': ('ln_final.weight', 0),
    },
    vision_blocks='visual.transformer.resblocks.',
    text_blocks='transformer.resblocks.',
)
HF = Layout(
    name='Hugging Face CLIPModel',
    expected=hf_shapes,
    harmless=lambda n: bool(_HARMLESS_HF.search(n)),
    probes={
        'vision_width': ('vision_model.embeddings.patch_embedding.weight', 0),
        'patch_size': ('vision_model.embeddings.patch_embedding.weight', 3),
        'num_positions': ('vision_model.embeddings.position_embedding.weight',
                          0),
        'embed_dim': ('text_projection.weight', 0),
        'context_length': ('text_model.embeddings.position_embedding.weight',
                           0),
        'vocab_size': ('text_model.embeddings.token_embedding.weight', 0),
        'text_width': ('text_model.final_layer_norm.weight', 0),
    },
    vision_blocks='vision_model.encoder.layers.',
    text_blocks='text_model.encoder.layers.',
)


def detect_layout(names, source: str) -> Layout:
  """Returns the layout whose names a checkpoint uses, from its names."""
  if any(n.startswith(('vision_model.', 'text_model.')) for n in names):
    return HF
  if any(n.startswith('visual.') for n in names):
    return OPENAI
  raise ValueError(
      f'{source}: no CLIP tensors found (neither OpenAI names like '
      "'visual.conv1.weight' nor Hugging Face names like "
      "'vision_model.embeddings.patch_embedding.weight')."
  )


def _count_blocks(names, prefix: str) -> int:
  indices = {int(m.group(1)) for n in names
             if (m := re.match(re.escape(prefix) + r'(\d+)\.', n))}
  # The highest index, not the count: a file missing a middle block is then
  # reported block by block instead of loading as a shallower model.
  return max(indices) + 1 if indices else 0


def _shape_fields(config: model.ClipConfig) -> dict[str, int]:
  """The config fields that the probed tensor shapes determine."""
  fields = dataclasses.asdict(config)
  for field in ('vision_heads', 'text_heads', 'mlp_ratio'):
    del fields[field]
  return fields


def infer_config(
    shapes: Mapping[str, tuple[int, ...]], source: str = 'checkpoint'
) -> model.ClipConfig:
  """Returns the known variant whose shapes a checkpoint has.

  Head counts do not show in tensor shapes, hence the match against
  model.VARIANTS instead of building a config from the shapes alone.

  Args:
    shapes: tensor name -> shape, OpenAI or Hugging Face names.
    source: str, the file, for messages.

  Returns:
    the matching model.ClipConfig.

  Raises:
    ValueError: a shape-giving tensor is missing, or no variant matches.
  """
  layout = detect_layout(shapes, source)
  missing = sorted({name for name, _ in layout.probes.values()} - set(shapes))
  if missing:
    raise ValueError(
        f'{source}: cannot tell the CLIP variant, these tensors are '
        f'missing: {missing}. Pass the variant ({sorted(model.VARIANTS)}) '
        'to get every problem listed.'
    )
  found = {f: shapes[name][axis] if len(shapes[name]) > axis else -1
           for f, (name, axis) in layout.probes.items()}
  grid = math.isqrt(max(found.pop('num_positions') - 1, 0))
  found['image_size'] = grid * found['patch_size']
  found['vision_layers'] = _count_blocks(shapes, layout.vision_blocks)
  found['text_layers'] = _count_blocks(shapes, layout.text_blocks)
  for config in model.VARIANTS.values():
    if _shape_fields(config) == found:
      return config
  raise ValueError(
      f'{source}: its tensor shapes ({found}) match no known CLIP variant '
      f'({sorted(model.VARIANTS)}). Pass the intended variant to get every '
      'mismatching tensor listed.'
  )


def check_tensors(
    shapes: Mapping[str, tuple[int, ...]],
    expected: Mapping[str, tuple[int, ...]],
    harmless: Callable[[str], bool] = lambda name: False,
    source: str = 'checkpoint',
) -> None:
  """Raises one ValueError listing every missing, mis-shaped or unknown name.

  Args:
    shapes: name -> shape found in the file.
    expected: name -> shape the model needs.
    harmless: predicate for extra names to ignore silently.
    source: str, the file, for the message.
  """
  problems = []
  for name, shape in expected.items():
    if name not in shapes:
      problems.append(f'  missing:     {name} (expected {shape})')
    elif tuple(shapes[name]) != tuple(shape):
      problems.append(f'  wrong shape: {name} (expected {tuple(shape)}, '
                      f'found {tuple(shapes[name])})')
  for name in sorted(set(shapes) - set(expected)):
    if not harmless(name):
      problems.append(f'  unexpected:  {name} (found {tuple(shapes[name])})')
  if problems:
    raise ValueError(
        f'{source}: {len(problems)} CLIP tensor problem(s):\n'
        + '\n'.join(problems)
    )
