"""Helpers shared by the CLIP tests: random checkpoints and file writers."""

import json
import math
import pathlib
import re
import struct

import ml_dtypes
import numpy as np

from clipgs_jax.clip import layouts

# LayerNorm scales in both namings: ln_1, ln_pre, ln_final, layer_norm1,
# pre_layrnorm, post_layernorm, final_layer_norm.
_LAYER_NORM_SCALE = re.compile(r'(ln_|norm)[^.]*\.weight$')
# safetensors dtype names of the numpy dtypes the tests write.
_SAFETENSORS_NAMES = {
    np.dtype(np.float32): 'F32',
    np.dtype(np.float16): 'F16',
    np.dtype(ml_dtypes.bfloat16): 'BF16',
    np.dtype(np.int64): 'I64',
}


def random_tensors(shapes, seed=0):
  """Returns name -> float32 normal(0, 0.05) array for each name -> shape.

  Non-zero everywhere, LayerNorm scales included, so that a swapped or
  untransposed tensor changes the outputs.
  """
  rng = np.random.default_rng(seed)
  out = {}
  for name, shape in shapes.items():
    out[name] = rng.normal(0.0, 0.05, shape).astype(np.float32)
    if _LAYER_NORM_SCALE.search(name):
      out[name] += 1.0  # near 1, like trained LayerNorm scales
  out['logit_scale'] = np.asarray(math.log(1 / 0.07), np.float32)
  return out


def random_openai_tensors(config, seed=0):
  """Returns a random state dict in OpenAI naming for config."""
  return random_tensors(layouts.openai_shapes(config), seed)


def random_hf_tensors(config, seed=0):
  """Returns a random state dict in transformers CLIPModel naming."""
  return random_tensors(layouts.hf_shapes(config), seed)


def write_safetensors(path, tensors):
  """Writes name -> numpy array as a .safetensors file, by hand.

  The format is an 8-byte little-endian header size, a JSON header of
  dtype, shape and byte offsets, then the raw little-endian data; writing
  it here keeps the tests independent of the safetensors writer API.
  """
  header, blobs, offset = {}, [], 0
  for name, x in tensors.items():
    x = np.asarray(x)  # not ascontiguousarray, which makes scalars 1-d
    data = x.tobytes(order='C')
    header[name] = {
        'dtype': _SAFETENSORS_NAMES[x.dtype],
        'shape': list(x.shape),
        'data_offsets': [offset, offset + len(data)],
    }
    blobs.append(data)
    offset += len(data)
  encoded = json.dumps(header).encode('utf-8')
  encoded += b' ' * (-len(encoded) % 8)  # the format pads to 8 bytes
  pathlib.Path(path).write_bytes(
      struct.pack('<Q', len(encoded)) + encoded + b''.join(blobs)
  )


def random_hf_model(config, seed):
  """Returns a transformers CLIPModel with seeded random weights.

  Faster than transformers' own initialisation (built on the meta device,
  then filled once), and unlike it, LayerNorm scales and biases are not 1
  and 0, so a swapped ln_1/ln_2 or a dropped bias would show. Needs torch
  and transformers (imported here, so the other helpers do not).
  """
  import torch  # pylint: disable=g-import-not-at-top
  import transformers  # pylint: disable=g-import-not-at-top

  with torch.device('meta'):
    hf = transformers.CLIPModel(config)
  hf = hf.to_empty(device='cpu').eval()
  generator = torch.Generator().manual_seed(seed)
  with torch.no_grad():
    for name, p in hf.named_parameters():
      if p.ndim >= 2:  # matrices: unit-variance activations, U(-a, a)
        bound = (3.0 / np.prod(p.shape[1:])) ** 0.5
      else:
        bound = 0.1
      p.uniform_(-bound, bound, generator=generator)
      if re.search(r'(norm|layrnorm)\d?\.weight$', name):
        p.add_(1.0)
    for name, b in hf.named_buffers():
      # to_empty leaves buffers uninitialised; CLIP's only ones are these.
      assert name.endswith('position_ids'), name
      b.copy_(torch.arange(b.shape[-1]).expand_as(b))
  return hf
