"""Config files to a checked Config, and back.

`check` turns a config file's ConfigDict (configs/*.py with command-line
overrides) into a `config.Config` and is the one place where a run's
config is checked, before any scene or weights load. `load_file` and
`named` read config files; `to_config_dict` and `from_dict` convert.
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
from clipgs_jax import features
from clipgs_jax import metrics as metrics_lib
from clipgs_jax import residual
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib


def from_dict(d: dict) -> config_lib.Config:
  """Inverse of `config.to_dict`; unknown keys raise (no silent typos)."""
  return _build(config_lib.Config, d, "")


# The checkout's config files (configs/ next to the package), found when
# the package is imported from the checkout (python -m pytest, PYTHONPATH)
# or installed editable; scripts pass config files by path.
CONFIGS_DIR = os.path.join(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__))), "configs")
# ConfigDict keys that the builder consumes instead of storing:
# semantic.scale_schedule scales the paper's semantic schedule to
# train.steps (SemanticConfig.scaled_to), for short runs.
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
    raise ValueError(f"config: unknown key {prefix}{unknown[0]} (a "
                     f"{cls.__name__} has {', '.join(sorted(fields))}).")
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
  sem = cfg.semantic.scaled_to(t.steps) if scale else cfg.semantic
  return dataclasses.replace(cfg, train=t, semantic=sem)


def _positive(ok: bool, key: str, value, fix: str) -> None:
  if not ok:
    raise app.UsageError(f"--config.{key}={value} {fix}")


def _semantic_problems(sem: config_lib.SemanticConfig) -> list[str]:
  """What makes a SemanticConfig unable to run, one phrase per field."""
  problems = []
  if sem.scorer not in config_lib.SCORERS:
    problems.append(f"scorer={sem.scorer!r} is not one of "
                    f"{', '.join(config_lib.SCORERS)}")
  if sem.evidence not in config_lib.EVIDENCES:
    problems.append(f"evidence={sem.evidence!r} is not one of "
                    f"{', '.join(config_lib.EVIDENCES)}")
  if sem.scorer == "clip" and not sem.distractor_prompts:
    problems.append("scorer='clip' has no distractor prompts; give some "
                    "(e.g. the paper's) or use scorer='off' for vanilla 3DGS")
  if (sem.scorer == "clip" and sem.evidence == "pixel"
      and not sem.static_prompts):
    problems.append("scorer='clip' with evidence='pixel' needs static "
                    "prompts: p(distractor) is a softmax over D and S, which "
                    "is identically 1 without S")
  if not 0.0 <= sem.prune_harm <= 1.0:
    problems.append(f"prune_harm={sem.prune_harm} is not in [0, 1]")
  if not 0.0 <= sem.tau_p <= 1.0:
    problems.append(f"tau_p={sem.tau_p} is not in [0, 1]")
  if not 0.0 < sem.max_prune_fraction <= 1.0:
    problems.append(f"max_prune_fraction={sem.max_prune_fraction} is not in "
                    "(0, 1] (1.0 lifts the guard)")
  if sem.scorer == "uniform" and sem.evidence != "pixel":
    problems.append("scorer='uniform' is a per-pixel control map; it needs "
                    "evidence='pixel'")
  problems += _residual_problems(sem)
  if sem.loss_masking and sem.evidence != "pixel":
    problems.append("loss_masking needs evidence='pixel' (a per-pixel map)")
  if sem.dense_input_size <= 0:
    problems.append(f"dense_input_size={sem.dense_input_size} must be a "
                    "positive multiple of the ViT's patch size")
  if sem.weighting not in config_lib.WEIGHTINGS:
    problems.append(f"weighting={sem.weighting!r} is not one of "
                    f"{', '.join(config_lib.WEIGHTINGS)}")
  if not 0.0 <= sem.tau <= 1.0:
    problems.append(f"tau={sem.tau} is not in [0, 1]")
  if not sem.beta > 0:
    problems.append(f"beta={sem.beta} must be positive")
  if not sem.lambda_c >= 0:
    problems.append(f"lambda_c={sem.lambda_c} must be >= 0")
  if (sem.enabled and sem.lambda_c == 0 and not sem.prune
      and not sem.loss_masking):
    problems.append("lambda_c=0 with prune and loss_masking off leaves "
                    "guidance nothing to do; use scorer='off' for vanilla "
                    "3DGS")
  for name in ("accumulate_start", "reg_start", "prune_start",
               "reset_quiet", "residual_start", "residual_uniform_until"):
    if getattr(sem, name) < 0:
      problems.append(f"{name}={getattr(sem, name)} must be >= 0")
  for name in ("prune_every", "score_every"):
    if getattr(sem, name) < 1:
      problems.append(f"{name}={getattr(sem, name)} must be >= 1")
  if not 0.0 < sem.oracle_saturation <= 1.0:
    problems.append(f"oracle_saturation={sem.oracle_saturation} is not in "
                    "(0, 1]")
  if any(not p.strip() for p in sem.distractor_prompts + sem.static_prompts):
    problems.append("a prompt is empty")
  return problems


def _residual_problems(sem: config_lib.SemanticConfig) -> list[str]:
  """What makes the residual map's settings unable to run."""
  problems = []
  if sem.scorer in ("residual", "oracle_patch") and sem.evidence != "pixel":
    problems.append(f"scorer={sem.scorer!r} is a per-pixel map; it needs "
                    "evidence='pixel'")
  if sem.residual and (sem.scorer not in ("clip", "oracle_patch")
                       or sem.evidence != "pixel"):
    problems.append("residual=True combines the residual map with a "
                    "semantic map: it needs scorer='clip' or 'oracle_patch' "
                    "and evidence='pixel' (scorer='residual' is the residual "
                    "map alone)")
  if sem.features and sem.features not in features.NETS:
    problems.append(f"features={sem.features!r} is not one of "
                    f"{', '.join(sorted(features.NETS))} (or '' for none)")
  if sem.features and not sem.uses_residual:
    problems.append("features votes the residual test over regions: it "
                    "needs scorer='residual' or residual=True")
  if not 0.0 <= sem.residual_min_share < 1.0:
    problems.append(f"residual_min_share={sem.residual_min_share} is not "
                    "in [0, 1)")
  if not 0.0 < sem.residual_vote <= 1.0:
    problems.append(f"residual_vote={sem.residual_vote} is not in (0, 1]")
  if not sem.residual_uniformity >= 0:
    problems.append(f"residual_uniformity={sem.residual_uniformity} must "
                    "be >= 0 (0: no gate)")
  if sem.residual_rule not in residual.RULES:
    problems.append(f"residual_rule={sem.residual_rule!r} is not one of "
                    f"{', '.join(residual.RULES)}")
  if not 0.0 < sem.residual_quantile < 1.0:
    problems.append(f"residual_quantile={sem.residual_quantile} is not in "
                    "(0, 1)")
  if not 0.0 <= sem.residual_decay < 1.0:
    problems.append(f"residual_decay={sem.residual_decay} is not in [0, 1)")
  if not sem.residual_median_factor >= 0:
    problems.append(f"residual_median_factor={sem.residual_median_factor} "
                    "must be >= 0")
  if not 0.0 <= sem.residual_min_threshold < 1.0:
    problems.append(f"residual_min_threshold={sem.residual_min_threshold} "
                    "is not in [0, 1)")
  if not 0.0 <= sem.residual_min_alpha < 1.0:
    problems.append(f"residual_min_alpha={sem.residual_min_alpha} is not in "
                    "[0, 1)")
  if not sem.residual_warmup >= 0:
    problems.append(f"residual_warmup={sem.residual_warmup} must be >= 0")
  return problems


def check(values: dict | ml_collections.ConfigDict) -> config_lib.Config:
  """The checked Config of one run: every config check, in one place.

  Runs before any scene or weights are read (only the scene's existence
  is): keys and types (`from_config_dict`), then every value. train.steps
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
  t = cfg.train
  _positive(t.steps > 0, "train.steps", t.steps, "must be positive")
  _positive(t.batch_size >= 1, "train.batch_size", t.batch_size,
            "must be positive (1: one view per step)")
  _positive(t.checkpoint_every >= 0, "train.checkpoint_every",
            t.checkpoint_every, "must be >= 0 (0: only at the end)")
  _positive(cfg.render.tile_budget > 0, "render.tile_budget",
            cfg.render.tile_budget, "must be positive; raise it when the "
            "log warns that tile-list entries were dropped")
  _positive(cfg.data.downscale >= 1, "data.downscale", cfg.data.downscale,
            "must be a positive integer (1: full size)")
  _positive(cfg.eval.curve_points >= 0, "eval.curve_points",
            cfg.eval.curve_points, "must be >= 0 (0: keep train.eval_every)")
  problems = _semantic_problems(cfg.semantic)
  if problems:
    raise app.UsageError("--config.semantic: SemanticConfig: "
                         + "; ".join(problems) + ".")
  data, ev = cfg.data, cfg.eval
  cli.require(data.train_split in scene_lib.TRAIN_SPLITS,
              "config.data.train_split", data.train_split,
              f"is not one of {', '.join(scene_lib.TRAIN_SPLITS)}")
  nets = metrics_lib.LPIPS_NETS
  cli.require(ev.lpips_net in nets, "config.eval.lpips_net", ev.lpips_net,
              f"is not one of {', '.join(nets)}")
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
