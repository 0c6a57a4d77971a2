"""Image files: OpenImageIO reading, area downscaling with a cache, PNG out."""

import hashlib
import os
import uuid

import numpy as np
import OpenImageIO as oiio

# Bumped whenever the resize or the cache encoding changes, so that files
# written by an older version are never read back as current.
_CACHE_VERSION = 1


def _read_config() -> oiio.ImageSpec:
  config = oiio.ImageSpec()
  # OpenImageIO premultiplies colour by alpha on read unless told not to;
  # alpha is dropped below, so the stored (unassociated) colour is wanted.
  config.attribute("oiio:UnassociatedAlpha", 1)
  return config


def _to_unit_float(pixels: np.ndarray, path: str) -> np.ndarray:
  """float32 array in [0, 1] from the native pixel type of a file."""
  if pixels.dtype == np.uint8:
    return pixels.astype(np.float32) / np.float32(255)
  if pixels.dtype == np.uint16:
    return pixels.astype(np.float32) / np.float32(65535)
  if pixels.dtype == np.uint32:
    return (pixels.astype(np.float64) / 4294967295.0).astype(np.float32)
  if np.issubdtype(pixels.dtype, np.floating):
    # Float files (EXR, TIFF) may hold values outside [0, 1]; the renderer
    # and losses assume display-range targets, so clamp rather than refuse.
    return np.clip(np.nan_to_num(pixels.astype(np.float32)), 0.0, 1.0)
  raise ValueError(f"{path}: unsupported pixel type {pixels.dtype}; convert "
                   "the image to 8- or 16-bit PNG/JPEG.")


def read_image(path: str, background=None) -> np.ndarray:
  """Reads an image file as RGB.

  The stored pixels are returned as they are: EXIF orientation is NOT applied,
  because COLMAP poses (and its width/height) refer to the stored pixel grid.
  An alpha channel is composited onto `background`, or dropped without one
  (colour kept as stored). Grey images are replicated into three channels.

  Args:
    path: str, any format OpenImageIO reads (PNG, JPEG, TIFF, EXR, ...).
    background: None, or float [3] in [0, 1]: the colour behind a photo
      with an alpha channel (colour * alpha + background * (1 - alpha)).

  Returns:
    float32 [H, W, 3], values in [0, 1] (8-bit / 255, 16-bit / 65535).
  """
  if not os.path.isfile(path):
    raise FileNotFoundError(f"image file not found: {path}")
  if not os.access(path, os.R_OK):
    # OpenImageIO would report "could not open", and we would advise
    # re-saving a file that is fine.
    raise PermissionError(f"image {path} is not readable (permission "
                          "denied); make it readable (chmod a+r) or run as "
                          "its owner.")
  inp = oiio.ImageInput.open(path, _read_config())
  if inp is None:
    raise ValueError(f"cannot read image {path}: "
                     f"{oiio.geterror().strip() or 'unknown format'}; "
                     "re-save it as PNG or JPEG.")
  try:
    spec = inp.spec()
    pixels = inp.read_image(0, 0, 0, spec.nchannels, spec.format)
    if pixels is None:
      raise ValueError(f"cannot decode image {path}: "
                       f"{inp.geterror().strip()}; re-save it as PNG or JPEG.")
  finally:
    inp.close()
  pixels = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)
  image = _to_unit_float(pixels, path)
  alpha = None
  if spec.nchannels in (1, 2):       # grey, or grey + alpha
    alpha = image[..., 1:2] if spec.nchannels == 2 else None
    image = np.repeat(image[..., :1], 3, axis=-1)
  elif spec.nchannels >= 3:          # RGB, RGBA, more
    alpha = image[..., 3:4] if spec.nchannels == 4 else None
    image = image[..., :3]
  else:
    raise ValueError(f"{path} has no colour channels.")
  if alpha is not None and background is not None:
    # The stored colour is unassociated (_read_config), so this is "over".
    image = image * alpha + np.asarray(background, np.float32) * (1 - alpha)
  return np.ascontiguousarray(image, dtype=np.float32)


def has_alpha(path: str) -> bool:
  """Whether an image file has an alpha channel, from its header only."""
  return _header(path).alpha_channel >= 0


def _header(path: str) -> oiio.ImageSpec:
  if not os.path.isfile(path):
    raise FileNotFoundError(f"image file not found: {path}")
  inp = oiio.ImageInput.open(path)
  if inp is None:
    raise ValueError(f"cannot read image {path}: "
                     f"{oiio.geterror().strip() or 'unknown format'}; "
                     "re-save it as PNG or JPEG.")
  spec = inp.spec()
  inp.close()
  return spec


def image_size(path: str) -> tuple[int, int]:
  """(width, height) of an image file, from its header only."""
  spec = _header(path)
  return spec.width, spec.height


def downscaled_size(width: int, height: int, factor: int) -> tuple[int, int]:
  """(width, height) after downscaling by `factor`: round(W / K), at least 1.

  Sizes that are not divisible by K are rounded to the nearest integer; the
  intrinsics are then scaled by new_W / W and new_H / H (see `scale_factors`),
  which keeps the image plane covering the same field of view.
  """
  if int(factor) != factor or factor < 1:
    raise ValueError(f"downscale factor must be a positive integer, got "
                     f"{factor!r}.")
  return (max(1, int(np.floor(width / factor + 0.5))),
          max(1, int(np.floor(height / factor + 0.5))))


def _area_taps(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray]:
  """Source indices int [n_out, T] and weights float64 [n_out, T].

  Output pixel j covers the source interval [j s, (j + 1) s), s = n_in / n_out
  (pixel edges, so pixel centres stay at +0.5 in both grids); each source
  pixel is weighted by its overlap with that interval.
  """
  s = n_in / n_out
  taps = int(np.ceil(s)) + 1
  start = np.arange(n_out, dtype=np.float64) * s
  idx = np.floor(start).astype(np.int64)[:, None] + np.arange(taps)[None]
  lo = np.maximum(idx, start[:, None])
  hi = np.minimum(idx + 1, start[:, None] + s)
  weights = np.clip(hi - lo, 0.0, None)
  weights /= weights.sum(axis=1, keepdims=True)
  # Taps past the edge have zero weight; clamp them to a valid index.
  return np.minimum(idx, n_in - 1), weights


def resize_area(image: np.ndarray, width: int, height: int) -> np.ndarray:
  """Antialiased resize by exact area averaging (box filter of the footprint).

  For an integer factor that divides the size this is the mean of each K x K
  block; other ratios weight the partially covered source pixels.

  Args:
    image: float [H, W] or [H, W, C].
    width, height: int, output size.

  Returns:
    float32 [height, width] or [height, width, C].
  """
  image = np.asarray(image, np.float32)
  rows, row_w = _area_taps(image.shape[0], height)
  cols, col_w = _area_taps(image.shape[1], width)
  extra = (1,) * (image.ndim - 2)
  out = np.zeros((height,) + image.shape[1:], np.float64)
  for k in range(rows.shape[1]):
    out += row_w[:, k].reshape((-1, 1) + extra) * image[rows[:, k]]
  tmp = out
  out = np.zeros((height, width) + image.shape[2:], np.float64)
  for k in range(cols.shape[1]):
    out += col_w[:, k].reshape((1, -1) + extra) * tmp[:, cols[:, k]]
  return out.astype(np.float32)


def _cache_file(cache_dir: str, path: str, factor: int, background) -> str:
  """Cache path keyed by source path, size, mtime and background (stale
  files ignored)."""
  st = os.stat(path)
  key = (f"{_CACHE_VERSION}|{os.path.realpath(path)}|{st.st_size}|"
         f"{st.st_mtime_ns}|{factor}")
  if background is not None:
    key += "|" + ",".join(f"{float(c):g}" for c in background)
  digest = hashlib.sha1(key.encode()).hexdigest()[:16]
  return os.path.join(cache_dir, f"{digest}-{os.path.basename(path)}.png")


def _check_size(path, actual, expected, what):
  if tuple(actual) != tuple(expected):
    raise ValueError(
        f"{path} is {actual[0]}x{actual[1]} pixels but {what} says "
        f"{expected[0]}x{expected[1]}; replace the image or fix its camera.")


def _codes(image: np.ndarray) -> np.ndarray:
  """`image` quantised to 16-bit codes (8- and 16-bit files are already)."""
  return np.round(np.clip(image, 0, 1) * 65535).astype(np.float32) / 65535


def load_image(path: str, *, factor: int = 1,
               expected_size: tuple[int, int] | None = None,
               cache_dir: str | None = None,
               prescaled_path: str | None = None,
               background=None) -> np.ndarray:
  """Reads an image downscaled by an integer factor.

  With factor K > 1: a pre-scaled file (e.g. RobustNeRF's `images_K/`) is
  used when `prescaled_path` exists; else the full-size file is area-averaged
  to `downscaled_size` and, if `cache_dir` is given, stored there as a 16-bit
  PNG (atomic write) and read back on later calls. Values are quantised to
  16 bits before they are returned, so a fresh and a cached load agree.

  Args:
    path: str, the full-resolution image.
    factor: int, downscale factor K >= 1.
    expected_size: (width, height) of the full-resolution image (from its
      camera); a mismatch raises ValueError naming the file.
    cache_dir: str or None, folder for resized copies.
    prescaled_path: str or None, a file already downscaled by K.
    background: None or float [3], see `read_image`; an alpha channel is
      composited at full resolution, before the area average.

  Returns:
    float32 [h, w, 3] in [0, 1]; (w, h) is `downscaled_size` (or within one
    pixel of W / K for a pre-scaled file, whose own size is kept).
  """
  if factor == 1:
    image = read_image(path, background)
    if expected_size is not None:
      _check_size(path, image.shape[1::-1], expected_size, "its camera")
    return _codes(image)
  if prescaled_path is not None and os.path.isfile(prescaled_path):
    image = read_image(prescaled_path, background)
    if expected_size is not None:
      w, h = expected_size
      if (abs(image.shape[1] - w / factor) >= 1 or
          abs(image.shape[0] - h / factor) >= 1):
        raise ValueError(
            f"{prescaled_path} is {image.shape[1]}x{image.shape[0]} pixels, "
            f"not about 1/{factor} of its camera's {w}x{h}; delete the "
            "pre-scaled folder or fix the image.")
    return _codes(image)
  if not os.path.isfile(path):
    raise FileNotFoundError(f"image file not found: {path}")
  cached = (_cache_file(cache_dir, path, factor, background) if cache_dir
            else None)
  if cached is not None and os.path.isfile(cached):
    return read_image(cached)
  image = read_image(path, background)
  size = image.shape[1::-1]
  if expected_size is not None:
    _check_size(path, size, expected_size, "its camera")
  image = _codes(resize_area(image, *downscaled_size(*size, factor)))
  if cached is not None:
    # Cache files are written once and read often: favour write speed.
    write_png(cached, image, bits=16, compression=1)
  return image


def _atomic_temp(path: str) -> str:
  """A temp name next to `path` with the same extension (format detection)."""
  folder, base = os.path.split(os.path.abspath(path))
  ext = os.path.splitext(base)[1]
  return os.path.join(folder, f".{base}.{os.getpid()}-{uuid.uuid4().hex}"
                      f".tmp{ext}")


def write_png(path: str, image, bits: int = 8, compression: int = 6
              ) -> None:
  """Writes an image as PNG, atomically (temp file, then os.replace).

  Args:
    path: str, output file; parent folders are created.
    image: float [H, W], [H, W, 1], [H, W, 3] or [H, W, 4] in [0, 1] (values
      outside are clipped), or bool [H, W] (True = white).
    bits: 8 or 16, bits per channel.
    compression: 0-9, zlib level (1 is much faster, files somewhat larger).
  """
  image = np.asarray(image)
  if image.dtype == np.bool_:
    image = image.astype(np.float32)
  if image.ndim == 2:
    image = image[..., None]
  if image.ndim != 3 or image.shape[-1] not in (1, 3, 4) or 0 in image.shape:
    raise ValueError(f"write_png({path}): expected an image [H, W], [H, W, 1],"
                     f" [H, W, 3] or [H, W, 4], got shape {image.shape}.")
  if bits not in (8, 16):
    raise ValueError(f"write_png({path}): bits must be 8 or 16, got {bits}.")
  if not np.issubdtype(image.dtype, np.floating):
    raise ValueError(f"write_png({path}): expected a float image in [0, 1], "
                     f"got dtype {image.dtype}.")
  dtype, fmt = (np.uint8, "uint8") if bits == 8 else (np.uint16, "uint16")
  top = np.iinfo(dtype).max
  pixels = np.round(np.clip(np.nan_to_num(image.astype(np.float64)), 0, 1)
                    * top).astype(dtype)
  folder = os.path.dirname(os.path.abspath(path))
  os.makedirs(folder, exist_ok=True)
  tmp = _atomic_temp(path)
  out = oiio.ImageOutput.create(tmp)
  if out is None:
    raise OSError(f"cannot create PNG writer for {path}: {oiio.geterror()}")
  try:
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2],
                          fmt)
    # Pixels are stored as given; without this the PNG writer would divide
    # colour by alpha (it assumes premultiplied input).
    spec.attribute("oiio:UnassociatedAlpha", 1)
    spec.attribute("png:compressionLevel", int(compression))
    if not out.open(tmp, spec):
      raise OSError(f"cannot write {path}: {out.geterror()}")
    ok = out.write_image(np.ascontiguousarray(pixels))
    out.close()
    if not ok:
      raise OSError(f"cannot write {path}: {out.geterror()}")
    os.replace(tmp, path)
  finally:
    if os.path.exists(tmp):
      os.remove(tmp)
