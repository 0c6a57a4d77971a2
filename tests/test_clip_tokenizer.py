"""Tests of the CLIP BPE tokenizer."""

import importlib.util
import os
import pathlib
import sys
import tempfile
import types
import unittest
import zipfile

from absl.testing import absltest
from absl.testing import parameterized
import numpy as np

from clipgs_jax.clip import tokenizer

# Ids checked against two independent implementations: transformers'
# CLIPTokenizer (tokenizers backend) built from the same merge file, and
# open_clip 3.3.0's SimpleTokenizer run with ftfy installed (see
# OpenClipCrossCheckTest).
KNOWN_IDS = {
    'a photo of a person': [320, 1125, 539, 320, 2533],
    'a photo of people': [320, 1125, 539, 1047],
    'a photo of pedestrians': [320, 1125, 539, 33895],
    'a photo of hands': [320, 1125, 539, 3500],
    'a photo of a balloon': [320, 1125, 539, 320, 13634],
    'a photo of a building': [320, 1125, 539, 320, 2307],
    'a photo of a wall': [320, 1125, 539, 320, 2569],
    'a photo of furniture': [320, 1125, 539, 7993],
    'A  Photo of a  PERSON!': [320, 1125, 539, 320, 2533, 256],
    "it's 3 o'clock": [585, 568, 274, 334, 262, 6716],
    # HTML entities are unescaped twice, as in the reference.
    'Tom &amp;amp; Jerry': [2435, 261, 9164],
    # Curly quotes become straight ones, as ftfy does.
    'it\u2019s': [585, 568],
}
# Strings for the cross-checks; transformers does no HTML unescaping and no
# quote straightening, so those are left out of its list.
CROSS_CHECK = (
    'a photo of a person',
    'A photo of PEOPLE.',
    'pedestrians crossing the street, 2 of them!!',
    "don't   stop\tnow\n",
    'naïve café',
    'cafe\u0301 (decomposed accent)',
    '日本語のテキスト',
    'emoji \U0001f388 balloon',
    'under_score hy-phen 3.14 ½ ²',
    'x' * 100,
)
PHOTO = 1125  # id of 'photo</w>'


class KnownIdsTest(parameterized.TestCase):

  @parameterized.parameters(*KNOWN_IDS.items())
  def test_encode(self, text, ids):
    self.assertEqual(tokenizer.default_tokenizer().encode(text), ids)

  def test_paper_prompt_row(self):
    row = tokenizer.tokenize('a photo of a person')[0]
    self.assertEqual(
        row[:7].tolist(), [49406, 320, 1125, 539, 320, 2533, 49407]
    )
    np.testing.assert_array_equal(row[7:], 0)

  def test_batch_shape_dtype_and_padding(self):
    rows = tokenizer.tokenize(['a photo of hands', '', 'a photo of a wall'])
    self.assertEqual(rows.shape, (3, tokenizer.CONTEXT_LENGTH))
    self.assertEqual(rows.dtype, np.int32)
    self.assertEqual(rows[1, :3].tolist(), [49406, 49407, 0])
    # Each row: start, ids, end, zeros; argmax finds the end token.
    for row, text in zip(rows, ['a photo of hands', '', 'a photo of a wall']):
      n = len(tokenizer.default_tokenizer().encode(text)) + 2
      self.assertEqual(int(np.argmax(row)), n - 1)
      np.testing.assert_array_equal(row[n:], 0)

  def test_vocabulary(self):
    tok = tokenizer.default_tokenizer()
    self.assertLen(tok.vocab, tokenizer.VOCAB_SIZE)
    self.assertEqual(tok.vocab['!'], 0)  # first printable byte
    self.assertEqual(tok.vocab['a</w>'], 320)  # 256 + 64
    self.assertEqual(tok.vocab['<|startoftext|>'], tokenizer.START_OF_TEXT)
    self.assertEqual(tok.vocab['<|endoftext|>'], tokenizer.END_OF_TEXT)

  def test_byte_symbols_are_printable_and_distinct(self):
    symbols = tokenizer.byte_symbols()
    self.assertLen(set(symbols), 256)
    for s in symbols:
      self.assertTrue(s.isprintable() and not s.isspace(), repr(s))
    self.assertEqual(symbols[ord('a')], 'a')
    self.assertEqual(symbols[ord(' ')], chr(256 + 32))  # 33rd moved byte


class CleaningAndSplittingTest(parameterized.TestCase):

  @parameterized.parameters(
      ('  A\tPhoto\n of  X ', 'a photo of x'),
      ('&amp;lt;', '<'),  # unescaped twice
      ('cafe\u0301', 'caf\u00e9'),  # NFC
      ('\ufb01sh \uff21\uff22', 'fish ab'),  # ligature, full width
      ('\u201cq\u201d', '"q"'),
      ('a\x07b', 'ab'),  # control character dropped
  )
  def test_clean_text(self, raw, clean):
    self.assertEqual(tokenizer.clean_text(raw), clean)

  @parameterized.parameters(
      ("it's", ['it', "'s"]),
      ("we'll they're", ['we', "'ll", 'they', "'re"]),
      ('2026', ['2', '0', '2', '6']),
      ('a!?b', ['a', '!?', 'b']),
      ("!'s", ["!'", 's']),  # punctuation runs swallow the apostrophe
      ('<|endoftext|>', ['<|', 'endoftext', '|>']),
  )
  def test_split_words(self, text, words):
    self.assertEqual(tokenizer.split_words(text), words)

  def test_decode_round_trip(self):
    tok = tokenizer.default_tokenizer()
    for text in ('a photo of a person', 'naïve café', 'hi ! 3 4'):
      row = tok.tokenize(text)[0]
      self.assertEqual(tok.decode(row), text)


class LengthTest(parameterized.TestCase):

  def test_exact_fit(self):
    text = ' '.join(['photo'] * 75)  # 75 ids + start + end = 77
    row = tokenizer.tokenize(text)[0]
    self.assertEqual(row[-1], tokenizer.END_OF_TEXT)
    np.testing.assert_array_equal(row[1:-1], PHOTO)

  def test_over_long_raises(self):
    text = ' '.join(['photo'] * 76)
    with self.assertRaisesRegex(ValueError, r'78 tokens.*77.*truncate=True'):
      tokenizer.tokenize(['a photo of hands', text])

  def test_truncate_keeps_end_token(self):
    row = tokenizer.tokenize(' '.join(['photo'] * 200), truncate=True)[0]
    self.assertEqual(row[0], tokenizer.START_OF_TEXT)
    np.testing.assert_array_equal(row[1:-1], PHOTO)
    self.assertEqual(row[-1], tokenizer.END_OF_TEXT)

  def test_shorter_context(self):
    rows = tokenizer.tokenize('a photo of a person', context_length=8)
    self.assertEqual(rows.shape, (1, 8))
    with self.assertRaises(ValueError):
      tokenizer.tokenize('a photo of a person', context_length=6)


class TransformersCrossCheckTest(parameterized.TestCase):
  """Against transformers' CLIPTokenizer built from the same merges."""

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    try:
      import transformers  # pylint: disable=g-import-not-at-top
    except ImportError as e:
      raise unittest.SkipTest(f'transformers is not installed: {e}') from e
    tok = tokenizer.default_tokenizer()
    try:
      # transformers >= 5 takes the vocabulary and merges as objects.
      cls.hf = transformers.CLIPTokenizer(
          vocab=dict(tok.vocab), merges=list(tok.merges)
      )
    except TypeError:
      cls.hf = cls._from_files(transformers, tok)

  @staticmethod
  def _from_files(transformers, tok):
    # Older transformers read vocab.json and merges.txt from disk.
    import json  # pylint: disable=g-import-not-at-top
    d = pathlib.Path(tempfile.mkdtemp())
    (d / 'vocab.json').write_text(json.dumps(tok.vocab), 'utf-8')
    merges = ['#version: 0.2'] + [f'{a} {b}' for a, b in tok.merges]
    (d / 'merges.txt').write_text('\n'.join(merges) + '\n', 'utf-8')
    return transformers.CLIPTokenizer(str(d / 'vocab.json'),
                                      str(d / 'merges.txt'))

  @parameterized.parameters(*CROSS_CHECK)
  def test_same_ids(self, text):
    expected = self.hf(text, add_special_tokens=False)['input_ids']
    self.assertEqual(tokenizer.default_tokenizer().encode(text), expected)

  def test_special_tokens(self):
    ids = self.hf('a photo of a person')['input_ids']
    self.assertEqual(ids, tokenizer.tokenize('a photo of a person')[0, :7]
                     .tolist())


def _load_open_clip_tokenizer():
  """Loads open_clip's tokenizer module from its wheel, or skips."""
  wheel = os.environ.get('CLIPGS_OPEN_CLIP_WHEEL')
  if not wheel or not os.path.exists(wheel):
    raise unittest.SkipTest(
        'set CLIPGS_OPEN_CLIP_WHEEL to an open_clip_torch wheel file to '
        'compare with its tokenizer')
  for name in ('ftfy', 'regex', 'torch'):
    if importlib.util.find_spec(name) is None:
      raise unittest.SkipTest(
          f"open_clip's tokenizer needs {name}, which is not installed")
  d = pathlib.Path(tempfile.mkdtemp())
  with zipfile.ZipFile(wheel) as z:
    source = z.read('open_clip/tokenizer.py').decode('utf-8')
    (d / tokenizer.VOCAB_FILE).write_bytes(
        z.read('open_clip/' + tokenizer.VOCAB_FILE))
  # Executed as a lone module: the package __init__ would pull in models.
  module = types.ModuleType('open_clip_tokenizer')
  module.__file__ = str(d / 'tokenizer.py')
  sys.modules.pop(module.__name__, None)
  code = compile(source, module.__file__, 'exec')
  exec(code, module.__dict__)  # pylint: disable=exec-used
  return module


class OpenClipCrossCheckTest(parameterized.TestCase):
  """Against the reference tokenizer itself, ftfy included (opt-in)."""

  @classmethod
  def setUpClass(cls):
    super().setUpClass()
    cls.ref = _load_open_clip_tokenizer().SimpleTokenizer()

  @parameterized.parameters(*(CROSS_CHECK + tuple(KNOWN_IDS)))
  def test_same_ids(self, text):
    self.assertEqual(tokenizer.default_tokenizer().encode(text),
                     self.ref.encode(text))

  def test_truncation(self):
    text = ' '.join(['photo'] * 100)
    np.testing.assert_array_equal(
        tokenizer.tokenize(text, truncate=True), self.ref([text]).numpy())


if __name__ == '__main__':
  absltest.main()
