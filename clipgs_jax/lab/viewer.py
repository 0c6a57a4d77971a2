"""A web viewer of finished runs on viser: splats, cameras, s_j, the prune.

`serve` shows one run (or two of the same scene, switched in the panel)
as Gaussian splats in the browser, the training and test cameras as
frustums (a click moves the view there and shows the view's photo, our
render, its transient map and ground-truth mask), and for guided runs
s_j as colour, a tau slider that highlights what a prune at that threshold
would remove, a switch that hides those rows, and the rows the run
pruned. The scene (cameras, photos) loads in a background thread, so the
splats are served at once (BUILD_NOTES.md, "Viewer and logs").
"""

import contextlib
import errno
import io
import signal
import socket
import sys
import threading
import time

import numpy as np
import viser
from viser import transforms as viser_tf

from clipgs_jax import camera as camera_lib
from clipgs_jax.lab import viewed_run

# Panel images are at most this wide (pixels), so a click sends little.
PANEL_WIDTH = 320
# Frustum size as a fraction of the camera positions' spread (scene.extent).
FRUSTUM_SCALE = 0.01
TRAIN_RGB, TEST_RGB, TRANSIENT_RGB = (60, 110, 255), (30, 170, 80), (255,
                                                                       140, 0)
# A client's view looks at a point this far along the camera's axis, as a
# fraction of scene.extent: the orbit centre of a moved view.
LOOK_DISTANCE = 0.5
# The start: the first training view, this far behind it (fraction of
# scene.extent), so that its frustum and the scene are both in sight.
START_BACK = 0.3
READY_LINE = "viewer: serving"       # the line a script waits for


def check_port(host: str, port: int) -> None:
  """Raises OSError naming `port` if nothing can listen on it.

  viser moves on to the next free port by itself; a viewer that answers on
  a port nobody asked for is worse than one clear error.
  """
  with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
    # As the server's own socket: a port left in TIME_WAIT is free.
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
      s.bind((host, port))
    except OSError as e:
      what = ("is in use" if e.errno == errno.EADDRINUSE
              else f"cannot be opened ({e.strerror})")
      raise OSError(f"--port={port}: {host}:{port} {what}; pass another "
                    "--port or stop what listens there") from e


def _wxyz_position(cam: camera_lib.Camera) -> tuple[np.ndarray, np.ndarray]:
  """The camera-to-world rotation (w, x, y, z) and centre; viser's
  cameras and frustums use the OpenCV axes, as camera.py does."""
  rot = np.asarray(cam.rotation, np.float64)
  return (viser_tf.SO3.from_matrix(rot.T).wxyz,
          np.asarray(camera_lib.camera_center(cam), np.float64))


def _vertical_fov(cam: camera_lib.Camera) -> float:
  return float(2 * np.arctan(camera_lib.tan_half_fov(cam)[1]))


def _small(image) -> np.ndarray:
  """uint8 [h, w, 3] of a float [H, W] or [H, W, 3] image in [0, 1], at
  most PANEL_WIDTH wide (nearest neighbour: masks stay binary)."""
  image = np.asarray(image, np.float32)
  if image.ndim == 2:
    image = np.repeat(image[..., None], 3, axis=-1)
  step = max(1, int(np.ceil(image.shape[1] / PANEL_WIDTH)))
  return (np.clip(image[::step, ::step], 0, 1) * 255).astype(np.uint8)


def pose(cam: camera_lib.Camera, extent: float, back: float = 0.0):
  """(position, look_at, up, vertical fov) of viser's camera at `cam`,
  `back` x `extent` behind it, orbiting a point ahead of it."""
  rot = np.asarray(cam.rotation, np.float64)
  _, centre = _wxyz_position(cam)
  position = centre - rot[2] * back * extent
  look_at = centre + rot[2] * LOOK_DISTANCE * extent
  return position, look_at, -rot[1], _vertical_fov(cam)


def start_pose(scene):
  """Where every client starts once the cameras are loaded."""
  return pose(viewed_run.camera(scene, "train", 0), scene.extent,
              START_BACK)


class Viewer:
  """The viser server and the state its panel edits (host-side only)."""

  def __init__(self, runs: list[viewed_run.ViewedRun],
               server: viser.ViserServer):
    self.runs, self.server = runs, server
    self.scene = None             # data.scene.Scene once loaded
    self.shown = 0                # index into runs
    self.selected = None          # (split, index) of the clicked view
    self.lock = threading.Lock()  # callbacks run in viser's thread pool
    self.nodes = []
    self.opacity_order = [np.argsort(-r.splats.opacities[:, 0],
                                     kind="stable") for r in runs]
    for i, run in enumerate(runs):
      s = run.splats
      self.nodes.append(server.scene.add_gaussian_splats(
          f"/runs/{i}/splats", s.centers, s.covariances, s.rgbs,
          s.opacities, visible=i == 0))
    self.pruned_nodes = [
        None if r.pruned is None or not len(r.pruned.centers) else
        server.scene.add_gaussian_splats(
            f"/runs/{i}/pruned", r.pruned.centers, r.pruned.covariances,
            r.pruned.rgbs, r.pruned.opacities, visible=False)
        for i, r in enumerate(runs)]
    self._build_panel()

  # The panel.

  def _build_panel(self) -> None:
    gui = self.server.gui
    if len(self.runs) > 1:
      self.run_choice = gui.add_dropdown(
          "run", tuple(f"{i}: {r.name}" for i, r in enumerate(self.runs)))
      self.run_choice.on_update(lambda _: self._switch_run())
    self.label = gui.add_markdown("")
    self.show_splats = gui.add_checkbox("Gaussians", True)
    self.show_splats.on_update(lambda _: self._update_splats())
    # Software WebGL (no GPU) draws ~1 frame/s per 10k Gaussians on the
    # 2-core box: drawing only the most opaque share keeps it usable.
    self.drawn = gui.add_slider("share drawn (most opaque)", 0.01, 1.0,
                                0.01, 1.0)
    self.drawn.on_update(lambda _: self._update_splats())
    with gui.add_folder("transient scores"):
      self.by_score = gui.add_checkbox("colour by s_j", False)
      self.tau = gui.add_slider("tau", 0.0, 1.0, 0.001, 0.5)
      self.highlight = gui.add_checkbox("highlight what a prune removes",
                                        False)
      self.hide = gui.add_checkbox("hide them (preview the prune)", False)
      self.show_pruned = gui.add_checkbox("rows the run pruned", False)
      self.prune_text = gui.add_markdown("")
    for handle in (self.by_score, self.tau, self.highlight, self.hide):
      handle.on_update(lambda _: self._update_splats())
    self.hide.on_update(lambda _: self._refresh_view())
    self.show_pruned.on_update(lambda _: self._update_pruned())
    self.views_text = gui.add_markdown("cameras: loading the scene ...")
    with gui.add_folder("clicked view"):
      self.view_text = gui.add_markdown("click a camera")
      blank = np.zeros((1, 1, 3), np.uint8)
      self.panel = {name: gui.add_image(blank, label=name, visible=False)
                    for name in ("photo", "render", "transient map",
                                 "ground-truth mask")}
    self._switch_run()

  def _run(self) -> viewed_run.ViewedRun:
    return self.runs[self.shown]

  def _switch_run(self) -> None:
    if len(self.runs) > 1:
      self.shown = int(self.run_choice.value.split(":")[0])
    run = self._run()
    guided = run.stats is not None
    self.label.content = (f"**{run.name}**: {run.info.get('guidance', '')}"
                          f", {len(run.splats.centers):,} Gaussians")
    low, high = viewed_run.score_range(run)
    sem = run.cfg.semantic
    self.tau.min, self.tau.max = low, high
    self.tau.step = (high - low) / 1000
    self.tau.precision = int(np.ceil(-np.log10(self.tau.step)))
    self.tau.value = run.cfg.pixel.tau_p if sem.localized else sem.tau
    for handle in (self.by_score, self.tau, self.highlight, self.hide):
      handle.disabled = not guided
    self.show_pruned.disabled = self.pruned_nodes[self.shown] is None
    for i, node in enumerate(self.nodes):
      node.visible = i == self.shown and self.show_splats.value
    self._update_splats()
    self._update_pruned()
    self._refresh_view()

  def _flagged(self) -> np.ndarray | None:
    """bool [N], the rows the prune preview marks, or None."""
    run = self._run()
    if run.stats is None or not (self.highlight.value or self.hide.value):
      return None
    out = viewed_run.would_prune(run, float(self.tau.value))
    return (np.zeros_like(out["by_score"]) if out["refused"]
            else out["by_score"] | out["faint"])

  def _update_splats(self) -> None:
    with self.lock:
      run, node = self._run(), self.nodes[self.shown]
      node.visible = bool(self.show_splats.value)
      flagged = self._flagged()
      rgbs = viewed_run.colors(
          run, bool(self.by_score.value) and run.stats is not None,
          flagged if self.highlight.value else None)
      opacities = run.splats.opacities
      if flagged is not None and self.hide.value:
        opacities = np.where(flagged[:, None], 0.0, opacities)
      s, keep = run.splats, self._drawn_rows()
      node.set_gaussians(s.centers[keep], s.covariances[keep], rgbs[keep],
                         opacities[keep].astype(np.float32))
      self.prune_text.content = self._prune_summary()

  def _drawn_rows(self) -> np.ndarray:
    """int [M], the rows drawn (in row order): all, or the most opaque
    share of them."""
    order = self.opacity_order[self.shown]
    return np.sort(order[:max(1, int(np.ceil(self.drawn.value
                                               * len(order))))])

  def _prune_summary(self) -> str:
    run = self._run()
    if run.stats is None:
      return "no s_j: a vanilla run (or one without its checkpoint)"
    out = viewed_run.would_prune(run, float(self.tau.value))
    if out["refused"]:
      return (f"a prune at tau = {self.tau.value:.3g} would be refused "
              "(more than max_prune_fraction of the Gaussians)")
    return (f"a prune at tau = {self.tau.value:.3g} removes "
            f"{int(out['by_score'].sum()):,} by s_j + "
            f"{int(out['faint'].sum()):,} faint, rarely seen")

  def _update_pruned(self) -> None:
    for i, node in enumerate(self.pruned_nodes):
      if node is not None:
        node.visible = i == self.shown and bool(self.show_pruned.value)

  # The cameras.

  def add_cameras(self, scene) -> None:
    """Frustums of every view, and the first training view as the start."""
    self.scene = scene
    scale = FRUSTUM_SCALE * scene.extent
    for split in viewed_run.SPLITS:
      vs = viewed_run.views(scene, split)
      for i in range(len(vs.names)):
        cam = viewed_run.camera(scene, split, i)
        wxyz, position = _wxyz_position(cam)
        masks = vs.masks
        color = (TRANSIENT_RGB if masks is not None and masks[i].any()
                 else TRAIN_RGB if split == "train" else TEST_RGB)
        frustum = self.server.scene.add_camera_frustum(
            f"/cameras/{split}/{i}", fov=_vertical_fov(cam),
            aspect=cam.width / cam.height, scale=scale, color=color,
            wxyz=wxyz, position=position)
        frustum.on_click(
            lambda event, s=split, j=i: self.select(event.client, s, j))
    self.views_text.content = (
        f"cameras: {len(scene.train.names)} training (blue; orange: with "
        f"transients), {len(scene.test.names)} test (green); click one")
    start = self.server.initial_camera
    at = start_pose(scene)
    start.position, start.look_at, start.up, start.fov = at
    # Clients that came before the cameras start there too.
    for client in self.server.get_clients().values():
      self._move(client, at)

  @staticmethod
  def _move(client, at) -> None:
    position, look_at, up, fov = at
    with client.atomic():
      client.camera.position = position
      client.camera.look_at = look_at
      client.camera.up_direction = up
      client.camera.fov = fov

  def select(self, client, split: str, index: int) -> None:
    """A frustum click: the view moves there and the panel shows it."""
    self._move(client, pose(viewed_run.camera(self.scene, split, index),
                            self.scene.extent))
    self.selected = (split, index)
    self._refresh_view()

  def _refresh_view(self) -> None:
    if self.selected is None or self.scene is None:
      return
    split, index = self.selected
    run, scene = self._run(), self.scene
    name = viewed_run.views(scene, split).names[index]
    self.view_text.content = f"{split} view {index}: {name} (rendering ...)"
    images = {
        "photo": viewed_run.views(scene, split).images[index],
        "render": viewed_run.render(run, scene, split, index,
                                    hidden=self._flagged()
                                    if self.hide.value else None),
        "transient map": viewed_run.transient_map(run, scene, split, index),
        "ground-truth mask": viewed_run.ground_truth_mask(scene, split,
                                                          index)}
    for key, image in images.items():
      handle = self.panel[key]
      handle.visible = image is not None
      if image is not None:
        handle.image = _small(image)
    self.view_text.content = f"{split} view {index}: {name}"


def _load_cameras(viewer: Viewer) -> None:
  """The background thread: the scene, then its frustums."""
  try:
    viewer.add_cameras(viewed_run.load_scene(viewer.runs[0]))
  except (OSError, ValueError) as e:
    message = " ".join(str(e).split())
    viewer.views_text.content = f"cameras: not loaded ({message})"
    print(f"viewer: the scene did not load, no cameras: {message}",
          file=sys.stderr, flush=True)


def serve(run_dir: str, compare_dir: str | None = None,
          host: str = "127.0.0.1", port: int = 8080) -> None:
  """Serves the viewer until Ctrl-C (or SIGTERM); prints READY_LINE with
  the address once the splats are served.

  Raises:
    OSError, ValueError: one line (not a run, no Gaussians, port in use).
  """
  tic = time.perf_counter()
  check_port(host, port)
  if compare_dir is not None:
    viewed_run.check_same_scene(run_dir, compare_dir)
  runs = [viewed_run.load(d) for d in (run_dir, compare_dir) if d is not None]
  with contextlib.redirect_stdout(io.StringIO()):   # its banner: ours below
    server = viser.ViserServer(host=host, port=port, verbose=False)
  try:
    if server.get_port() != port:      # taken between the check and here
      raise OSError(f"--port={port}: {host}:{port} is in use; pass another "
                    "--port or stop what listens there")
    viewer = Viewer(runs, server)
    threading.Thread(target=_load_cameras, args=(viewer,),
                     daemon=True).start()
    print(f"{READY_LINE} http://{host}:{port} after "
          f"{time.perf_counter() - tic:.1f} s (Ctrl-C stops it)",
          flush=True)
    # SIGTERM ends the viewer as Ctrl-C does, and so does SIGINT where the
    # shell started it with SIGINT ignored (a background job). pycolmap,
    # which the scene loader imports, installs glog's SIGTERM handler (a
    # stack dump) at import: imported first, it is replaced here.
    import pycolmap  # pylint: disable=g-import-not-at-top,unused-import
    for sig in (signal.SIGINT, signal.SIGTERM):
      signal.signal(sig, signal.default_int_handler)
    try:
      while True:
        time.sleep(1.0)
    except KeyboardInterrupt:
      pass
  finally:
    server.stop()
  print("viewer: stopped", flush=True)
