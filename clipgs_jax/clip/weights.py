"""CLIP checkpoint import: OpenAI .pt, Hugging Face safetensors, our .npz."""

from collections.abc import Mapping
import dataclasses
import json
import os
import pathlib
import tempfile
import warnings
import zipfile

from flax import traverse_util
import jax
import ml_dtypes
import numpy as np
import safetensors
import safetensors.numpy

from clipgs_jax.clip import layouts
from clipgs_jax.clip import model

ENV_VAR = 'CLIPGS_CLIP_WEIGHTS'
# Key of the JSON-encoded ClipConfig inside our .npz files.
CONFIG_KEY = '__config__'
_SAFETENSORS_DTYPES = {
    'F64': np.float64,
    'F32': np.float32,
    'F16': np.float16,
    'BF16': ml_dtypes.bfloat16,
    'I64': np.int64,
    'I32': np.int32,
}


def resolve_weights_path(flag_value: str | None) -> pathlib.Path:
  """Returns where the CLIP weights are; nothing is ever downloaded.

  Args:
    flag_value: str or None, the --clip_weights flag; empty means unset.

  Returns:
    pathlib.Path of an existing file or Hugging Face model directory.

  Raises:
    ValueError: neither the flag nor the environment variable is set.
    FileNotFoundError: the path given does not exist.
  """
  if flag_value:
    path, source = flag_value, '--clip_weights'
  elif os.environ.get(ENV_VAR):
    path, source = os.environ[ENV_VAR], ENV_VAR
  else:
    raise ValueError(
        'CLIP weights are needed but none were given: pass '
        f'--clip_weights=PATH or set the environment variable {ENV_VAR}=PATH '
        "(OpenAI .pt, Hugging Face model.safetensors or a directory holding "
        'it, or a .npz from experiments/convert_clip.py). Nothing is '
        'downloaded.'
    )
  path = pathlib.Path(path).expanduser()
  if not path.exists():
    raise FileNotFoundError(f'CLIP weights {str(path)!r} (from {source}) do '
                            'not exist.')
  return path


# --------------------------------------------------------------------------
# Readers.


def _to_float32(x: np.ndarray) -> np.ndarray:
  """fp16/bf16/fp64 tensors become float32; integer buffers stay as they are."""
  x = np.asarray(x)
  if np.issubdtype(x.dtype, np.floating) or x.dtype == ml_dtypes.bfloat16:
    return x.astype(np.float32, copy=False)
  return x


class WeightsError(ValueError):
  """A weights file that cannot be read: names the file, format and fix."""


_FIX = ('pass CLIP ViT-B/32 weights (OpenAI ViT-B-32.pt, a Hugging Face '
        'model.safetensors or its folder, or a .npz from '
        'experiments/convert_clip.py)')
# Bytes read to tell what a file really holds.
_SNIFF_BYTES = 16
# A reader's own message is cut to this many characters in ours.
_REASON_CHARS = 100


def sniff(path: pathlib.Path) -> str:
  """What the file's first bytes say it is, for error messages."""
  try:
    size = path.stat().st_size
    with open(path, 'rb') as f:
      head = f.read(_SNIFF_BYTES)
  except OSError as e:
    return f'unreadable ({e.strerror})'
  if not head:
    what = 'an empty file'
  elif head.startswith(b'PK\x03\x04'):
    what = 'a zip archive (torch.save or .npz)'
  elif head[:1] == b'\x80':
    what = 'a Python pickle (old torch.save)'
  elif head.startswith(b'\x93NUMPY'):
    what = 'a .npy array'
  elif len(head) > 8 and head[8:9] == b'{':
    what = 'a safetensors file'
  elif all(32 <= c < 127 or c in b'\t\r\n' for c in head):
    what = 'text'
  else:
    what = 'binary data of no known weights format'
  return f'{what}, {size} bytes'


def _reason(e: BaseException) -> str:
  """A reader's error, in one short line, without unsafe-loading advice.

  torch's weights_only failures suggest `weights_only=False` and numpy's
  pickle refusal suggests `allow_pickle=True`: both run code from the file,
  so neither is repeated.
  """
  text = ' '.join(str(e).split())
  if 'WeightsUnpickler error:' in text:
    text = text.split('WeightsUnpickler error:', 1)[1]
    text = text.split('. ')[0].strip()
  elif 'allow_pickle' in text:
    text = 'it holds pickled Python objects, which are never loaded'
  if 'weights_only' in text or 'allow_pickle' in text or 'trust' in text:
    text = ''
  return f'{type(e).__name__}: {text[:_REASON_CHARS]}'.rstrip(': ')


def _unreadable(path: pathlib.Path, fmt: str,
                e: BaseException) -> WeightsError:
  return WeightsError(
      f'CLIP weights {path} cannot be read as {fmt} (from its extension): '
      f'{_reason(e)}; the file holds {sniff(path)}; {_FIX}.')


def _read_safetensors(path: pathlib.Path) -> dict[str, np.ndarray]:
  with safetensors.safe_open(path, framework='numpy') as f:
    dtypes = {n: f.get_slice(n).get_dtype() for n in f.keys()}
  if 'BF16' not in dtypes.values():
    return safetensors.numpy.load_file(path)
  # numpy has no bfloat16, so safetensors.numpy refuses these files; decode
  # the raw bytes with ml_dtypes' bfloat16 (a jax dependency) instead.
  out = {}
  for name, info in safetensors.deserialize(path.read_bytes()):
    if info['dtype'] not in _SAFETENSORS_DTYPES:
      raise WeightsError(f'{path}: tensor {name} has unsupported dtype '
                         f'{info["dtype"]}; {_FIX}.')
    dtype = _SAFETENSORS_DTYPES[info['dtype']]
    out[name] = np.frombuffer(info['data'], dtype).reshape(info['shape'])
  return out


def _is_torchscript(path: pathlib.Path) -> bool:
  if not zipfile.is_zipfile(path):
    return False
  with zipfile.ZipFile(path) as z:
    # TorchScript archives hold their code; torch.save archives do not.
    return any(n.endswith('/constants.pkl') for n in z.namelist())


def _read_torch(path: pathlib.Path) -> dict[str, np.ndarray]:
  """Reads a torch.save'd state dict or an OpenAI TorchScript .pt.

  A file is read with torch.load(weights_only=True), which unpickles
  tensors and plain containers only. TorchScript archives (OpenAI's CLIP
  release) are refused by weights_only=True, and are read with
  torch.jit.load instead, whose C++ reader restores tensors and TorchScript
  code without running Python pickles; only the state dict is used. Unsafe
  loading (weights_only=False) is never used nor advised.
  """
  try:
    import torch  # pylint: disable=g-import-not-at-top
  except ImportError as e:
    raise ImportError(
        f'{path} is a PyTorch checkpoint; reading it needs torch, which is '
        'not installed. Convert it on a machine that has torch with '
        f'`python experiments/convert_clip.py --src={path} --dst=clip.npz` '
        'and pass the .npz instead.'
    ) from e
  with open(path, 'rb') as f:
    head = f.read(1)
  if not zipfile.is_zipfile(path) and head != b'\x80':
    raise ValueError('neither a torch.save zip archive nor a pickle')
  if _is_torchscript(path):
    with warnings.catch_warnings():
      # OpenAI released CLIP only as TorchScript, which torch now deprecates;
      # there is no other reader for these files.
      warnings.filterwarnings(
          'ignore', message='.*torch.jit.load.*', category=DeprecationWarning
      )
      state = torch.jit.load(str(path), map_location='cpu').state_dict()
  else:
    state = torch.load(str(path), map_location='cpu', weights_only=True)
    if isinstance(state, Mapping) and isinstance(state.get('state_dict'),
                                                 Mapping):
      state = state['state_dict']
  if not isinstance(state, Mapping) or not all(
      isinstance(t, torch.Tensor) for t in state.values()):
    raise WeightsError(f'CLIP weights {path} hold a {type(state).__name__} '
                       f'that is not a name -> tensor mapping; {_FIX}.')
  out = {}
  for name, tensor in state.items():
    tensor = tensor.detach().cpu()
    if tensor.is_floating_point():
      tensor = tensor.float()  # also bf16, which numpy cannot hold
    out[name] = tensor.numpy()
  return out


def _read_npz(path: pathlib.Path) -> dict[str, np.ndarray]:
  if not zipfile.is_zipfile(path):
    # np.load would try it as a pickle and talk about allow_pickle.
    raise ValueError('not a zip archive, as every .npz is')
  with np.load(path, allow_pickle=False) as f:
    return {name: f[name] for name in f.files}


# Reader and format name per file extension.
_READERS = {
    '.safetensors': (_read_safetensors, 'safetensors'),
    '.pt': (_read_torch, 'a PyTorch checkpoint'),
    '.pth': (_read_torch, 'a PyTorch checkpoint'),
    '.bin': (_read_torch, 'a PyTorch checkpoint'),
    '.npz': (_read_npz, 'a numpy .npz'),
}


def read_tensors(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """Reads every tensor of a checkpoint file into numpy, floats as float32.

  Args:
    path: .pt/.pth/.bin (torch), .safetensors, a Hugging Face model directory
      holding model.safetensors, or .npz.

  Returns:
    name -> numpy array, in the file's own naming.

  Raises:
    FileNotFoundError: the file (or the folder's model.safetensors) is
      missing.
    WeightsError: any reader error, re-raised naming the file, the format
      its extension selects, what its bytes look like, and the fix.
  """
  path = pathlib.Path(path)
  if path.is_dir():
    path = path / 'model.safetensors'
    if not path.exists():
      raise FileNotFoundError(f'{path.parent} holds no model.safetensors; '
                              f'{_FIX}.')
  suffix = path.suffix.lower()
  if suffix not in _READERS:
    raise WeightsError(
        f'{path}: unknown CLIP checkpoint type {suffix!r}; expected .pt, '
        '.pth, .bin, .safetensors or .npz.'
    )
  reader, fmt = _READERS[suffix]
  if not path.is_file():
    raise FileNotFoundError(f'CLIP weights {path} do not exist; {_FIX}.')
  try:
    tensors = reader(path)
  except (WeightsError, ImportError):
    raise
  except Exception as e:  # pylint: disable=broad-except
    # safetensors, torch's unpicklers, zipfile and numpy raise many types
    # (SafetensorError, UnpicklingError, RuntimeError, BadZipFile, ...);
    # each means the file is not what its extension says.
    raise _unreadable(path, fmt, e) from e
  return {name: _to_float32(x) for name, x in tensors.items()}


# --------------------------------------------------------------------------
# Entry points.


def _config_from_npz(tensors: Mapping[str, np.ndarray]) -> model.ClipConfig:
  fields = json.loads(str(tensors[CONFIG_KEY]))
  return model.ClipConfig(**fields)


def params_from_tensors(
    tensors: Mapping[str, np.ndarray],
    variant: str | model.ClipConfig | None = None,
    source: str = 'checkpoint',
) -> tuple[model.ClipConfig, dict]:
  """Checks and converts tensors of any supported layout.

  Args:
    tensors: name -> array in OpenAI, Hugging Face or our '/'-keyed naming.
    variant: name in model.VARIANTS, a ClipConfig, or None to infer it.
    source: str, the file, for messages.

  Returns:
    (config, params): the model's shapes and its parameter tree of float32
    jax arrays.

  Raises:
    ValueError: listing every missing, mis-shaped or unexpected tensor, or
      when the variant cannot be inferred or differs from the requested one.
  """
  shapes = {name: tuple(np.shape(x)) for name, x in tensors.items()}
  if CONFIG_KEY in tensors:  # ours
    config = _config_from_npz(tensors)
    if variant is not None and model.get_config(variant) != config:
      raise ValueError(f'{source} holds {config}, not the requested '
                       f'{model.get_config(variant)}.')
    shapes.pop(CONFIG_KEY)
    layouts.check_tensors(shapes, layouts.flat_shapes(config), source=source)
    flat = {n: x for n, x in tensors.items() if n != CONFIG_KEY}
  else:
    layout = layouts.detect_layout(shapes, source)
    if variant is None:
      config = layouts.infer_config(shapes, source)
    else:
      config = model.get_config(variant)
    layouts.check_tensors(shapes, layout.expected(config), layout.harmless,
                          f'{source} ({layout.name} names)')
    if layout is layouts.HF:
      tensors = layouts.hf_to_openai(tensors, config)
    flat = layouts.openai_to_flat(tensors, config)
  # The expected-name tables and the converters are written separately;
  # this catches them drifting apart from the flax modules.
  assert {n: x.shape for n, x in flat.items()} == layouts.flat_shapes(config)
  params = traverse_util.unflatten_dict(
      {tuple(n.split('/')): np.asarray(x, np.float32) for n, x in flat.items()}
  )
  # On device once, so jitted encoders do not copy them on every call.
  return config, jax.device_put(params)


def load(
    path: str | os.PathLike, variant: str | model.ClipConfig | None = None
) -> tuple[model.ClipConfig, dict]:
  """Loads CLIP weights from a file; see read_tensors and params_from_tensors.

  Args:
    path: checkpoint file or Hugging Face model directory.
    variant: name in model.VARIANTS, a ClipConfig, or None to infer it.

  Returns:
    (config, params), params a nested dict of float32 jax arrays.
  """
  return params_from_tensors(read_tensors(path), variant, str(path))


def save_npz(
    path: str | os.PathLike, config: model.ClipConfig, params: dict
) -> None:
  """Writes params as a flat '/'-keyed .npz, atomically.

  Args:
    path: destination; it is replaced only once the file is complete.
    config: the model's shapes, stored as JSON under CONFIG_KEY.
    params: parameter tree of Clip(config).
  """
  path = pathlib.Path(path)
  flat = traverse_util.flatten_dict(jax.device_get(params), sep='/')
  arrays = {name: np.asarray(x, np.float32) for name, x in flat.items()}
  arrays[CONFIG_KEY] = np.asarray(json.dumps(dataclasses.asdict(config)))
  # A temporary file in the same directory, so os.replace is a rename on one
  # file system and readers never see a half-written file.
  fd, tmp = tempfile.mkstemp(dir=path.parent, suffix='.tmp.npz')
  try:
    with os.fdopen(fd, 'wb') as f:
      np.savez(f, **arrays)
    os.chmod(tmp, 0o644)  # mkstemp makes it owner-only
    os.replace(tmp, path)
  except BaseException:
    os.unlink(tmp)
    raise
