"""Headless Chromium for the viewer's tests: Debian's chromium through
Debian's chromedriver (selenium), screenshots as arrays, a frame counter."""

import io
import os
import shlex
import shutil
import tempfile
import time

import numpy as np
from PIL import Image

# Debian's names; .ci/run installs both (packages chromium and
# chromium-driver) when either is not on PATH.
CHROMIUM, CHROMEDRIVER = "chromium", "chromedriver"
# Small: swiftshader's time per frame grows with the pixels drawn.
WINDOW = (640, 480)
# How long a command may wait for the page: a software-rendered frame of a
# large scene blocks the page's thread for tens of seconds, minutes on a
# 2-core box with trainings beside the tests.
PAGE_WAIT_S = 300
# Headless as root, with no network but localhost, on a machine without a
# GPU: swiftshader is Chromium's software GL, which WebGL needs here.
FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-dev-shm-usage", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--disable-extensions")
# Run in the page before its own scripts: counts the animation frames in
# which WebGL drew anything (viser renders on demand, so an idle page
# draws nothing), and hides viser's notices (e.g. "software WebGL"), which
# come and go over the picture.
_PAGE_SETUP = """
window.__drawnFrames = 0;
const getContext = HTMLCanvasElement.prototype.getContext;
HTMLCanvasElement.prototype.getContext = function(type, attrs) {
  const gl = getContext.call(this, type, attrs);
  if (gl && type.startsWith('webgl') && !gl.__counted) {
    gl.__counted = true;
    for (const name of ['drawArrays', 'drawElements', 'drawArraysInstanced',
                        'drawElementsInstanced']) {
      const draw = gl[name];
      if (draw) gl[name] = function() {
        window.__drew = true; return draw.apply(this, arguments); };
    }
  }
  return gl;
};
(function tick() {
  if (window.__drew) { window.__drawnFrames++; window.__drew = false; }
  requestAnimationFrame(tick);
})();
document.addEventListener('DOMContentLoaded', () => {
  const style = document.createElement('style');
  style.textContent =
      '.mantine-Notifications-root { display: none !important; }';
  document.head.appendChild(style);
});
"""


def _driver_command(folder: str) -> str:
  """The driver binary selenium starts.

  As root, chromedriver starts Chromium at nice 0 and Chromium raises its
  browser and GPU processes to -8 (CAP_SYS_NICE), ahead of every other job
  on a shared box, whatever nice the test runs at. So as root the driver
  is started through a script that drops that capability from its
  bounding set (util-linux setpriv), which the browser inherits: both keep
  the test's nice value. A user without root has no such capability.
  """
  driver = shutil.which(CHROMEDRIVER)
  setpriv = shutil.which("setpriv")
  if os.geteuid() != 0 or setpriv is None:
    return driver
  script = os.path.join(folder, "chromedriver")
  with open(script, "w") as f:
    f.write(f"#!/bin/sh\nexec {shlex.quote(setpriv)} --bounding-set "
            f"-sys_nice {shlex.quote(driver)} \"$@\"\n")
  os.chmod(script, 0o755)
  return script


def missing() -> str | None:
  """Why the browser cannot run here, or None."""
  for name in (CHROMIUM, CHROMEDRIVER):
    if shutil.which(name) is None:
      return (f"{name} is not on PATH (apt-get install chromium "
              "chromium-driver; .ci/run does)")
  try:
    import selenium  # pylint: disable=g-import-not-at-top,unused-import
  except ImportError:
    return "selenium is not installed (pip install '.[test]')"
  return None


class Browser:
  """One headless Chromium with a fresh profile in a temporary folder;
  close() removes the folder."""

  def __init__(self, window: tuple[int, int] = WINDOW):
    # pylint: disable=g-import-not-at-top
    from selenium import webdriver
    from selenium.webdriver.chrome import service
    self.folder = tempfile.mkdtemp(prefix="chromium-")
    profile = os.path.join(self.folder, "profile")
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which(CHROMIUM)
    for flag in FLAGS + (f"--user-data-dir={profile}",
                         f"--window-size={window[0]},{window[1]}"):
      options.add_argument(flag)
    # The driver's path is given, so selenium never looks for (or
    # downloads) one.
    self.driver = webdriver.Chrome(service=service.Service(
        _driver_command(self.folder)),
                                   options=options)
    self.driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument",
                                {"source": _PAGE_SETUP})
    # Every script and command (a click too) waits for the page's frame;
    # selenium's client gives up on the driver after 120 s by default,
    # which the loaded box exceeded (12-06).
    self.driver.set_script_timeout(PAGE_WAIT_S)
    self.driver.command_executor.client_config.timeout = PAGE_WAIT_S
    # The page gets exactly `window` (headless Chromium's window size
    # counts a toolbar that it does not draw).
    self.driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", {
        "width": window[0], "height": window[1], "deviceScaleFactor": 1,
        "mobile": False})

  def open(self, url: str) -> None:
    self.driver.get(url)

  def screenshot(self) -> np.ndarray:
    """uint8 [H, W, 3] of the page as shown. Chromedriver stops waiting
    for a busy renderer after 10 s; this asks again for up to PAGE_WAIT_S
    (the loaded box's frames took longer, 12-06)."""
    # pylint: disable=g-import-not-at-top
    from selenium.common import exceptions
    end = time.monotonic() + PAGE_WAIT_S
    while True:
      try:
        png = self.driver.get_screenshot_as_png()
        break
      except exceptions.TimeoutException:
        if time.monotonic() > end:
          raise
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))

  def rect(self, css: str) -> tuple[int, int, int, int] | None:
    """(x, y, width, height) of the first element matching `css`."""
    r = self.driver.execute_script(
        "const e = document.querySelector(arguments[0]);"
        "if (!e) return null; const r = e.getBoundingClientRect();"
        "return [r.x, r.y, r.width, r.height];", css)
    return None if r is None else tuple(int(round(v)) for v in r)

  def viewport(self) -> tuple[int, int]:
    return tuple(self.driver.execute_script(
        "return [window.innerWidth, window.innerHeight];"))

  def click_label(self, text: str) -> None:
    """Clicks the panel control labelled `text` (a checkbox)."""
    label = self.driver.find_element(
        "xpath", f"//label[normalize-space()='{text}']")
    label.click()

  def set_number(self, text: str, value: float) -> None:
    """Types `value` into the number box of the slider labelled `text`."""
    # pylint: disable=g-import-not-at-top
    from selenium.webdriver.common import keys
    box = self.driver.find_element(
        "xpath", f"//label[normalize-space()='{text}']/following::input"
        "[contains(@class, 'NumberInput')][1]")
    box.send_keys(keys.Keys.CONTROL, "a")
    box.send_keys(str(value), keys.Keys.ENTER)

  def wait_for_text(self, text: str, timeout: float) -> None:
    end = time.monotonic() + timeout
    while text not in self.driver.find_element("tag name", "body").text:
      if time.monotonic() > end:
        raise TimeoutError(f"the page never showed {text!r}")
      time.sleep(0.25)

  def drawn_frames(self) -> int:
    return int(self.driver.execute_script("return window.__drawnFrames;"))

  def frames_per_second(self, seconds: float) -> float:
    """WebGL frames drawn per second while the page orbits the camera
    (synthetic pointer drags on the canvas, as a user's)."""
    self.driver.execute_script("""
      const canvas = document.querySelector('canvas');
      const r = canvas.getBoundingClientRect();
      const x0 = r.x + r.width / 2, y = r.y + r.height / 2;
      const ev = (type, x) => canvas.dispatchEvent(new PointerEvent(type, {
          clientX: x, clientY: y, pointerId: 1, pointerType: 'mouse',
          button: 0, buttons: type === 'pointerup' ? 0 : 1,
          bubbles: true}));
      ev('pointerdown', x0);
      const t0 = performance.now();
      window.__orbit = setInterval(() => {
        const t = performance.now() - t0;
        ev('pointermove', x0 + 120 * Math.sin(t / 700));
      }, 8);
      window.__stopOrbit = () => {
        clearInterval(window.__orbit); ev('pointerup', x0); };
    """)
    time.sleep(1.0)                          # the first frames start it
    first, tic = self.drawn_frames(), time.monotonic()
    time.sleep(seconds)
    frames, elapsed = self.drawn_frames() - first, time.monotonic() - tic
    self.driver.execute_script("window.__stopOrbit();")
    return frames / elapsed

  def close(self) -> None:
    try:
      self.driver.quit()
    finally:
      shutil.rmtree(self.folder, ignore_errors=True)
