"""Timings of the CLIP encoders and view scorers on random weights."""

import statistics
import time
from typing import Iterator

import jax
import jax.numpy as jnp

from clipgs_jax.lab import timing
from clipgs_jax import config as config_lib
from clipgs_jax import guidance_config
from clipgs_jax.clip import model
from clipgs_jax.clip import preprocess
from clipgs_jax.clip import scorer
from clipgs_jax.clip import tokenizer

# The eight prompts of the CLIP-GS paper: five distractor, three static.
PAPER_PROMPTS = (
    'a photo of a person', 'a photo of people', 'a photo of pedestrians',
    'a photo of hands', 'a photo of a balloon', 'a photo of a building',
    'a photo of a wall', 'a photo of furniture',
)
WEIGHTS_SEED = 0   # random weights: the timings do not depend on them


def _ms(fn, runs: int, warmup: int) -> dict:
  """first_call_ms, median_ms, min_ms and median_cpu_ms of fn()."""
  t = timing.time_calls(fn, repeats=runs, warmup=warmup)
  return dict(first_call_ms=round(t.first_s * 1e3, 1),
              median_ms=round(statistics.median(t.wall_s) * 1e3, 2),
              min_ms=round(min(t.wall_s) * 1e3, 2),
              median_cpu_ms=round(statistics.median(t.cpu_s) * 1e3, 2))


def _render(render_hw):
  return jax.random.uniform(jax.random.key(2), (*render_hw, 3))


def setup(variant: str, runs: int):
  """(ClipConfig, random params, the fields every result line carries)."""
  config = model.VARIANTS[variant]
  params = model.init_params(config, jax.random.key(WEIGHTS_SEED))
  jax.block_until_ready(params)
  common = dict(variant=variant, backend=jax.default_backend(),
                devices=len(jax.devices()), runs=runs)
  return config, params, common


def scorers(variant: str, render_hw: tuple[int, int], *, runs: int,
            warmup: int, dense_input_sizes: list[int],
            dense_readouts: list[str]) -> Iterator[dict]:
  """ClipScorer.score (paper, image-level) and DenseClipScorer.score_map at
  each input size and readout, jitted as the train step runs them, on one
  render of render_hw."""
  config, params, common = setup(variant, runs)
  render = _render(render_hw)
  view = jnp.int32(0)
  sem = guidance_config.SemanticConfig(scorer='clip')  # the paper's prompts
  image_level = scorer.make(sem, clip_params=(config, params))
  score = jax.jit(lambda s, im: s.score(im, view))
  yield dict(what='scorer_image_level', render_hw=list(render_hw),
             input_size=config.image_size,
             **_ms(lambda: score(image_level, render), runs, warmup),
             **common)
  score_map = jax.jit(lambda s, im: s.score_map(im, view))
  for readout in dense_readouts:
    for input_size in dense_input_sizes:
      dense_scorer = scorer.make_dense(sem, clip_params=(config, params),
                                       input_size=input_size, readout=readout)
      yield dict(what='scorer_dense', readout=readout,
                 render_hw=list(render_hw), input_size=input_size,
                 grid=dense_scorer.grid,
                 **_ms(lambda: score_map(dense_scorer, render), runs, warmup),
                 **common)


def encoders(variant: str, render_hw: tuple[int, int], *, runs: int,
             warmup: int, batch_sizes: list[int]) -> Iterator[dict]:
  """encode_image per batch size, preprocessing of a render_hw render,
  the tokenizer and encode_text of the paper prompts, and the text cache
  (one miss, then hits)."""
  config, params, common = setup(variant, runs)
  size = config.image_size
  for batch in batch_sizes:
    images = jax.random.normal(jax.random.key(1), (batch, size, size, 3))
    t = _ms(lambda: model.encode_image(params, images, config=config),
            runs, warmup)
    yield dict(what='encode_image', batch=batch, **t,
               median_ms_per_image=round(t['median_ms'] / batch, 2), **common)

  render = _render(render_hw)
  prep = jax.jit(preprocess.preprocess, static_argnames=('mode', 'size'))
  yield dict(what='preprocess', render_hw=list(render_hw),
             **_ms(lambda: prep(render, size=size), runs, warmup), **common)

  start = time.perf_counter()
  tokenizer.default_tokenizer()  # reads the merge list, once per process
  load_ms = (time.perf_counter() - start) * 1e3
  start = time.perf_counter()
  tokens = jnp.asarray(tokenizer.tokenize(PAPER_PROMPTS))
  tokenize_ms = (time.perf_counter() - start) * 1e3
  yield dict(what='encode_text', prompts=len(PAPER_PROMPTS),
             tokens_per_prompt=tokens.shape[1],
             tokenizer_load_ms=round(load_ms, 1),
             tokenize_ms=round(tokenize_ms, 2),
             **_ms(lambda: model.encode_text(params, tokens, config=config),
                   runs, warmup), **common)

  # What a training run pays: one miss (tokenize, trim the padding, compile,
  # encode), then hits. A fresh cache per miss, timed after the first one
  # compiled.
  misses = []
  for _ in range(1 + runs):
    cache = model.TextEmbeddingCache(params, config)
    start = time.perf_counter()
    jax.block_until_ready(cache(PAPER_PROMPTS))
    misses.append((time.perf_counter() - start) * 1e3)
  hit = statistics.median(timing.time_calls(
      lambda: cache(PAPER_PROMPTS), repeats=runs).wall_s) * 1e3
  yield dict(what='text_cache', prompts=len(PAPER_PROMPTS),
             first_miss_ms=round(misses[0], 1),
             miss_median_ms=round(statistics.median(misses[1:]), 2),
             hit_median_ms=round(hit, 4), **common)
