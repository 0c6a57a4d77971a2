"""Config files to a checked Config, and back.

`check` turns a config file's ConfigDict (configs/*.py with command-line
overrides) into a `config.Config` and checks it (config.check, and that
the scene exists) before any scene or weights load. `load_file` and
`named` read config files; `to_config_dict` and `from_dict` convert (a
saved run's dict under the names it was written with: config.migrate).
"""

import dataclasses
import importlib.util
import os
import types
import typing

from absl import app
import ml_collections

from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib


def from_dict(d: dict) -> config_lib.Config:
  """Inverse of `config.to_dict`, also of the dicts of older runs
  (config.migrate); unknown keys raise (no silent typos)."""
  return _build(config_lib.Config, config_lib.migrate(d), "")


# The checkout's config files (configs/ next to the package), found when
# the package is imported from the checkout (python -m pytest, PYTHONPATH)
# or installed editable; scripts pass config files by path.
CONFIGS_DIR = os.path.join(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__))), "configs")
# ConfigDict keys that the builder consumes instead of storing:
# semantic.scale_schedule scales the paper's semantic and residual-map
# schedules to train.steps (Config.scaled_to), for short runs.
SCALE_SCHEDULE = "scale_schedule"


def _field_value(default, value, key: str):
  """`value` in the type of the field whose default is `default`."""
  if isinstance(default, tuple):
    if isinstance(value, str):
      # "a,b" in a config file or dict; "" is ().
      value = [v for v in value.split(",") if v]
    return tuple(value)
  if isinstance(default, bool) or default is None:
    return value
  if isinstance(default, float) and isinstance(value, int):
    return float(value)
  if not isinstance(value, type(default)):
    raise ValueError(f"config: {key}={value!r} must be of type "
                     f"{type(default).__name__} (the default is {default!r}).")
  return value


def _optional_str(cls, name: str) -> bool:
  hint = typing.get_type_hints(cls)[name]
  return isinstance(hint, types.UnionType) and str in hint.__args__


def _build(cls, values, prefix: str):
  """cls(**values) with nested dataclasses; unknown keys raise, by name."""
  fields = {f.name for f in dataclasses.fields(cls)}
  unknown = sorted(set(values) - fields)
  if unknown:
    key = prefix + unknown[0]
    if key in config_lib.RENAMED:
      raise ValueError(f"config: {key} is now {config_lib.RENAMED[key]}; "
                       "rename it in the config file.")
    raise ValueError(f"config: unknown key {key} (a {cls.__name__} has "
                     f"{', '.join(sorted(fields))}).")
  kwargs = {}
  for name, value in values.items():
    default = getattr(cls(), name)
    key = prefix + name
    if dataclasses.is_dataclass(default):
      if not isinstance(value, dict):
        raise ValueError(f"config: {key} must be a section, got {value!r}.")
      value = _build(type(default), value, key + ".")
    elif value is None and not _optional_str(cls, name):
      raise ValueError(f"config: {key} is not set; give it a value.")
    elif value is not None:
      value = _field_value(default, value, key)
    kwargs[name] = value
  return cls(**kwargs)


def from_config_dict(cd: ml_collections.ConfigDict, *,
                     auto_steps: int = config_lib.TrainConfig.steps
                     ) -> config_lib.Config:
  """The frozen Config that a config file (ConfigDict) describes, unchecked.

  Every key must be a Config field of the field's type (unknown keys and
  wrong types raise ValueError, named), except semantic.scale_schedule
  (see SCALE_SCHEDULE). train.steps None means `auto_steps`;
  eval.curve_points > 0 sets train.eval_every. The values are checked by
  `check`, which calls this.

  Args:
    cd: the ConfigDict (configs/*.py get_config(), with overrides).
    auto_steps: int, the steps of a config whose train.steps is None.
  Returns:
    Config.
  """
  values = cd.to_dict() if isinstance(cd, ml_collections.ConfigDict) else (
      dict(cd))
  sem = dict(values.get("semantic", {}))
  scale = bool(sem.pop(SCALE_SCHEDULE, False))
  train = dict(values.get("train", {}))
  if train.get("steps", 0) is None:
    train["steps"] = auto_steps
  cfg = _build(config_lib.Config, dict(values, semantic=sem, train=train), "")
  t = cfg.train
  if cfg.eval.curve_points > 0:
    t = dataclasses.replace(
        t, eval_every=max(1, t.steps // cfg.eval.curve_points))
  cfg = dataclasses.replace(cfg, train=t)
  return cfg.scaled_to(t.steps) if scale else cfg


def check(values: dict | ml_collections.ConfigDict) -> config_lib.Config:
  """The checked Config of one run.

  Runs before any scene or weights are read (only the scene's existence
  is): keys and types (`from_config_dict`), then every value
  (config.check, each section's checks beside its fields). train.steps
  None means default_scene.TRAIN_STEPS on the embedded scene (data.scene
  None) and TrainConfig's 30k on a scene folder. data.scene becomes an
  absolute path, so that --resume from another folder matches.

  Args:
    values: a config file's ConfigDict (with overrides), or its dict.
  Returns:
    Config.
  Raises:
    app.UsageError: a bad key or value; the line names it as
      --config.SECTION.FIELD and says the fix.
    FileNotFoundError: data.scene is neither a folder nor a pack file.
  """
  if isinstance(values, ml_collections.ConfigDict):
    values = values.to_dict()
  embedded = (values.get("data") or {}).get("scene") is None
  auto = default_scene.TRAIN_STEPS if embedded else config_lib.TrainConfig.steps
  try:
    cfg = from_config_dict(values, auto_steps=auto)
  except ValueError as e:
    raise app.UsageError(str(e)) from e
  config_lib.check(cfg)
  data = cfg.data
  if data.scene is None:
    return cfg
  if data.scene.endswith(scene_lib.PACK_SUFFIX):
    cli.require_file("scene", data.scene)
  else:
    cli.require_folder("scene", data.scene)
  return dataclasses.replace(cfg, data=dataclasses.replace(
      data, scene=os.path.abspath(data.scene)))


def to_config_dict(cfg: config_lib.Config) -> ml_collections.ConfigDict:
  """A ConfigDict of `cfg` with every field, for config files to edit.

  data.scene is a string placeholder (None: the embedded scene), so that a
  command line can set it; semantic.scale_schedule starts False.
  """
  cd = ml_collections.ConfigDict(config_lib.to_dict(cfg))
  cd.data.scene = ml_collections.config_dict.placeholder(str)
  if cfg.data.scene is not None:
    cd.data.scene = cfg.data.scene
  cd.semantic[SCALE_SCHEDULE] = False
  return cd


def load_file(path: str) -> ml_collections.ConfigDict:
  """get_config() of the config file at `path` (as --config=path loads it).

  Raises:
    FileNotFoundError: no such file.
    ValueError: the file has no get_config().
  """
  path = os.fspath(path)
  if not os.path.isfile(path):
    raise FileNotFoundError(f"config file {path} does not exist; pass a "
                            f"file such as {CONFIGS_DIR}/default.py")
  name = "clipgs_config_" + os.path.splitext(os.path.basename(path))[0]
  spec = importlib.util.spec_from_file_location(name, path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  if not hasattr(module, "get_config"):
    raise ValueError(f"config file {path} defines no get_config(); add one "
                     "that returns an ml_collections.ConfigDict")
  return module.get_config()


def named(name: str) -> config_lib.Config:
  """The Config of the checkout's configs/<name>.py, e.g. named("smoke")
  (one run's config; a config with train.steps None gets 30k steps)."""
  return from_config_dict(load_file(os.path.join(CONFIGS_DIR, name + ".py")))
