"""Videos of finished runs: a smooth camera path, runs side by side with
their labels (and s_j as a colour overlay), written as H.264 MP4 or GIF."""

import dataclasses
import os
import warnings

import jax
import jax.numpy as jnp
from matplotlib import colormaps
import numpy as np
from PIL import Image
from PIL import ImageDraw
from PIL import ImageFont
from scipy import interpolate
from scipy.spatial import transform
import tqdm

from clipgs_jax import camera as camera_lib
from clipgs_jax import evaluation
from clipgs_jax import fileio
from clipgs_jax import gaussians
from clipgs_jax import run as run_lib
from clipgs_jax import sh
from clipgs_jax.data import scene as scene_lib
from clipgs_jax.lab import viewed_run

# orbit: an ellipse fitted to the training cameras; train, test: through
# those cameras in name order.
PATHS = ("orbit", "train", "test")
FORMATS = (".mp4", ".gif")
# Share of the s_j colour in a frame with the overlay: enough to read the
# colour map, little enough to recognise the scene under it.
OVERLAY_WEIGHT = 0.5
# The label strip above each panel: its text height in pixels is this share
# of the panel's width, at most LABEL_MAX_SIZE, and shrinks (down to
# LABEL_MIN_SIZE, then the label is cut) until the label fits the width.
LABEL_WIDTH_SHARE = 1 / 16
LABEL_MAX_SIZE = 24
LABEL_MIN_SIZE = 6
# H.264's 4:2:0 chroma halves both sides, so the frame's are made even.
_EVEN = 2


@dataclasses.dataclass(frozen=True)
class Plan:
  """What a video shows, checked before any Gaussians or photos are read.

  Attributes:
    runs: 1 or 2 run folders, left to right.
    path: one of PATHS.
    frames: int, frames in the video (seconds x fps, at least 2).
    fps: float, frames per second.
    out: str, the .mp4 or .gif file.
    scores: bool, s_j as a colour overlay where a run has it.
  """
  runs: tuple[str, ...]
  path: str
  frames: int
  fps: float
  out: str
  scores: bool


def plan(run: str, compare: str | None, path: str, seconds: float,
         fps: float, out: str, scores: bool = False) -> Plan:
  """The checked Plan of a video: flags, run folders and the output only.

  Raises:
    ValueError, FileNotFoundError: one line naming the flag and the fix.
  """
  if path not in PATHS:
    raise ValueError(f"--path={path} is not one of {', '.join(PATHS)}")
  if not fps > 0:
    raise ValueError(f"--fps={fps:g} must be positive (30 is usual)")
  if not seconds > 0:
    raise ValueError(f"--seconds={seconds:g} must be positive")
  frames = int(round(seconds * fps))
  if frames < 2:
    raise ValueError(f"--seconds={seconds:g} at --fps={fps:g} is {frames} "
                     "frame(s); a video needs at least 2")
  ext = os.path.splitext(out)[1].lower()
  if ext not in FORMATS:
    raise ValueError(f"--out={out} must end in {' or '.join(FORMATS)}")
  folder = os.path.dirname(os.path.abspath(out))
  if not os.path.isdir(folder) or os.path.isdir(out):
    raise FileNotFoundError(f"--out={out}: " + (
        f"{out} is a folder; name a file in it" if os.path.isdir(out) else
        f"its folder {folder} does not exist; create it first"))
  viewed_run.read_info(run)
  if compare is not None:
    viewed_run.check_same_scene(run, compare)
  return Plan(runs=(run,) if compare is None else (run, compare), path=path,
              frames=frames, fps=float(fps), out=out, scores=scores)


def _look_at_point(rotations: np.ndarray, centers: np.ndarray) -> np.ndarray:
  """float64 [3], the point nearest to every camera's optical axis (least
  squares): what an orbit looks at."""
  axes = rotations[:, 2]                             # [V, 3] viewing rays
  proj = np.eye(3) - axes[:, :, None] * axes[:, None, :]   # [V, 3, 3]
  lhs, rhs = proj.sum(0), np.einsum("vij,vj->i", proj, centers)
  return np.linalg.lstsq(lhs, rhs, rcond=None)[0]


def orbit(cams: camera_lib.Camera, n: int) -> camera_lib.Camera:
  """n cameras on an ellipse fitted to the cameras `cams` ([V] stacked),
  looking at the point nearest their optical axes, with their mean up
  vector, starting at the first camera and turning as the captures do.

  The ellipse lies in the plane of the camera centres' two main axes
  (PCA), through their mean, with semi-axes sqrt(2) x the centres' spread
  along each: the exact ellipse for centres spaced evenly around one.
  """
  rot = np.asarray(cams.rotation, np.float64)
  centers = camera_lib.camera_center(cams).astype(np.float64)   # [V, 3]
  mean = centers.mean(0)
  _, _, basis = np.linalg.svd(centers - mean, full_matrices=False)
  uv = (centers - mean) @ basis[:2].T                           # [V, 2]
  radii = np.sqrt(2.0) * uv.std(0)
  if radii[0] <= 1e-9 * max(1.0, np.abs(mean).max()):
    raise ValueError("--path=orbit: the training cameras share one position, "
                     "so no orbit fits them; pass --path=train")
  # Cameras on a line give a flat ellipse: the orbit runs along it.
  radii = np.maximum(radii, 1e-6 * radii[0])
  angles = np.unwrap(np.arctan2(uv[:, 1] / radii[1], uv[:, 0] / radii[0]))
  turn = 1.0 if angles[-1] >= angles[0] else -1.0
  theta = angles[0] + turn * 2 * np.pi * np.arange(n) / n      # [n]
  eyes = mean + (radii[0] * np.cos(theta))[:, None] * basis[0] + (
      radii[1] * np.sin(theta))[:, None] * basis[1]
  target = _look_at_point(rot, centers)
  up = -rot[:, 1].mean(0)           # image up is the camera's -y
  first = camera_lib.camera_at(cams, 0)
  return _stack([camera_lib.look_at(e, target, up, float(first.fx),
                                    float(first.fy), cams.width, cams.height)
                 for e in eyes])


def through(cams: camera_lib.Camera, n: int) -> camera_lib.Camera:
  """n cameras along the cameras `cams` ([V] stacked, V >= 2) in order:
  centres on a cubic spline, rotations on a rotation spline, intrinsics
  linear, each key camera at an even share of the time."""
  rot = np.asarray(cams.rotation, np.float64)
  keys = np.arange(len(rot), dtype=np.float64)
  times = np.linspace(0.0, keys[-1], n)
  centers = interpolate.CubicSpline(keys, camera_lib.camera_center(cams))(
      times)
  # Our R is world-to-camera; the spline runs on camera-to-world.
  rotations = transform.RotationSpline(
      keys, transform.Rotation.from_matrix(rot.transpose(0, 2, 1)))(
          times).as_matrix().transpose(0, 2, 1)                # [n, 3, 3]
  intr = {k: np.interp(times, keys, np.asarray(getattr(cams, k), np.float64))
          for k in ("fx", "fy", "cx", "cy")}
  return _stack([camera_lib.Camera.create(
      r, -r @ c, *(intr[k][i] for k in ("fx", "fy", "cx", "cy")),
      cams.width, cams.height) for i, (r, c) in enumerate(
          zip(rotations, centers))])


def _stack(cams: list[camera_lib.Camera]) -> camera_lib.Camera:
  return jax.tree.map(lambda *x: np.stack(x), *cams)


def camera_path(scene, path: str, n: int) -> camera_lib.Camera:
  """The n cameras of `path` (PATHS) for a loaded scene.

  Raises:
    ValueError: the split has fewer than 2 cameras.
  """
  cams = (scene_lib.all_train_cameras(scene) if path != "test"
          else scene.test.cameras)
  count = len(np.asarray(cams.fx))
  if count < 2:
    split = "training" if path != "test" else "test"
    raise ValueError(f"--path={path}: the run's scene has {count} {split} "
                     "view(s); a path needs at least 2 (pick another --path)")
  return orbit(cams, n) if path == "orbit" else through(cams, n)


def label(run: viewed_run.ViewedRun) -> str:
  """A panel's label: the run folder's name and its test PSNR."""
  path = os.path.join(run.path, run_lib.METRICS_JSON)
  if not os.path.isfile(path):
    return run.name
  psnr = run_lib.read_json(path, "test metrics")["test"]["psnr"]
  return f"{run.name}  {psnr:.2f} dB"


def _score_params(run: viewed_run.ViewedRun) -> gaussians.GaussianParams:
  """The run's Gaussians coloured by s_j (viewed_run's colour map), with no
  view-dependent colour."""
  rgb = viewed_run.colors(run, by_score=True)
  return run.params.replace(sh_dc=sh.rgb_to_dc(jnp.asarray(rgb)),
                            sh_rest=jnp.zeros_like(run.params.sh_rest))


def _label_strip(text: str, width: int) -> np.ndarray:
  """uint8 [h, width, 3], `text` in white on black."""
  size = int(np.clip(width * LABEL_WIDTH_SHARE, LABEL_MIN_SIZE,
                     LABEL_MAX_SIZE))
  font = ImageFont.load_default(size=size)
  while size > LABEL_MIN_SIZE and font.getlength(text) > width - 4:
    size -= 1
    font = ImageFont.load_default(size=size)
  strip = Image.new("RGB", (width, size + 4))
  ImageDraw.Draw(strip).text((2, 1), text, fill=(255, 255, 255), font=font)
  return np.asarray(strip)


def frames(runs: list[viewed_run.ViewedRun], cams: camera_lib.Camera,
           scores: bool):
  """uint8 [H, W, 3] frames: each run's render of each camera, side by
  side under its label, with s_j over it (OVERLAY_WEIGHT) where `scores`
  and the run has s_j; sides padded to even sizes."""
  strips = [_label_strip(label(r) + (" + s_j" if scores and r.scores
                                     is not None else ""), cams.width)
            for r in runs]
  coloured = [_score_params(r) if scores and r.scores is not None else None
              for r in runs]
  alive = [jnp.ones(r.params.means.shape[0], bool) for r in runs]
  for i in range(len(np.asarray(cams.fx))):
    cam = camera_lib.camera_at(cams, i)
    panels = []
    for r, strip, by_score, live in zip(runs, strips, coloured, alive):
      image = evaluation.render_camera(r.params, live, cam, r.cfg)
      if by_score is not None:
        image = (1 - OVERLAY_WEIGHT) * image + OVERLAY_WEIGHT * (
            evaluation.render_camera(by_score, live, cam, r.cfg))
      pixels = np.asarray(jnp.round(image * 255), np.uint8)
      panels.append(np.concatenate([strip, pixels], 0))
    frame = np.concatenate(panels, 1)
    pad = [(0, -s % _EVEN) for s in frame.shape[:2]] + [(0, 0)]
    yield np.pad(frame, pad)


def _write_mp4(tmp: str, frames_iter, size, fps: float) -> None:
  import imageio_ffmpeg  # pylint: disable=import-outside-toplevel
  writer = imageio_ffmpeg.write_frames(
      tmp, size, fps=fps, codec="libx264", pix_fmt_out="yuv420p",
      macro_block_size=_EVEN, ffmpeg_log_level="error", quality=8)
  with warnings.catch_warnings():
    # JAX warns on any fork; this one is subprocess's fork-then-exec of
    # ffmpeg, which runs no Python (and takes no lock) in the child.
    warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
    writer.send(None)                    # starts ffmpeg
  try:
    for frame in frames_iter:
      writer.send(np.ascontiguousarray(frame))
  finally:
    writer.close()


def _write_gif(tmp: str, frames_iter, fps: float) -> None:
  images = [Image.fromarray(f) for f in frames_iter]
  images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:],
                 duration=round(1000 / fps), loop=0)


def write(p: Plan, progress: bool = True) -> dict:
  """Renders the video `p` describes and writes it atomically.

  Returns:
    {"out", "frames", "fps", "size": [W, H], "path"}.
  """
  runs = [viewed_run.load(r) for r in p.runs]
  scene = viewed_run.load_scene(runs[0])
  cams = camera_path(scene, p.path, p.frames)
  frame_iter = frames(runs, cams, p.scores)
  first = next(frame_iter)
  size = (first.shape[1], first.shape[0])
  every = tqdm.tqdm(_chain(first, frame_iter), total=p.frames, unit="frame",
                    disable=not progress)
  if p.out.lower().endswith(".gif"):
    fileio.atomic_write(p.out, lambda tmp: _write_gif(tmp, every, p.fps),
                        ".gif")
  else:
    fileio.atomic_write(p.out, lambda tmp: _write_mp4(tmp, every, size,
                                                      p.fps), ".mp4")
  return {"out": os.path.abspath(p.out), "frames": p.frames, "fps": p.fps,
          "size": list(size), "path": p.path}


def _chain(first, rest):
  yield first
  yield from rest
