"""Times the CLIP encoders on random weights; prints one JSON line per result.

  python experiments/bench_clip.py --variant=ViT-B/32 --batch_sizes=1,8
  # The view scorers as the train step calls them, image-level and dense:
  python experiments/bench_clip.py --noencoders --scorers \
      --dense_input_sizes=224,448
"""

import json
import statistics
import time

from absl import app
from absl import flags
import jax
import jax.numpy as jnp

from clipgs_jax import cli
from clipgs_jax import config as config_lib
from clipgs_jax.clip import dense
from clipgs_jax.clip import model
from clipgs_jax.clip import preprocess
from clipgs_jax.clip import scorer
from clipgs_jax.clip import tokenizer

_VARIANT = flags.DEFINE_enum(
    'variant', model.DEFAULT_VARIANT, list(model.VARIANTS), 'Model shapes.')
_BATCH_SIZES = flags.DEFINE_list(
    'batch_sizes', ['1', '8'], 'Image batch sizes to time.')
_RUNS = flags.DEFINE_integer('runs', 10, 'Timed runs per measurement.')
_WARMUP = flags.DEFINE_integer(
    'warmup', 2, 'Untimed runs after compilation, before timing.')
_RENDER_SIZE = flags.DEFINE_list(
    'render_size', ['378', '504'],
    'Height,width of the render that preprocessing resizes to 224x224.')
_SEED = flags.DEFINE_integer('seed', 0, 'Seed of the random weights.')
_ENCODERS = flags.DEFINE_bool(
    'encoders', True, 'Time encode_image/encode_text/preprocess/text cache.')
_SCORERS = flags.DEFINE_bool(
    'scorers', False,
    'Time the view scorers on one --render_size render, jitted as the train '
    'step runs them: ClipScorer.score (paper, image-level) and '
    'DenseClipScorer.score_map at each --dense_input_sizes.')
_DENSE_INPUT_SIZES = flags.DEFINE_list(
    'dense_input_sizes', [str(scorer.DENSE_INPUT_SIZE)],
    'CLIP input sides for the dense scorer (multiples of the patch size).')
_DENSE_READOUTS = flags.DEFINE_list(
    'dense_readouts', [dense.DEFAULT_READOUT],
    f'Dense readouts to time, of {dense.READOUTS}.')

# The eight prompts of the CLIP-GS paper: five distractor, three static.
PAPER_PROMPTS = (
    'a photo of a person', 'a photo of people', 'a photo of pedestrians',
    'a photo of hands', 'a photo of a balloon', 'a photo of a building',
    'a photo of a wall', 'a photo of furniture',
)


def _time_ms(fn, runs, warmup):
  """Times fn(); the first call compiles.

  Returns:
    (first call ms, median ms, min ms, median process CPU ms). CPU time sums
    all threads and is not inflated by other processes on a shared box.
  """
  start = time.perf_counter()
  jax.block_until_ready(fn())
  first = (time.perf_counter() - start) * 1e3
  for _ in range(warmup):
    jax.block_until_ready(fn())
  times, cpu_times = [], []
  for _ in range(runs):
    start, cpu_start = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn())
    times.append((time.perf_counter() - start) * 1e3)
    cpu_times.append((time.process_time() - cpu_start) * 1e3)
  return (first, statistics.median(times), min(times),
          statistics.median(cpu_times))


def _emit(**fields):
  print(json.dumps(fields), flush=True)


def _time_scorers(config, params, common):
  """Times ClipScorer.score and DenseClipScorer.score_map on one render."""
  h, w = map(int, _RENDER_SIZE.value)
  render = jax.random.uniform(jax.random.key(2), (h, w, 3))
  view = jnp.int32(0)
  sem = config_lib.SemanticConfig(scorer='clip')  # the paper's prompts
  image_level = scorer.make(sem, clip_params=(config, params))
  score = jax.jit(lambda s, im: s.score(im, view))
  first, median, best, cpu = _time_ms(lambda: score(image_level, render),
                                      _RUNS.value, _WARMUP.value)
  _emit(what='scorer_image_level', render_hw=[h, w],
        input_size=config.image_size, first_call_ms=round(first, 1),
        median_ms=round(median, 2), min_ms=round(best, 2),
        median_cpu_ms=round(cpu, 2), **common)
  score_map = jax.jit(lambda s, im: s.score_map(im, view))
  for readout in _DENSE_READOUTS.value:
    for input_size in map(int, _DENSE_INPUT_SIZES.value):
      dense_scorer = scorer.make_dense(sem, clip_params=(config, params),
                                       input_size=input_size, readout=readout)
      first, median, best, cpu = _time_ms(
          lambda: score_map(dense_scorer, render), _RUNS.value, _WARMUP.value)
      _emit(what='scorer_dense', readout=readout, render_hw=[h, w],
            input_size=input_size, grid=dense_scorer.grid,
            first_call_ms=round(first, 1), median_ms=round(median, 2),
            min_ms=round(best, 2), median_cpu_ms=round(cpu, 2), **common)


def _time_encoders(config, params, common):
  """Times the encoders, preprocessing, tokenizer and the text cache."""
  size = config.image_size

  for batch in map(int, _BATCH_SIZES.value):
    images = jax.random.normal(jax.random.key(1), (batch, size, size, 3))
    first, median, best, cpu = _time_ms(
        lambda: model.encode_image(params, images, config=config),
        _RUNS.value, _WARMUP.value)
    _emit(what='encode_image', batch=batch, first_call_ms=round(first, 1),
          median_ms=round(median, 2), min_ms=round(best, 2),
          median_ms_per_image=round(median / batch, 2),
          median_cpu_ms=round(cpu, 2), **common)

  h, w = map(int, _RENDER_SIZE.value)
  render = jax.random.uniform(jax.random.key(2), (h, w, 3))
  prep = jax.jit(preprocess.preprocess, static_argnames=('mode', 'size'))
  first, median, best, cpu = _time_ms(lambda: prep(render, size=size),
                                      _RUNS.value, _WARMUP.value)
  _emit(what='preprocess', render_hw=[h, w], first_call_ms=round(first, 1),
        median_ms=round(median, 2), min_ms=round(best, 2),
        median_cpu_ms=round(cpu, 2), **common)

  start = time.perf_counter()
  tokenizer.default_tokenizer()  # reads the merge list, once per process
  load_ms = (time.perf_counter() - start) * 1e3
  start = time.perf_counter()
  tokens = jnp.asarray(tokenizer.tokenize(PAPER_PROMPTS))
  tokenize_ms = (time.perf_counter() - start) * 1e3
  first, median, best, cpu = _time_ms(
      lambda: model.encode_text(params, tokens, config=config),
      _RUNS.value, _WARMUP.value)
  _emit(what='encode_text', prompts=len(PAPER_PROMPTS),
        tokens_per_prompt=tokens.shape[1],
        tokenizer_load_ms=round(load_ms, 1), tokenize_ms=round(tokenize_ms, 2),
        first_call_ms=round(first, 1), median_ms=round(median, 2),
        min_ms=round(best, 2), median_cpu_ms=round(cpu, 2), **common)

  # What a training run pays: one miss (tokenize, trim the padding, compile,
  # encode), then hits. A fresh cache per miss, timed after the first one
  # compiled.
  misses = []
  for _ in range(1 + _RUNS.value):
    cache = model.TextEmbeddingCache(params, config)
    start = time.perf_counter()
    jax.block_until_ready(cache(PAPER_PROMPTS))
    misses.append((time.perf_counter() - start) * 1e3)
  hit = _time_ms(lambda: cache(PAPER_PROMPTS), _RUNS.value, 0)[1]
  _emit(what='text_cache', prompts=len(PAPER_PROMPTS),
        first_miss_ms=round(misses[0], 1),
        miss_median_ms=round(statistics.median(misses[1:]), 2),
        hit_median_ms=round(hit, 4), **common)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f'Unexpected arguments: {argv[1:]}')
  config = model.VARIANTS[_VARIANT.value]
  params = model.init_params(config, jax.random.key(_SEED.value))
  jax.block_until_ready(params)
  common = dict(variant=_VARIANT.value, backend=jax.default_backend(),
                devices=len(jax.devices()), runs=_RUNS.value)
  if _SCORERS.value:
    _time_scorers(config, params, common)
  if _ENCODERS.value:
    _time_encoders(config, params, common)


if __name__ == '__main__':
  cli.run(main)
