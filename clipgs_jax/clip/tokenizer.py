"""CLIP byte-level BPE tokenizer over OpenAI's merge list, shipped with us."""

from collections.abc import Iterable, Sequence
import functools
import gzip
import html
import importlib.resources
import pathlib
import unicodedata

import numpy as np

START_OF_TEXT = 49406  # id of <|startoftext|>, first in every sequence
END_OF_TEXT = 49407  # id of <|endoftext|>; the text tower pools here
CONTEXT_LENGTH = 77  # sequence length of every OpenAI CLIP text tower
VOCAB_SIZE = 49408
VOCAB_FILE = 'bpe_simple_vocab_16e6.txt.gz'

# The merge file holds more merges than CLIP uses: the vocabulary is 256 byte
# symbols, their 256 word-final forms, the first 48894 merges and the two
# special tokens, 49408 ids in all.
_NUM_MERGES = VOCAB_SIZE - 2 * 256 - 2
_WORD_END = '</w>'
_START_TOKEN = '<|startoftext|>'
_END_TOKEN = '<|endoftext|>'
_CONTRACTIONS = ("'s", "'t", "'re", "'ve", "'m", "'ll", "'d")
# Stand-ins for the parts of ftfy.fix_text that change plain prompts: it
# straightens curly quotes and NFKC-folds ligatures and full-width forms.
_STRAIGHT_QUOTES = str.maketrans({
    '\u2018': "'", '\u2019': "'", '\u201a': "'", '\u201b': "'",
    '\u201c': '"', '\u201d': '"', '\u201e': '"', '\u201f': '"',
})
_LIGATURES = frozenset('\ufb00\ufb01\ufb02\ufb03\ufb04\ufb05\ufb06')


def byte_symbols() -> list[str]:
  """Returns the printable character that stands for each byte value.

  Returns:
    list of 256 one-character strings; entry b stands for byte b.
  """
  # Printable Latin-1 bytes stand for themselves. The other 68 (controls,
  # space, NBSP, soft hyphen) move to code points 256 and up, in byte order,
  # so that no symbol is whitespace or a control character.
  printable = (
      set(range(0x21, 0x7F)) | set(range(0xA1, 0xAD)) | set(range(0xAE, 0x100))
  )
  symbols, moved = [], 0
  for b in range(256):
    if b in printable:
      symbols.append(chr(b))
    else:
      symbols.append(chr(256 + moved))
      moved += 1
  return symbols


def _base_symbol_order(symbols: Sequence[str]) -> list[str]:
  """Orders the byte symbols as CLIP numbers them: printable bytes first."""
  return [s for s in symbols if ord(s) < 256] + [
      s for s in symbols if ord(s) >= 256
  ]


def _char_kind(c: str) -> str:
  """Returns 'L' (letter), 'N' (number), ' ' (space) or 'O' (other)."""
  if c.isspace():
    return ' '
  major = unicodedata.category(c)[0]
  return major if major in 'LN' else 'O'


def split_words(text: str) -> list[str]:
  """Splits cleaned text into the pieces that BPE encodes one by one.

  Same pieces as CLIP's pattern: English contractions, letter runs, single
  digits and runs of other non-space characters. Unlike the reference, the
  strings '<|startoftext|>' and '<|endoftext|>' are ordinary text here, so a
  prompt can never smuggle an end token into the middle of a sequence.

  Args:
    text: str, output of `clean_text`.

  Returns:
    list of str pieces, whitespace dropped.
  """
  words = []
  i, n = 0, len(text)
  while i < n:
    kind = _char_kind(text[i])
    if kind == ' ':
      i += 1
      continue
    if text[i] == "'":
      match = next((c for c in _CONTRACTIONS if text.startswith(c, i)), None)
      if match is not None:
        words.append(match)
        i += len(match)
        continue
    j = i + 1
    if kind != 'N':  # numbers are split into single digits
      while j < n and _char_kind(text[j]) == kind:
        j += 1
    words.append(text[i:j])
    i = j
  return words


def _fix_text(text: str) -> str:
  """Normalises Unicode the way ftfy.fix_text does for ordinary prompts.

  ftfy is not a dependency. What it would do to prompts is NFC composition,
  straight quotes, unfolded ligatures and half-width forms of full-width
  characters; those are done here. Its mojibake repair is not: prompts are
  typed by us, not decoded with the wrong codec.

  Args:
    text: str, raw prompt.

  Returns:
    str, normalised prompt.
  """
  text = text.translate(_STRAIGHT_QUOTES)
  text = ''.join(
      unicodedata.normalize('NFKC', c)
      if c in _LIGATURES or unicodedata.east_asian_width(c) == 'F'
      else c
      for c in text
  )
  # ftfy drops control characters other than whitespace.
  text = ''.join(
      c for c in text if c.isspace() or unicodedata.category(c) != 'Cc'
  )
  return unicodedata.normalize('NFC', text)


def clean_text(text: str) -> str:
  """Cleans a prompt as CLIP does before BPE.

  Args:
    text: str, raw prompt.

  Returns:
    str, unescaped, single-spaced, stripped and lower-cased prompt.
  """
  text = _fix_text(text)
  # Twice, as the reference does, for doubly escaped scraped captions.
  text = html.unescape(html.unescape(text))
  return ' '.join(text.split()).lower()


class Tokenizer:
  """CLIP byte-level BPE over a merge list."""

  def __init__(self, merges: Sequence[tuple[str, str]]):
    """Builds the vocabulary.

    Args:
      merges: the first `_NUM_MERGES` merge rules, best first.
    """
    if len(merges) != _NUM_MERGES:
      raise ValueError(
          f'CLIP needs {_NUM_MERGES} merges, got {len(merges)}.'
      )
    self._byte_symbols = byte_symbols()
    base = _base_symbol_order(self._byte_symbols)
    vocab = base + [s + _WORD_END for s in base]
    vocab += [a + b for a, b in merges]
    vocab += [_START_TOKEN, _END_TOKEN]
    self.vocab = {token: i for i, token in enumerate(vocab)}
    self._id_to_token = vocab
    self._byte_of_symbol = {s: b for b, s in enumerate(self._byte_symbols)}
    self._ranks = {pair: rank for rank, pair in enumerate(merges)}
    self.merges = tuple(merges)
    self._bpe_cache = {}
    assert self.vocab[_START_TOKEN] == START_OF_TEXT
    assert self.vocab[_END_TOKEN] == END_OF_TEXT

  def _bpe(self, word: str) -> tuple[str, ...]:
    """Applies the merges to one piece written in byte symbols."""
    cached = self._bpe_cache.get(word)
    if cached is not None:
      return cached
    parts = list(word[:-1]) + [word[-1] + _WORD_END]
    while len(parts) > 1:
      pairs = list(zip(parts[:-1], parts[1:]))
      best = min(pairs, key=lambda p: self._ranks.get(p, _NUM_MERGES))
      if best not in self._ranks:
        break
      # Merge every occurrence of the best pair, left to right.
      merged, i = [], 0
      while i < len(parts):
        if i + 1 < len(parts) and (parts[i], parts[i + 1]) == best:
          merged.append(parts[i] + parts[i + 1])
          i += 2
        else:
          merged.append(parts[i])
          i += 1
      parts = merged
    result = tuple(parts)
    self._bpe_cache[word] = result
    return result

  def encode(self, text: str) -> list[int]:
    """Returns the BPE ids of a prompt, without start and end tokens."""
    ids = []
    for word in split_words(clean_text(text)):
      symbols = ''.join(self._byte_symbols[b] for b in word.encode('utf-8'))
      ids.extend(self.vocab[token] for token in self._bpe(symbols))
    return ids

  def decode(self, ids: Iterable[int]) -> str:
    """Returns the cleaned text of one id row, up to its end token.

    Args:
      ids: iterable of int, e.g. one row of `tokenize`.

    Returns:
      str, the words of the row joined by single spaces.
    """
    tokens = []
    for i in ids:
      if i == END_OF_TEXT:  # what follows is padding
        break
      if i != START_OF_TEXT:
        tokens.append(self._id_to_token[i])
    words = ''.join(tokens).split(_WORD_END)
    return ' '.join(
        bytes(self._byte_of_symbol[c] for c in w).decode('utf-8', 'replace')
        for w in words
        if w
    )

  def tokenize(
      self,
      texts: str | Sequence[str],
      context_length: int = CONTEXT_LENGTH,
      truncate: bool = False,
  ) -> np.ndarray:
    """Tokenizes prompts into padded id rows.

    Args:
      texts: str or sequence of P str, the prompts.
      context_length: int, row length (77 for every OpenAI model).
      truncate: bool, cut over-long prompts, keeping the end token last,
        instead of raising.

    Returns:
      int32 [P, context_length], start token, BPE ids, end token, zeros.

    Raises:
      ValueError: a prompt does not fit and truncate is False.
    """
    if isinstance(texts, str):
      texts = [texts]
    rows = np.zeros((len(texts), context_length), np.int32)
    for row, text in zip(rows, texts):
      ids = [START_OF_TEXT] + self.encode(text) + [END_OF_TEXT]
      if len(ids) > context_length:
        if not truncate:
          raise ValueError(
              f'Prompt {text!r} is {len(ids)} tokens with start and end '
              f'tokens; the context length is {context_length}. Shorten it '
              'or pass truncate=True to cut it (the end token is kept).'
          )
        ids = ids[: context_length - 1] + [END_OF_TEXT]
      row[: len(ids)] = ids
    return rows


def read_merges(path=None) -> list[tuple[str, str]]:
  """Reads the merge rules CLIP uses from a gzipped merge list.

  Args:
    path: path-like or None for the file shipped as package data.

  Returns:
    list of `_NUM_MERGES` (left, right) symbol pairs, best first.
  """
  if path is None:
    path = importlib.resources.files(__package__).joinpath(VOCAB_FILE)
  else:
    path = pathlib.Path(path)
  lines = gzip.decompress(path.read_bytes()).decode('utf-8').split('\n')
  # Line 0 is a '#version' header.
  return [tuple(line.split()) for line in lines[1 : 1 + _NUM_MERGES]]


@functools.cache
def default_tokenizer() -> Tokenizer:
  """Returns the tokenizer over the shipped merge list, built once."""
  return Tokenizer(read_merges())


def tokenize(
    texts: str | Sequence[str],
    context_length: int = CONTEXT_LENGTH,
    truncate: bool = False,
) -> np.ndarray:
  """Tokenizes prompts with the default tokenizer; see Tokenizer.tokenize."""
  return default_tokenizer().tokenize(texts, context_length, truncate)
