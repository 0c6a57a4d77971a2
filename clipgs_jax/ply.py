"""Gaussians to and from the 3DGS PLY layout (binary little-endian)."""

import os
import re
import uuid

import jax
import jax.numpy as jnp
import numpy as np

from clipgs_jax import gaussians

# PLY scalar types and their numpy equivalents (both spellings of the spec).
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}


def _field_names(num_rest: int) -> list[str]:
  """3DGS vertex properties, in the order 3DGS writes them."""
  return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] +
          [f"f_rest_{i}" for i in range(3 * num_rest)] +
          ["opacity", "scale_0", "scale_1", "scale_2",
           "rot_0", "rot_1", "rot_2", "rot_3"])


def write_ply(path: str, params: gaussians.GaussianParams, alive) -> None:
  """Writes the alive Gaussians as a 3DGS-compatible PLY, atomically.

  Values are stored unconstrained, as 3DGS does: opacity as a logit, scales
  as logs, rotations as raw (w, x, y, z) quaternions, normals as zeros.
  f_rest is channel-major: every rest coefficient of R, then G, then B.

  Args:
    path: str, output file.
    params: GaussianParams with capacity C.
    alive: bool [C], which slots to write.
  """
  gaussians.validate(params, jnp.asarray(alive))
  alive = np.asarray(alive)
  get = lambda x: np.asarray(x, np.float32)[alive]
  means, rest = get(params.means), get(params.sh_rest)     # rest [N, K, 3]
  n, k = means.shape[0], rest.shape[1]
  names = _field_names(k)
  columns = np.concatenate([
      means, np.zeros((n, 3), np.float32), get(params.sh_dc),
      rest.transpose(0, 2, 1).reshape(n, 3 * k),            # [N, 3 K]
      get(params.opacity_logits)[:, None], get(params.log_scales),
      get(params.quats)], axis=1)
  records = np.empty(n, np.dtype([(name, "<f4") for name in names]))
  for i, name in enumerate(names):
    records[name] = columns[:, i]
  header = ("ply\nformat binary_little_endian 1.0\n"
            f"element vertex {n}\n" +
            "".join(f"property float {name}\n" for name in names) +
            "end_header\n")
  folder = os.path.dirname(os.path.abspath(path))
  os.makedirs(folder, exist_ok=True)
  tmp = os.path.join(folder, f".{os.path.basename(path)}."
                     f"{os.getpid()}-{uuid.uuid4().hex}.tmp")
  try:
    with open(tmp, "wb") as f:
      f.write(header.encode("ascii"))
      f.write(records.tobytes())
    os.replace(tmp, path)
  finally:
    if os.path.exists(tmp):
      os.remove(tmp)


def _read_header(f, path: str) -> tuple[int, np.dtype]:
  """(vertex count, vertex record dtype) from a binary PLY header."""
  if f.readline().strip() != b"ply":
    raise ValueError(f"{path} is not a PLY file (no 'ply' magic line).")
  count, fields, in_vertex = None, [], False
  while True:
    line = f.readline()
    if not line:
      raise ValueError(f"{path}: PLY header has no end_header line.")
    words = line.decode("ascii", "replace").split()
    if not words or words[0] in ("comment", "obj_info"):
      continue
    if words[0] == "end_header":
      break
    if words[0] == "format" and words[1:2] != ["binary_little_endian"]:
      raise ValueError(f"{path}: PLY format {' '.join(words[1:])} is not "
                       "supported; write it as binary_little_endian.")
    if words[0] == "element":
      if count is not None and in_vertex:
        raise ValueError(f"{path}: only a single 'vertex' element is "
                         "supported.")
      in_vertex = words[1] == "vertex"
      if in_vertex:
        count = int(words[2])
      elif count is None:
        raise ValueError(f"{path}: element {words[1]} before 'vertex' is "
                         "not supported.")
    elif words[0] == "property" and in_vertex:
      if words[1] == "list" or words[1] not in _PLY_TYPES:
        raise ValueError(f"{path}: unsupported vertex property "
                         f"{' '.join(words[1:])}.")
      fields.append((words[2], _PLY_TYPES[words[1]]))
  if count is None:
    raise ValueError(f"{path}: PLY file has no vertex element.")
  return count, np.dtype(fields)


def _check_finite(records: np.ndarray, path: str) -> None:
  """Raises ValueError naming the fields and rows with NaN or Inf values.

  Such a file is rejected, not loaded with those rows dead: a trainer never
  writes them (train.fit stops on non-finite values), so they mark a broken
  producer or a damaged file, and a loader that quietly drops rows would
  return a different model than the file claims to hold.
  """
  bad_rows = np.zeros(len(records), bool)
  counts = {}
  for name in records.dtype.names:
    if records.dtype[name].kind != "f":
      continue
    bad = ~np.isfinite(records[name])
    if bad.any():
      counts[name] = int(bad.sum())
      bad_rows |= bad
  if counts:
    fields = ", ".join(f"{n} in {c} rows" for n, c in counts.items())
    first = int(np.argmax(bad_rows))
    raise ValueError(
        f"{path}: {int(bad_rows.sum())} of {len(records)} vertices hold NaN "
        f"or Inf ({fields}; first row {first}); re-export the file or drop "
        "those rows.")


def read_ply(path: str, capacity: int | None = None
             ) -> tuple[gaussians.GaussianParams, jax.Array]:
  """Reads a 3DGS PLY (as written by `write_ply` or by 3DGS itself).

  Args:
    path: str, input file.
    capacity: int or None, number of slots C; default: the file's count N.
      Slots past N are dead (alive False, zero parameters, identity quats).

  Returns:
    (GaussianParams of float32 jax arrays with capacity C, alive bool [C]).
  """
  if not os.path.isfile(path):
    raise FileNotFoundError(f"PLY file not found: {path}")
  with open(path, "rb") as f:
    count, dtype = _read_header(f, path)
    data = f.read(count * dtype.itemsize)
  if len(data) < count * dtype.itemsize:
    raise ValueError(f"{path}: truncated, {len(data)} bytes of vertex data "
                     f"for {count} vertices of {dtype.itemsize} bytes.")
  records = np.frombuffer(data, dtype, count)
  _check_finite(records, path)
  names = set(dtype.names)
  rest_ids = sorted(int(m.group(1)) for name in names
                    if (m := re.fullmatch(r"f_rest_(\d+)", name)))
  k3 = len(rest_ids)
  required = set(_field_names(0)) - {"nx", "ny", "nz"}
  missing = sorted(required - names)
  if missing:
    raise ValueError(f"{path} is not a 3DGS PLY: vertex properties "
                     f"{missing} are missing.")
  if rest_ids != list(range(k3)) or k3 // 3 not in (0, 3, 8, 15) or k3 % 3:
    raise ValueError(f"{path}: expected f_rest_0 .. f_rest_{{3K-1}} with "
                     f"K in (0, 3, 8, 15) (SH degree 0-3), got {k3} f_rest "
                     "properties.")
  k = k3 // 3
  capacity = count if capacity is None else int(capacity)
  if capacity < count:
    raise ValueError(f"capacity={capacity} is smaller than the {count} "
                     f"Gaussians in {path}; pass a larger capacity.")

  def cols(*fields):
    out = np.zeros((capacity, len(fields)), np.float32)
    for i, f in enumerate(fields):
      out[:count, i] = records[f]
    return out

  rest = cols(*[f"f_rest_{i}" for i in range(k3)])
  quats = cols("rot_0", "rot_1", "rot_2", "rot_3")
  quats[count:, 0] = 1.0       # dead slots hold the identity rotation
  params = gaussians.GaussianParams(
      means=jnp.asarray(cols("x", "y", "z")),
      log_scales=jnp.asarray(cols("scale_0", "scale_1", "scale_2")),
      quats=jnp.asarray(quats),
      opacity_logits=jnp.asarray(cols("opacity")[:, 0]),
      sh_dc=jnp.asarray(cols("f_dc_0", "f_dc_1", "f_dc_2")),
      sh_rest=jnp.asarray(rest.reshape(capacity, 3, k).transpose(0, 2, 1)))
  alive = np.arange(capacity) < count
  return params, jnp.asarray(alive)
