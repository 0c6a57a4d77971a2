"""TrainState checkpoints as flat '/'-keyed .npz files, written atomically.

Layout: every leaf of the state under "state/<path>" (e.g.
"state/params/means", "state/opt_state/inner_states/means/inner_state/0/mu/
means"); the PRNG key as its raw key data; "meta/config" (the resolved
config as JSON), "meta/extra" (JSON: the loop's curve and timers),
"meta/version", and host records that are arrays under "arrays/<name>" (the
rows semantic prunes removed). No pickles: the file loads with
allow_pickle=False.
"""

import json
import os
from typing import Any
import zipfile
import zlib

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import config as config_lib
from clipgs_jax import fileio
from clipgs_jax import state as state_lib

# 2: SemanticStats gained `weight` (contribution-weighted s_j normaliser).
VERSION = 2
STATE_PREFIX = "state/"
ARRAYS_PREFIX = "arrays/"


# What np.load and NpzFile raise on a file that is not a whole .npz.
_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile,
                zlib.error)


class CheckpointError(ValueError):
  """A checkpoint that cannot be used; the message names the file and fix."""


def _key_name(entry) -> str:
  for attr in ("name", "key", "idx"):
    if hasattr(entry, attr):
      return str(getattr(entry, attr))
  raise TypeError(f"checkpoint: unsupported pytree path entry {entry!r}.")


def _is_prng_key(x) -> bool:
  return isinstance(x, jax.Array) and jnp.issubdtype(x.dtype,
                                                      jax.dtypes.prng_key)


def flatten(tree) -> dict[str, Any]:
  """{'/'-joined path: leaf} of a pytree."""
  leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
  return {"/".join(_key_name(e) for e in path): leaf for path, leaf in leaves}


def save(path: str, state: state_lib.TrainState, cfg: config_lib.Config,
         extra: dict | None = None,
         records: dict[str, np.ndarray] | None = None) -> None:
  """Writes `state`, the config, `extra` (JSON) and `records` (arrays,
  under ARRAYS_PREFIX + name) to `path`."""
  arrays = {ARRAYS_PREFIX + k: np.asarray(v)
            for k, v in (records or {}).items()}
  for name, leaf in flatten(jax.device_get(state)).items():
    if _is_prng_key(leaf):
      leaf = jax.random.key_data(leaf)
    arrays[STATE_PREFIX + name] = np.asarray(leaf)
  arrays["meta/config"] = np.asarray(json.dumps(config_lib.to_dict(cfg)))
  arrays["meta/extra"] = np.asarray(json.dumps(extra or {}))
  arrays["meta/version"] = np.asarray(VERSION, np.int32)

  def write(tmp):
    with open(tmp, "wb") as f:
      np.savez(f, **arrays)
      f.flush()
      os.fsync(f.fileno())
  fileio.atomic_write(path, write, ".npz")


def _unreadable(path: str, e: BaseException) -> CheckpointError:
  reason = " ".join(str(e).split())[:120] or type(e).__name__
  return CheckpointError(
      f"checkpoint {path} is unreadable ({type(e).__name__}: {reason}); it "
      "was cut short or is not a clipgs_jax checkpoint: delete it (or use a "
      "new workdir) to start over")


def _read(path: str, fn):
  """fn(NpzFile) on the checkpoint at `path`; read errors name the file."""
  if not os.path.exists(path):
    raise FileNotFoundError(f"checkpoint {path} does not exist; check the "
                            "workdir, or run without resume to start over.")
  try:
    # Our own file object: np.load leaves a path it opened open when the
    # file is not a zip.
    with open(path, "rb") as f, np.load(f, allow_pickle=False) as data:
      return fn(data)
  except CheckpointError:
    raise
  except FileNotFoundError:
    raise
  except _READ_ERRORS as e:
    raise _unreadable(path, e) from e


def read_arrays(path: str, *prefixes: str) -> dict[str, np.ndarray]:
  """{name: array} of the entries whose names start with one of
  `prefixes`, e.g. STATE_PREFIX + "params/" (the Gaussians) or
  ARRAYS_PREFIX; loads only those entries and needs no template."""
  return _read(path, lambda data: {k: data[k] for k in data.files
                                   if k.startswith(prefixes)})


def read_meta(path: str) -> dict[str, Any]:
  """{"config": dict, "extra": dict, "version": int} of a checkpoint."""
  return _read(path, lambda data: _meta(data, path))


def _meta(data, path) -> dict[str, Any]:
  for key in ("meta/config", "meta/extra", "meta/version"):
    if key not in data:
      raise CheckpointError(f"checkpoint: {path} has no {key}; it is not a "
                            "clipgs_jax checkpoint: delete it or use a new "
                            "workdir.")
  return {"config": json.loads(str(data["meta/config"])),
          "extra": json.loads(str(data["meta/extra"])),
          "version": int(data["meta/version"])}


def config_differences(a: dict, b: dict, prefix: str = "") -> list[str]:
  """'field: a -> b' for every leaf where two nested dicts differ."""
  out = []
  for k in sorted(set(a) | set(b)):
    x, y = a.get(k), b.get(k)
    if isinstance(x, dict) and isinstance(y, dict):
      out += config_differences(x, y, f"{prefix}{k}.")
    elif x != y:
      out.append(f"{prefix}{k}: {x} -> {y}")
  return out


def check_resumable(path: str, cfg: config_lib.Config) -> None:
  """Raises CheckpointError unless `cfg` can continue the run at `path`.

  Reads only the metadata, so a script can check before it creates or
  writes anything.
  """
  meta = read_meta(path)
  saved = json.loads(json.dumps(config_lib.migrate(meta["config"])))
  wanted = json.loads(json.dumps(config_lib.to_dict(cfg)))
  if saved != wanted:
    diff = config_differences(saved, wanted)
    more = f" and {len(diff) - 3} more" if len(diff) > 3 else ""
    raise CheckpointError(
        f"{path} was written with a different config ({'; '.join(diff[:3])}"
        f"{more}); resume with the flags that wrote it, or use a new workdir "
        "to start over.")


def restore(path: str, template: state_lib.TrainState
            ) -> tuple[state_lib.TrainState, dict[str, Any]]:
  """Loads a checkpoint into the structure of `template`.

  The template gives the pytree structure; a template of another capacity
  is resized first (state.resize), since capacity grows during training.
  Every leaf must be present with the template's dtype and shape.

  Returns:
    (state, meta) with meta as in `read_meta`.
  """
  return _read(path, lambda data: _restore(data, path, template))


def _restore(data, path, template):
  """`restore` on an open NpzFile."""
  meta = _meta(data, path)
  if meta["version"] != VERSION:
    raise CheckpointError(f"checkpoint: {path} has format version "
                          f"{meta['version']}, this code reads {VERSION}; "
                          "start over in a new workdir.")
  capacity = data[STATE_PREFIX + "alive"].shape[0]
  if template.alive.shape[0] != capacity:
    template = state_lib.resize(template, capacity)
  names = flatten(template)
  missing = [n for n in names if STATE_PREFIX + n not in data]
  if missing:
    raise CheckpointError(f"checkpoint: {path} lacks {missing[:3]}; it was "
                          "written for a different config or code version.")
  leaves = []
  for name, like in names.items():
    value = data[STATE_PREFIX + name]
    if _is_prng_key(like):
      expected = jax.random.key_data(like)
      if value.shape != expected.shape or value.dtype != expected.dtype:
        raise CheckpointError(f"checkpoint: {path} key data has shape "
                              f"{value.shape}, expected {expected.shape}.")
      leaves.append(jax.random.wrap_key_data(
          value, impl=jax.random.key_impl(like)))
      continue
    like_dtype = jnp.result_type(like)
    if value.shape != np.shape(like) or value.dtype != like_dtype:
      raise CheckpointError(f"checkpoint: {path} entry {name} is "
                            f"{value.dtype} {value.shape}, expected "
                            f"{like_dtype} {np.shape(like)}.")
    leaves.append(jnp.asarray(value))
  state = jax.tree.unflatten(jax.tree.structure(template), leaves)
  return state, meta
