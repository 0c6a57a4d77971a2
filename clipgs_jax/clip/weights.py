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
      raise ValueError(f'{path}: tensor {name} has unsupported dtype '
                       f'{info["dtype"]}.')
    dtype = _SAFETENSORS_DTYPES[info['dtype']]
    out[name] = np.frombuffer(info['data'], dtype).reshape(info['shape'])
  return out


def _read_torch(path: pathlib.Path) -> dict[str, np.ndarray]:
  """Reads an OpenAI TorchScript .pt or a torch.save'd state dict."""
  try:
    import torch  # pylint: disable=g-import-not-at-top
  except ImportError as e:
    raise ImportError(
        f'{path} is a PyTorch checkpoint; reading it needs torch, which is '
        'not installed. Convert it on a machine that has torch with '
        f'`python experiments/convert_clip.py --src={path} --dst=clip.npz` '
        'and pass the .npz instead.'
    ) from e
  is_script = False
  if zipfile.is_zipfile(path):
    with zipfile.ZipFile(path) as z:
      # TorchScript archives hold their code; torch.save archives do not.
      is_script = any(n.endswith('/constants.pkl') for n in z.namelist())
  if is_script:
    with warnings.catch_warnings():
      # OpenAI released CLIP only as TorchScript, which torch now deprecates;
      # there is no other reader for these files.
      warnings.filterwarnings(
          'ignore', message='.*torch.jit.load.*', category=DeprecationWarning
      )
      state = torch.jit.load(str(path), map_location='cpu').state_dict()
  else:
    state = torch.load(str(path), map_location='cpu', weights_only=True)
    if 'state_dict' in state and isinstance(state['state_dict'], Mapping):
      state = state['state_dict']
  out = {}
  for name, tensor in state.items():
    tensor = tensor.detach().cpu()
    if tensor.is_floating_point():
      tensor = tensor.float()  # also bf16, which numpy cannot hold
    out[name] = tensor.numpy()
  return out


def read_tensors(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """Reads every tensor of a checkpoint file into numpy, floats as float32.

  Args:
    path: .pt/.pth/.bin (torch), .safetensors, a Hugging Face model directory
      holding model.safetensors, or .npz.

  Returns:
    name -> numpy array, in the file's own naming.
  """
  path = pathlib.Path(path)
  if path.is_dir():
    path = path / 'model.safetensors'
    if not path.exists():
      raise FileNotFoundError(f'{path.parent} holds no model.safetensors.')
  suffix = path.suffix.lower()
  if suffix == '.safetensors':
    tensors = _read_safetensors(path)
  elif suffix in ('.pt', '.pth', '.bin'):
    tensors = _read_torch(path)
  elif suffix == '.npz':
    with np.load(path, allow_pickle=False) as f:
      tensors = {name: f[name] for name in f.files}
  else:
    raise ValueError(
        f'{path}: unknown CLIP checkpoint type {suffix!r}; expected .pt, '
        '.pth, .bin, .safetensors or .npz.'
    )
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
