"""Timings, one JSON line per result: rasterizer, step, clip, semantic,
features, views or peers.

  python experiments/bench.py --bench=rasterizer [--num_gaussians=10000
      --sizes=256x256]
  python experiments/bench.py --bench=step --bench_scene=DIR
      [--num_gaussians=0,220000]
  python experiments/bench.py --bench=clip --clip_variant=ViT-B/32
      --batch_sizes=1,8 [--noencoders --scorers --dense_input_sizes=224,448]
  python experiments/bench.py --bench=semantic [--timed_steps=40
      --checkpoint=RUN/checkpoint.npz --score_every=1,10,20]
  python experiments/bench.py --bench=features --bench_scene=DIR
      [--bench_downscale=8 --repeats=21]
  python experiments/bench.py --bench=views --bench_scene=DIR
      [--bench_downscale=4 --batch_devices=1x1,2x1,4x1,2x2,4x2 --host_devices=2
       --device_lanes=auto|scan|vmap]
  python experiments/bench.py --bench=peers --bench_scene=DIR --peers=PEERS
      --out=OUT [--bench_downscale=8 --train_steps=7000 --train_seed=0]

What each --bench times, and every field, is documented by the lab
function it calls: clipgs_jax/lab/timing.py (rasterizer, step, semantic),
clip_timing.py (clip), features.py (features),
batch_timing.py (views: B views a step on D devices), peers.py (peers).
"""

import json

from absl import flags
import jax

from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax.clip import dense
from clipgs_jax.clip import model
from clipgs_jax.clip import scorer
from clipgs_jax.data import default_scene
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.lab import batch_timing
from clipgs_jax.lab import clip_timing
from clipgs_jax.lab import peers
from clipgs_jax.lab import timing
from clipgs_jax.maps import features

# Per benchmark defaults of the shared flags (None on the command line).
DEFAULTS = {
    "rasterizer": dict(num_gaussians=["1000", "10000", "100000"],
                       repeats=5, tile_budget=0),
    # 220k: about where a bird ds4 7k-step run ends (BUILD_NOTES.md,
    # "Long runs": 223k at 5950).
    "step": dict(num_gaussians=["0", "220000"], repeats=3, tile_budget=8192,
                 bench_downscale=4),
    "clip": dict(repeats=10),
    "semantic": dict(tile_budget=8192, bench_downscale=1),
    "features": dict(repeats=21, bench_downscale=8),
    "views": dict(tile_budget=8192, bench_downscale=4, num_gaussians=["0"]),
    "peers": dict(bench_downscale=8),
}

_BENCH = flags.DEFINE_enum("bench", None, list(DEFAULTS), "What to time.")
_NUM = flags.DEFINE_list("num_gaussians", None, "rasterizer: scene sizes N; "
                         "step: alive counts (0 = the SfM points).")
_REPEATS = flags.DEFINE_integer("repeats", None, "Timed runs (median); "
                                "default 5 / 3 / 10 (rasterizer/step/clip).")
_TILE_BUDGET = flags.DEFINE_integer(
    "tile_budget", None, "K; rasterizer default 0 = the smallest power of "
    "two >= the longest tile list; step and semantic 8192.")
_CHUNK = flags.DEFINE_integer("chunk_size", 32, "B.")
_LANES = flags.DEFINE_integer("lanes", 0, "Blend lanes; 0 = automatic.")
_TILE_SIZE = flags.DEFINE_integer(
    "tile_size", config_lib.RenderConfig.tile_size, "Tile side, pixels.")
_SIZES = flags.DEFINE_list("sizes", ["256x256", "512x384"],
                           "rasterizer: image sizes WxH.")
_VARIANTS = flags.DEFINE_list("variants", ["custom_vjp", "autodiff"],
                              "rasterizer: custom_vjp and/or autodiff.")
_RADIUS = flags.DEFINE_list("radius_px", ["2", "20"], "rasterizer: range "
                            "of projected 3-sigma radii, pixels.")
_MAX_GIB = flags.DEFINE_float(
    "max_gib", 12.0, "rasterizer: skip a variant whose compiled forward + "
    "backward needs more memory than this (GiB).")
_SCENE = flags.DEFINE_string(
    "bench_scene", None, "step / semantic / features / views: scene folder "
    "or pack (step, features, views: required, e.g. the bird scene; "
    "semantic: default the embedded scene).")
_DOWNSCALE = flags.DEFINE_integer(
    "bench_downscale", None, "step / semantic / features / views: image "
    "downscale (default 4 / 1 / 8 / 4).")
_VIEW = flags.DEFINE_integer("view", 0, "step: training view index.")
_CHECKPOINT = flags.DEFINE_string("checkpoint", None, "step / semantic: a "
                                  "train.py checkpoint.npz of the scene.")
_CLIP_VARIANT = flags.DEFINE_enum("clip_variant", model.DEFAULT_VARIANT,
                                  list(model.VARIANTS), "clip / semantic: "
                                  "CLIP tower (random weights).")
_BATCH_SIZES = flags.DEFINE_list("batch_sizes", ["1", "8"],
                                 "clip: image batch sizes.")
_WARMUP = flags.DEFINE_integer("warmup", 2, "clip: untimed runs first.")
_RENDER_SIZE = flags.DEFINE_list("render_size", ["378", "504"], "clip: "
                                 "height,width of the render to score.")
_ENCODERS = flags.DEFINE_bool("encoders", True, "clip: time the encoders.")
_SCORERS = flags.DEFINE_bool("scorers", False, "clip: time the scorers.")
_DENSE_SIZES = flags.DEFINE_list(
    "dense_input_sizes", [str(scorer.DENSE_INPUT_SIZE)],
    "clip: dense scorer input sides (multiples of the patch size).")
_DENSE_READOUTS = flags.DEFINE_list(
    "dense_readouts", [dense.DEFAULT_READOUT],
    f"clip: dense readouts, of {dense.READOUTS}.")
_SCORE_EVERY = flags.DEFINE_list("score_every", ["1", "10", "20"],
                                 "semantic: CLIP scoring cadences.")
_TIMED_STEPS = flags.DEFINE_integer("timed_steps", 40, "semantic / views: "
                                    "timed steps per variant (semantic: a "
                                    "multiple of every --score_every).")
_BATCH_DEVICES = flags.DEFINE_list(
    "batch_devices", ["1x1", "2x1", "4x1", "2x2", "4x2"],
    "views: BxD variants, batch size B on D devices (D divides B).")
_HOST_DEVICES = flags.DEFINE_integer(
    "host_devices", 2, "views: CPU devices the host is split into (XLA's "
    "forced host devices); a GPU machine uses its GPUs.")
_DEVICE_LANES = flags.DEFINE_enum(
    "device_lanes", "auto", ["auto", "scan", "vmap"],
    "views: how a device renders its B / D lanes: auto (vmap on an "
    "accelerator, scan on a CPU: step.lanes_vmapped), or either.")
_PEERS = flags.DEFINE_string("peers", None, "peers: the folder holding "
                             "the peers' sources (../shared/bench_peers).")
_OUT = flags.DEFINE_string("out", None, "peers: output folder.")
_TRAIN_STEPS = flags.DEFINE_integer("train_steps", 7000, "peers: steps.")
_SEED = flags.DEFINE_integer("train_seed", 0, "peers: every run's seed.")
flags.mark_flag_as_required("bench")


def _radius_ok(values) -> bool:
  try:
    lo, hi = (float(x) for x in values)
  except ValueError:
    return False
  return 0 < lo <= hi


def _sizes_ok(values) -> bool:
  return all(len(v.split("x")) == 2 and all(
      s.isdigit() and int(s) > 0 for s in v.split("x")) for v in values)


flags.register_validator(
    "radius_px", _radius_ok,
    "--radius_px takes two numbers LO,HI with 0 < LO <= HI, e.g. 2,20")
flags.register_validator(
    "sizes", _sizes_ok, "--sizes takes WIDTHxHEIGHT items, e.g. 256x256")
flags.register_validator(
    "batch_devices", lambda v: _sizes_ok(v) and all(
        int(x.split("x")[0]) % int(x.split("x")[1]) == 0 for x in v),
    "--batch_devices takes BxD items with D dividing B, e.g. 4x2")


def _require_scene(what: str, why: str) -> None:
  """One line naming --bench_scene when --bench=`what` has no scene."""
  cli.require(_SCENE.value is not None, "bench_scene", _SCENE.value,
              f"is missing: --bench={what} {why}; pass a scene folder or "
              "pack, e.g. --bench_scene=DATA/bird")
  cli.require_file("bench_scene", _SCENE.value)


def _value(name: str, flag):
  return flag.value if flag.value is not None else DEFAULTS[
      _BENCH.value].get(name)


def _ints(values) -> list[int]:
  return [int(float(x)) for x in values]


def _results():
  what = _BENCH.value
  repeats = _value("repeats", _REPEATS)
  budget = _value("tile_budget", _TILE_BUDGET)
  if what == "rasterizer":
    for size in _SIZES.value:
      width, height = (int(s) for s in size.split("x"))
      for n in _ints(_value("num_gaussians", _NUM)):
        for variant in _VARIANTS.value:
          yield timing.rasterizer(
              n, width, height, variant,
              radius_px=tuple(float(r) for r in _RADIUS.value),
              tile_budget=budget, chunk_size=_CHUNK.value,
              lanes=_LANES.value, tile_size=_TILE_SIZE.value,
              repeats=repeats, max_gib=_MAX_GIB.value)
  elif what == "step":
    _require_scene("step", "times a real view")
    yield from timing.train_step(
        _SCENE.value, _value("bench_downscale", _DOWNSCALE),
        _ints(_value("num_gaussians", _NUM)), view=_VIEW.value,
        checkpoint_path=_CHECKPOINT.value, repeats=repeats,
        render=config_lib.RenderConfig(
            tile_budget=budget, chunk_size=_CHUNK.value, lanes=_LANES.value,
            tile_size=_TILE_SIZE.value))
  elif what == "clip":
    render_hw = tuple(_ints(_RENDER_SIZE.value))
    if _SCORERS.value:
      yield from clip_timing.scorers(
          _CLIP_VARIANT.value, render_hw, runs=repeats, warmup=_WARMUP.value,
          dense_input_sizes=_ints(_DENSE_SIZES.value),
          dense_readouts=_DENSE_READOUTS.value)
    if _ENCODERS.value:
      yield from clip_timing.encoders(
          _CLIP_VARIANT.value, render_hw, runs=repeats, warmup=_WARMUP.value,
          batch_sizes=_ints(_BATCH_SIZES.value))
  elif what == "features":
    _require_scene("features", "clusters real photos")
    downscale = _value("bench_downscale", _DOWNSCALE)
    photos = scene_lib.load_scene(
        _SCENE.value, downscale=downscale).train.images[:repeats]
    for benchmark in (features.benchmark, features.pixel_benchmark):
      yield dict(benchmark(photos), scene=_SCENE.value, downscale=downscale)
  elif what == "views":
    _require_scene("views", "times a real scene")
    yield from batch_timing.views_per_second(
        _SCENE.value, _value("bench_downscale", _DOWNSCALE),
        variants=[tuple(int(x) for x in v.split("x")) for v in
                  _BATCH_DEVICES.value],
        steps=_TIMED_STEPS.value,
        num_gaussians=_ints(_value("num_gaussians", _NUM))[0],
        vmap_lanes={"auto": None, "scan": False,
                    "vmap": True}[_DEVICE_LANES.value],
        render=config_lib.RenderConfig(
            tile_budget=budget, chunk_size=_CHUNK.value, lanes=_LANES.value,
            tile_size=_TILE_SIZE.value))
  elif what == "peers":
    _require_scene("peers", "trains on a real scene")
    cli.require(_PEERS.value and _OUT.value, "peers", _PEERS.value,
                "and --out are needed: the peers' folder and an output one")
    out = peers.bench(_PEERS.value, list(peers.PEERS), _SCENE.value,
                      _value("bench_downscale", _DOWNSCALE),
                      _TRAIN_STEPS.value, _SEED.value, _OUT.value)
    yield from ({"system": k, **c[-1]} for k, c in out["runs"].items())
  else:
    yield from timing.semantic_overhead(
        _SCENE.value or default_scene.ensure_default_scene(),
        _value("bench_downscale", _DOWNSCALE),
        score_every=_ints(_SCORE_EVERY.value), steps=_TIMED_STEPS.value,
        clip_variant=_CLIP_VARIANT.value, tile_budget=budget,
        checkpoint_path=_CHECKPOINT.value)


def main(argv):
  cli.no_arguments(argv)
  if _BENCH.value == "views":
    # Before anything touches a device: the CPU backend's device count.
    jax.config.update("jax_num_cpu_devices", _HOST_DEVICES.value)
  for result in _results():
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
  cli.run(main)
