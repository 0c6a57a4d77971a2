"""A batch of views per step, dealt over every device.

With batch size B the training views are dealt into B lanes (lane j holds
views j, j + B, j + 2B, ... of the split, in order) and a step takes one
view from every lane: lane j's views come in a fresh random order each of
its epochs (view.view_index on view.lane_key(key, j); lane 0 has the
run's key, so B = 1 is the one-view order). The lanes are sharded over a
one-axis mesh (AXIS) of every device of every process, B / D lanes per
device, so a device holds only its lanes' photos, cameras and per-view
maps, and a process of a multi-host run reads only its lanes' photos
(`holds`, data.scene.load_scene's train_views). Everything else is
replicated: the parameters, Adam's moments, every per-row statistic and
the PRNG key (step.py says how a step combines its views).
"""

import os
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec

from clipgs_jax import camera as camera_lib
from clipgs_jax.data import scene as scene_lib

AXIS = "views"       # the mesh's one axis: the batch's views


def join(coordinator_address: str | None = None,
         num_processes: int | None = None,
         process_id: int | None = None) -> bool:
  """Joins a multi-host run (jax.distributed.initialize) when asked to.

  Asked: any argument given, or $JAX_COORDINATOR_ADDRESS set (the address
  of process 0, host:port); what is not given comes from the environment
  JAX reads or its cluster detection (SLURM, Open MPI, Kubernetes, Cloud
  TPU). CPU processes exchange gradients over gloo. Must run before
  anything touches a device.

  Returns:
    Whether it joined one.
  """
  if (coordinator_address is None and num_processes is None
      and process_id is None and not os.environ.get("JAX_COORDINATOR_ADDRESS")):
    return False
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(coordinator_address=coordinator_address,
                             num_processes=num_processes,
                             process_id=process_id)
  return True


def make_mesh(batch_size: int, devices=None) -> Mesh:
  """The one-axis mesh over `devices` (default: every device of every
  process; one device for batch_size 1 in one process).

  Raises:
    ValueError: batch_size does not divide over the devices.
  """
  if devices is None:
    devices = jax.devices()
    if batch_size == 1 and jax.process_count() == 1:
      devices = devices[:1]
  if batch_size % len(devices):
    raise ValueError(
        f"--config.train.batch_size={batch_size} does not divide over the "
        f"{len(devices)} devices; use a multiple of {len(devices)}, or hide "
        "devices (e.g. CUDA_VISIBLE_DEVICES).")
  return Mesh(np.array(devices), (AXIS,))


def held_lanes(mesh: Mesh, batch_size: int) -> list[int]:
  """The lanes whose device belongs to this process, in mesh order."""
  per = batch_size // mesh.size
  return [k * per + i for k, d in enumerate(mesh.devices.flat)
          if d.process_index == jax.process_index() for i in range(per)]


def holds(view: int, batch_size: int, lanes) -> bool:
  """Whether a process holding `lanes` needs training view `view`."""
  return view % batch_size in lanes


def lane_length(num_views: int, batch_size: int) -> int:
  """L: the views of the longest lane."""
  return -(-num_views // batch_size)


@flax.struct.dataclass
class Lanes:
  """The training views dealt into lanes (a device's share inside a step).

  Attributes:
    images: float32 [B, L, H, W, 3], lane j's photos (position p is view
      j + p B); positions past the lane's count are zero and never read.
    cameras: camera.Camera with [B, L] fields; width and height are the
      canvas's.
    sizes: int32 [B, L, 2], each photo's width and height on the canvas
      (data.scene.Views.sizes), or None when every photo fills it.
    counts: int32 [B], the views of each lane.
  """
  images: jax.Array
  cameras: camera_lib.Camera
  sizes: jax.Array | None
  counts: jax.Array


def _rows(views, num_views: int, batch_size: int, lanes) -> np.ndarray:
  """int [len(lanes), L]: rows of `views` at each lane position, -1 where
  the lane is shorter."""
  ids = getattr(views, "ids", None)
  ids = np.arange(len(views.names)) if ids is None else np.asarray(ids)
  row_of = {int(v): r for r, v in enumerate(ids)}
  length = lane_length(num_views, batch_size)
  rows = np.full((len(lanes), length), -1, np.int64)
  for i, lane in enumerate(lanes):
    for p, view in enumerate(range(lane, num_views, batch_size)):
      if view not in row_of:
        raise ValueError(f"sharding: training view {view} of lane {lane} "
                         "was not loaded by this process; load the scene "
                         "with train_views=sharding.holds for its lanes.")
      rows[i, p] = row_of[view]
  return rows


def _deal(x, rows: np.ndarray) -> np.ndarray:
  """x [V, ...] to [lanes, L, ...] by `rows`; -1 rows are zero."""
  x = np.asarray(x)
  out = x[np.maximum(rows, 0)]
  out[rows < 0] = 0
  return out


def _pad_canvas(x: np.ndarray, height: int, width: int) -> np.ndarray:
  """[lanes, L, h, w, ...] zero-padded to [lanes, L, height, width, ...]."""
  pad = [(0, 0), (0, 0), (0, height - x.shape[2]), (0, width - x.shape[3])]
  return np.pad(x, pad + [(0, 0)] * (x.ndim - 4))


def canvas_of(scene) -> tuple[int, int]:
  """(width, height) of the canvas every process's lanes share: the
  largest of their training images."""
  height, width = np.shape(scene.train.images)[1:3]
  size = np.array([width, height], np.int64)
  if jax.process_count() > 1:
    size = np.max(multihost_utils.process_allgather(size), axis=0)
  return int(size[0]), int(size[1])


def _place(x: np.ndarray, mesh: Mesh) -> jax.Array:
  """A global array sharded along its first axis (the lanes) from this
  process's lanes `x` [lanes held, ...] (held_lanes order)."""
  sharding = NamedSharding(mesh, PartitionSpec(AXIS))
  local = [d for d in mesh.devices.flat
           if d.process_index == jax.process_index()]
  per = x.shape[0] // len(local)
  shape = (per * mesh.size,) + x.shape[1:]
  return jax.make_array_from_single_device_arrays(
      shape, sharding,
      [jax.device_put(x[k * per:(k + 1) * per], d)
       for k, d in enumerate(local)])


def lanes_of(scene, batch_size: int, mesh: Mesh
             ) -> tuple[Lanes, np.ndarray]:
  """The device-resident Lanes of this process's training views.

  Args:
    scene: data.scene.Scene whose train Views hold (at least) this
      process's lanes' views (Views.ids says which).
    batch_size: B.
    mesh: make_mesh(B).
  Returns:
    (Lanes sharded over the mesh, int [lanes held, L] rows of
    scene.train per lane position, for `scorer_lanes`).
  """
  views = scene.train
  num_views = len(np.asarray(scene_lib.all_train_cameras(scene).fx))
  if num_views < batch_size:
    raise ValueError(f"--config.train.batch_size={batch_size} exceeds the "
                     f"{num_views} training views; lower it.")
  rows = _rows(views, num_views, batch_size, held_lanes(mesh, batch_size))
  height, width = np.shape(views.images)[1:3]
  cams = views.cameras
  if np.ndim(views.images) != 4 or (cams.width, cams.height) != (width,
                                                                height):
    raise ValueError(f"sharding.lanes_of: cameras are {cams.width}x"
                     f"{cams.height} but images are "
                     f"{np.shape(views.images)}; images must be [V, "
                     f"{cams.height}, {cams.width}, 3].")
  cw, ch = canvas_of(scene)
  sizes = getattr(views, "sizes", None)
  if sizes is None and (cw, ch) != (width, height):
    sizes = np.tile(np.array([width, height], np.int32), (len(views), 1))
  images = _pad_canvas(_deal(np.asarray(views.images, np.float32), rows),
                       ch, cw)
  cams = jax.tree.map(lambda x: _place(_deal(np.asarray(x, np.float32), rows),
                                       mesh), views.cameras)
  cams = cams.replace(width=cw, height=ch)
  counts = np.sum(rows >= 0, axis=1).astype(np.int32)
  lanes = Lanes(images=_place(images, mesh), cameras=cams,
                sizes=None if sizes is None else _place(
                    _deal(np.asarray(sizes, np.int32), rows), mesh),
                counts=_place(counts, mesh))
  return lanes, rows


# Scorer fields with one entry per training view (a leading [V] axis),
# named by each scorer class's `per_view` attribute: they are dealt into
# lanes like the photos; every other leaf is replicated.
def _per_view_fields(scorer) -> tuple[str, ...]:
  return tuple(f for f in getattr(scorer, "per_view", ())
               if getattr(scorer, f) is not None)


def scorer_lanes(scorer, rows: np.ndarray, height: int, width: int,
                 mesh: Mesh):
  """The scorer with its per-view fields dealt into lanes [B, L, ...] on
  the `height` x `width` canvas and sharded; the rest replicated."""
  if scorer is None:
    return None
  fields = _per_view_fields(scorer)
  dealt = {}
  for f in fields:
    x = _deal(np.asarray(getattr(scorer, f)), rows)
    if x.ndim >= 4:
      x = _pad_canvas(x, height, width)
    dealt[f] = _place(x, mesh)
  # The per-view fields differ between processes: only the rest is
  # replicated.
  shared = replicate(scorer.replace(**dict.fromkeys(fields)), mesh)
  return shared.replace(**dealt)


def scorer_specs(scorer):
  """shard_map in_specs of a scorer from `scorer_lanes` (None for None)."""
  if scorer is None:
    return PartitionSpec()
  specs = jax.tree.map(lambda _: PartitionSpec(), scorer)
  return specs.replace(**{f: PartitionSpec(AXIS)
                          for f in _per_view_fields(scorer)})


def scorer_at(scorer, i):
  """Inside a step: the scorer of local lane i, its per-view fields [L,
  ...], indexed by position in the lane."""
  if scorer is None:
    return None
  return scorer.replace(**{f: getattr(scorer, f)[i]
                           for f in _per_view_fields(scorer)})


def lanes_specs(lanes: Lanes):
  return jax.tree.map(lambda _: PartitionSpec(AXIS), lanes)


def replicate(tree: Any, mesh: Mesh) -> Any:
  """`tree` (equal on every process) replicated on every device of `mesh`.

  PRNG keys travel as their key data."""
  sharding = NamedSharding(mesh, PartitionSpec())

  def put(x):
    if isinstance(x, jax.Array) and jax.dtypes.issubdtype(
        x.dtype, jax.dtypes.prng_key):
      return jax.random.wrap_key_data(
          jax.device_put(jax.random.key_data(x), sharding),
          impl=jax.random.key_impl(x))
    return jax.device_put(x, sharding)
  return jax.tree.map(put, tree)


def valid_mask(size: jax.Array, height: int, width: int) -> jax.Array:
  """float32 [height, width], 1 on the size[0] x size[1] photo in the
  canvas's top-left corner."""
  rows = jnp.arange(height)[:, None] < size[1]
  cols = jnp.arange(width)[None, :] < size[0]
  return (rows & cols).astype(jnp.float32)


def local(tree: Any) -> Any:
  """`tree` with every array on several devices (replicated) replaced by
  its copy on one of this process's devices; other leaves as they are."""
  def one(x):
    if isinstance(x, jax.Array) and len(x.sharding.device_set) > 1:
      return x.addressable_data(0)
    return x
  return jax.tree.map(one, tree)


def is_writer() -> bool:
  """Whether this process writes the run's files (process 0)."""
  return jax.process_index() == 0
