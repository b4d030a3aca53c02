"""The HTML viewer in a real browser: headless Chromium, driven through its DevTools protocol,
loads the file from disk with no console error and no network request, draws the scene (a
screenshot that is not blank), opens paused on the first frame with the slider at t = 0.00 s,
and a click on the time slider moves the robot, its label the time of the frame drawn.

Skipped where Chromium is missing, unless JSPHERE_BROWSER_TEST=required (`.ci/run` installs
Chromium and sets it)."""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from viewer_html import frame_time, viewer_figure

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"


def _chromium() -> str:
    exe = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
    if exe is None:
        if os.environ.get("JSPHERE_BROWSER_TEST") == "required":
            pytest.fail("JSPHERE_BROWSER_TEST=required but no chromium on PATH (apt-get install chromium).")
        pytest.skip("no chromium on PATH (set JSPHERE_BROWSER_TEST=required to make this a failure)")
    return exe


class Page:
    """One headless Chromium tab over the DevTools protocol: `call` a method, keep its events."""

    def __init__(self, exe: str, profile: Path):
        import websocket

        self.proc = subprocess.Popen(
            [
                exe,
                "--headless=new",
                "--no-sandbox",
                "--disable-gpu",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--no-first-run",
                "--disable-background-networking",
                "--remote-debugging-port=0",
                f"--user-data-dir={profile}",
                "--window-size=1000,800",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            port_file = profile / "DevToolsActivePort"
            for _ in range(300):
                if port_file.is_file() and port_file.read_text().strip():
                    break
                time.sleep(0.1)
            port = int(port_file.read_text().split()[0])
            from urllib.request import urlopen

            targets = json.loads(urlopen(f"http://127.0.0.1:{port}/json").read())
            url = next(t["webSocketDebuggerUrl"] for t in targets if t["type"] == "page")
            self.ws = websocket.create_connection(url, timeout=60, suppress_origin=True)
        except BaseException:
            self.proc.kill()
            self.proc.wait(10)
            raise
        self.n, self.events = 0, []

    def call(self, method: str, **params):
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == self.n:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self.events.append(msg)

    def evaluate(self, js: str):
        r = self.call("Runtime.evaluate", expression=js, awaitPromise=True, returnByValue=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{js}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait_for(self, js: str, seconds: float = 60.0):
        end = time.time() + seconds
        while time.time() < end:
            if self.evaluate(js):
                return
            time.sleep(0.2)
        raise AssertionError(f"timed out waiting for {js}")

    def close(self):
        self.ws.close()
        self.proc.terminate()
        self.proc.wait(10)


#: what the page shows: the slider's label and step, and the time in the frame's status line
SHOWN = """(() => {
  const g = window.jsphereViewer;
  const label = [...document.querySelectorAll(".slider-container text")].find(t => t.textContent.startsWith("t = "));
  const status = g._fullLayout.annotations[1].text.match(/t =\\s*(\\S+) s/)[1];
  return {label: label && label.textContent, active: g._fullLayout.sliders[0].active, status: status};
})()"""


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    from jsphere import animate

    out = tmp_path_factory.mktemp("viewer") / "ws_01.html"
    animate(str(DATA / "ws_01.csv"), out, fps=6, speed=2.0, size=(800, 600))
    return out


def test_viewer_loads_offline_draws_and_its_slider_moves_the_robot(viewer, tmp_path):
    page = Page(_chromium(), tmp_path / "profile")
    try:
        for domain in ("Runtime", "Log", "Network", "Page"):
            page.call(f"{domain}.enable")
        page.call("Page.navigate", url=viewer.as_uri())
        page.wait_for(
            "!!(window.jsphereViewer && window.jsphereViewer._fullLayout && document.readyState == 'complete')"
        )
        time.sleep(1.0)  # the WebGL scene's first draw (and time for an auto-play to move on)
        shot = base64.b64decode(page.call("Page.captureScreenshot", format="png")["data"])
        opened = page.evaluate(SHOWN)
        centre = "window.jsphereViewer.data[0].x.reduce((a, b) => a + b, 0) / window.jsphereViewer.data[0].x.length"
        before = page.evaluate(centre)
        rail = page.evaluate(
            "(() => { const r = document.querySelector('.slider-rail-rect').getBoundingClientRect();"
            " return [r.left, r.top, r.width, r.height]; })()"
        )
        x, y = rail[0] + 0.95 * rail[2], rail[1] + 0.5 * rail[3]
        for kind in ("mousePressed", "mouseReleased"):
            page.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1)
        page.wait_for(f"Math.abs(({centre}) - {before}) > 1e-3", seconds=30)
        after = page.evaluate(centre)
        active = page.evaluate("window.jsphereViewer._fullLayout.sliders[0].active")
        clicked = page.evaluate(SHOWN)
        page.call("Runtime.evaluate", expression="1")  # collect the events so far
        events = page.events
    finally:
        page.close()

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(shot)).convert("RGB"), float)
    assert img.std() > 20.0 and len(np.unique(img.reshape(-1, 3), axis=0)) > 200, "the screenshot is blank"
    scene = img[100:500, 100:700]
    assert (scene.sum(-1) < 600).mean() > 0.01, "nothing drawn in the 3-D scene"

    errors = [
        e
        for e in events
        if e.get("method") == "Runtime.exceptionThrown"
        or (e.get("method") == "Runtime.consoleAPICalled" and e["params"]["type"] == "error")
        or (e.get("method") == "Log.entryAdded" and e["params"]["entry"]["level"] == "error")
    ]
    assert not errors, errors
    requests = [e["params"]["request"]["url"] for e in events if e.get("method") == "Network.requestWillBeSent"]
    assert requests and all(u.startswith(("file:", "data:", "blob:")) for u in requests), requests
    assert active > 0
    assert abs(after - before) > 1e-3  # the robot moved [m]
    # the slider's label is the time of the frame drawn: on opening (paused) the first, t = 0
    _, layout, frames = viewer_figure(viewer)
    labels = [s["label"] for s in layout["sliders"][0]["steps"]]
    assert opened == {"label": "t = 0.00 s", "active": 0, "status": frame_time(frames[0])} and labels[0] == "0.00 s"
    assert clicked["label"] == f"t = {labels[active]}" and clicked["active"] == active
    assert f"{float(clicked['status']):.2f} s" == labels[active]
