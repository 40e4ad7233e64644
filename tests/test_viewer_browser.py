"""Browser check of ns-viewer on an EDyGS run: the page loads, the time slider moves, and the
output dropdown offers our outputs. Skipped when Debian's chromium is not installed (this is a
browser check, not a core test); screenshots are written to the test's tmp folder.

Chromium runs headless with its DevTools protocol on a local port; the test drives it through
a plain websocket (websocket-client): evaluate JavaScript, press keys, capture screenshots.
"""

from __future__ import annotations

import base64
import json
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any, Callable, Optional

import pytest
from test_eval_cli import train_tiny_run

CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="browser check: Debian chromium is not installed")

#: Browser window size, pixels.
WINDOW_W, WINDOW_H = 1280, 800
#: Flags of the headless browser (no sandbox as root, no network chatter, software WebGL).
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--no-first-run", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", f"--window-size={WINDOW_W},{WINDOW_H}",
)  # fmt: skip
#: Seconds to wait for the viewer server, the browser, the GUI and a render.
SERVER_TIMEOUT_S = 120.0
BROWSER_TIMEOUT_S = 30.0
GUI_TIMEOUT_S = 60.0
RENDER_SETTLE_S = 6.0
POLL_S = 0.25
#: A point inside the 3D viewport (left of the control panel), pixels.
CENTRE_X, CENTRE_Y = 480.0, 330.0
#: DevTools key code of the End key.
END_KEY_CODE = 35
#: Outputs the model adds beyond rgb, which the dropdown must list.
EXPECTED_OUTPUTS = ("mask", "rgb_static", "depth")
#: Training steps of the run shown in the viewer.
TRAIN_STEPS = 2
#: Std of the random weights put into the deformation's position head, so that renders depend on time.
HEAD_WEIGHT_STD = 2.0
#: Mask logit given to every Gaussian (m ~ 0.95, above the model's deformation threshold).
DYNAMIC_LOGIT = 3.0
#: Mouse-wheel steps (and delta, pixels) that zoom the viewer camera out until the scene is in view.
ZOOM_OUT_STEPS = 15
ZOOM_DELTA_PX = 300.0
#: A viewport pixel "changed" between two screenshots when its grey level moved by more than this.
CHANGED_LEVELS = 2.0
#: Moving time must change at least this many viewport pixels, and this many times more than two
#: screenshots taken at the same time do (render noise / progressive refinement).
MIN_CHANGED_PIXELS = 200
CHANGE_OVER_NOISE = 4


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _wait_for(check: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = check()
        except (OSError, ValueError):
            value = None
        if value:
            return value
        time.sleep(POLL_S)
    raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")


class DevTools:
    """Minimal Chrome DevTools Protocol client over one page's websocket."""

    def __init__(self, websocket_url: str) -> None:
        import websocket  # websocket-client

        self.ws = websocket.create_connection(websocket_url, timeout=BROWSER_TIMEOUT_S, suppress_origin=True)
        self.next_id = 0

    def call(self, method: str, **params: Any) -> dict:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv())
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError(f"DevTools {method}: {reply['error']}")
                return reply.get("result", {})

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        return result.get("result", {}).get("value")

    def key(self, key: str, code: str, key_code: int) -> None:
        for kind in ("keyDown", "keyUp"):
            self.call("Input.dispatchKeyEvent", type=kind, key=key, code=code, windowsVirtualKeyCode=key_code)

    def wheel(self, x: float, y: float, delta_y: float) -> None:
        self.call("Input.dispatchMouseEvent", type="mouseWheel", x=x, y=y, deltaX=0, deltaY=delta_y)

    def screenshot(self, path: Path) -> Path:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        path.write_bytes(base64.b64decode(data))
        return path

    def close(self) -> None:
        self.ws.close()


def _page_websocket(port: int) -> Optional[str]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=POLL_S * 4) as reply:
        pages = [t for t in json.loads(reply.read()) if t.get("type") == "page"]
    return pages[0]["webSocketDebuggerUrl"] if pages else None


def _http_ok(port: int) -> bool:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=POLL_S * 4) as reply:
        return reply.status == 200


#: JavaScript: the Time slider of the control panel (a Mantine slider whose label reads "Time").
FIND_TIME_SLIDER = """
(() => {
  const labels = [...document.querySelectorAll('label, p, div')].filter(e => e.childElementCount === 0 && e.textContent.trim() === 'Time');
  for (const label of labels) {
    let node = label;
    for (let depth = 0; depth < 6 && node; depth++, node = node.parentElement) {
      const slider = node.querySelector('[role="slider"]');
      if (slider) return slider;
    }
  }
  return null;
})()
"""


def _make_time_visible(config: Path) -> None:
    """Give the run's deformation a time-dependent position offset (its heads start at zero, and
    two training steps leave them there), so that moving the time slider changes the render."""
    import torch

    checkpoint = sorted((config.parent / "nerfstudio_models").glob("step-*.ckpt"))[-1]
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    generator = torch.Generator().manual_seed(0)
    keys = [k for k in state["pipeline"] if k.endswith("deformation.head_xyz.weight")]
    assert keys, f"{checkpoint} holds no deformation head"
    for key in keys:
        state["pipeline"][key] = torch.randn(state["pipeline"][key].shape, generator=generator) * HEAD_WEIGHT_STD
    for key in [k for k in state["pipeline"] if k.endswith("gauss_params.mask_logit")]:
        state["pipeline"][key] = torch.full_like(state["pipeline"][key], DYNAMIC_LOGIT)  # deformed everywhere
    torch.save(state, checkpoint)


def _viewport(tools: DevTools, screenshot: Path):
    """The 3D viewport (the largest canvas) cut out of a screenshot, as a float grey array."""
    import numpy as np
    from PIL import Image

    box = tools.evaluate(
        "(() => { const c = [...document.querySelectorAll('canvas')].sort((a, b) => b.width * b.height - a.width * a.height)[0];"
        " const r = c.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom].map(Math.round); })()"
    )
    with Image.open(screenshot) as image:
        return np.asarray(image.convert("L").crop(tuple(box)), dtype=np.float32)


@pytest.fixture(scope="module")
def viewer_page(tmp_path_factory):
    """A trained tiny run shown by ns-viewer, opened in headless Chromium: yields (DevTools, folder)."""
    root = tmp_path_factory.mktemp("viewer")
    config = train_tiny_run(root, steps=TRAIN_STEPS)
    _make_time_visible(config)
    viewer_port, debug_port = _free_port(), _free_port()
    viewer_log = open(root / "ns-viewer.log", "wb")
    viewer = subprocess.Popen(
        [str(Path(sys.executable).parent / "ns-viewer"), "--load-config", str(config), "--viewer.websocket-port", str(viewer_port)],
        stdout=viewer_log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    browser = None
    tools = None
    try:
        _wait_for(lambda: viewer.poll() is None and _http_ok(viewer_port), SERVER_TIMEOUT_S, "ns-viewer to serve its page")
        browser = subprocess.Popen(
            [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={root / 'chromium-profile'}", f"--remote-debugging-port={debug_port}",
             f"http://127.0.0.1:{viewer_port}/"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        tools = DevTools(_wait_for(lambda: _page_websocket(debug_port), BROWSER_TIMEOUT_S, "the browser page"))
        _wait_for(lambda: tools.evaluate(f"!!{FIND_TIME_SLIDER}"), GUI_TIMEOUT_S, "the viewer's Time slider")
        for _ in range(ZOOM_OUT_STEPS):  # the default viewer camera starts inside the tiny scene
            tools.wheel(CENTRE_X, CENTRE_Y, ZOOM_DELTA_PX)
        time.sleep(RENDER_SETTLE_S)
        yield tools, root
    finally:
        if tools is not None:
            tools.close()
        for process in (browser, viewer):
            if process is not None and process.poll() is None:
                process.terminate()
                try:
                    process.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    process.kill()
        viewer_log.close()


def _slider_value(tools: DevTools) -> float:
    return float(tools.evaluate(f"{FIND_TIME_SLIDER}.getAttribute('aria-valuenow')"))


def _changed_pixels(tools: DevTools, first: Path, second: Path) -> int:
    return int((abs(_viewport(tools, second) - _viewport(tools, first)) > CHANGED_LEVELS).sum())


def test_time_slider_changes_the_render(viewer_page):
    tools, root = viewer_page
    first = tools.screenshot(root / "viewer_t0.png")
    assert _viewport(tools, first).max() > 0.0, "the viewport shows nothing at t=0"
    time.sleep(RENDER_SETTLE_S)
    again = tools.screenshot(root / "viewer_t0_again.png")
    assert _slider_value(tools) == 0.0
    tools.evaluate(f"{FIND_TIME_SLIDER}.focus()")
    tools.key("End", "End", END_KEY_CODE)  # a Mantine slider jumps to its maximum
    _wait_for(lambda: _slider_value(tools) == 1.0, GUI_TIMEOUT_S, "the Time slider to reach 1")
    time.sleep(RENDER_SETTLE_S)
    second = tools.screenshot(root / "viewer_t1.png")
    noise = _changed_pixels(tools, first, again)
    change = _changed_pixels(tools, first, second)
    print(f"viewport pixels changed: same time {noise}, t=0 -> t=1 {change}")
    assert change >= MIN_CHANGED_PIXELS and change >= CHANGE_OVER_NOISE * noise, (noise, change)


def test_output_dropdown_lists_our_outputs(viewer_page):
    tools, root = viewer_page
    # the "Output type" select shows "rgb"; clicking it opens its listbox (aria-controls)
    options_js = """
    (() => {
      const input = [...document.querySelectorAll('input[aria-haspopup="listbox"]')].find(e => e.value === 'rgb');
      if (!input) return null;
      input.click();
      const box = document.getElementById(input.getAttribute('aria-controls'));
      return box ? [...box.querySelectorAll('[role="option"]')].map(e => e.textContent.trim()) : null;
    })()
    """
    options = _wait_for(lambda: tools.evaluate(options_js), GUI_TIMEOUT_S, "the output dropdown's options")
    tools.screenshot(root / "viewer_outputs.png")
    assert "rgb" in options
    for name in EXPECTED_OUTPUTS:
        assert name in options, f"{name} missing from the output dropdown {options}"
