"""Real viewers for the tests and the docs' screenshots: the native rerun viewer under Xvfb, and
headless Chromium on the ``--rerun-serve-web`` page (driven over the DevTools protocol).

    python tests/live_view.py viewer RUN.rrd OUT.png [--time S] [--size 1920x1080]
    python tests/live_view.py browser URL OUT.png [--wait S] [--size 1920x1080]

``viewer``: starts Xvfb (a display of its own), the viewer of the rerun-sdk package on a free
port, opens the recording, pauses it at mission time S and saves the viewer's own screenshot.
``browser``: opens URL in headless Chromium (software WebGL: SwiftShader), waits S seconds and
saves a screenshot. Both need Debian's packages xvfb + mesa-vulkan-drivers (the viewer draws
with Vulkan on the CPU: lavapipe) and chromium; the tests fail without them under CI=true.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

#: Chromium's flags for a headless WebGL/WebGPU page on a machine without a GPU or network.
CHROMIUM_FLAGS = (
    "--headless=new", "--no-sandbox", "--disable-gpu-sandbox", "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--disable-dev-shm-usage",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--no-first-run", "--no-default-browser-check", "--disable-extensions",
    "--mute-audio", "--hide-scrollbars",
)


def free_port(count: int = 1) -> int:
    """A port P with P .. P + count - 1 free on loopback (the OS's choice, checked)."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            p = s.getsockname()[1]
        if p + count > 65535:
            continue
        ok = True
        for q in range(p, p + count):
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", q))
                except OSError:
                    ok = False
        if ok:
            return p
    raise RuntimeError("no free port range")


def wait_port(port: int, timeout_s: float, proc: subprocess.Popen[Any] | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            if proc is not None and proc.poll() is not None:
                raise RuntimeError(f"process exited with {proc.returncode}") from None
            if time.monotonic() > deadline:
                raise TimeoutError(f"nothing listens on port {port}") from None
            time.sleep(0.1)


def stop(proc: subprocess.Popen[Any] | None, timeout_s: float = 10.0) -> None:
    """SIGTERM the process (its own id only), then SIGKILL."""
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=timeout_s)


@contextlib.contextmanager
def xvfb(size: str = "1920x1080") -> Iterator[str]:
    """An X display of our own (Xvfb with Composite, as the viewer's window needs)."""
    exe = shutil.which("Xvfb")
    if exe is None:
        raise FileNotFoundError("Xvfb is not installed (Debian: apt-get install xvfb)")
    proc = subprocess.Popen([exe, "-displayfd", "1", "-screen", "0", f"{size}x24",
                             "-extension", "Composite", "-nolisten", "tcp"],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().decode().strip()
        if not line.isdigit():
            raise RuntimeError(f"Xvfb did not start (exit code {proc.poll()})")
        yield f":{line}"
    finally:
        stop(proc)


@contextlib.contextmanager
def native_viewer(display: str, size: str = "1600x900"
                  ) -> Iterator[tuple[Any, subprocess.Popen[bytes]]]:
    """The rerun-sdk viewer on ``display`` and a free port, its window ``size``:
    (ViewerClient, process)."""
    from rerun.experimental import ViewerClient

    from vtube_fleet.recording.live import rerun_executable

    port = free_port()
    env = {**os.environ, "DISPLAY": display, "RERUN_APP_ONLY": "true"}
    env.pop("WAYLAND_DISPLAY", None)
    lvp = Path("/usr/share/vulkan/icd.d/lvp_icd.x86_64.json")
    if lvp.is_file():  # Vulkan on the CPU (the viewer refuses GL on llvmpipe: no R32Float)
        env["VK_ICD_FILENAMES"] = str(lvp)
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen([rerun_executable(), "--port", str(port), "--bind", "127.0.0.1",
                             "--window-size", size], env=env, stdout=log,
                            stderr=subprocess.STDOUT)
    try:
        try:
            wait_port(port, 30.0, proc)
        except (RuntimeError, TimeoutError) as exc:
            log.seek(0)
            raise RuntimeError(f"the rerun viewer did not start: {exc}: "
                               f"{log.read().decode(errors='replace')[-800:]}") from None
        yield ViewerClient(f"rerun+http://127.0.0.1:{port}/proxy"), proc
    finally:
        stop(proc)
        log.close()


def viewer_screenshot(rrd: Path, out: Path, *, time_s: float | None = None,
                      size: str = "1920x1080", settle_s: float = 8.0) -> dict[str, Any]:
    """Render ``rrd`` in the native viewer under Xvfb and save the viewer's screenshot; returns
    the viewer's state (its views and what each failed to draw, if anything)."""
    with xvfb(size) as display, native_viewer(display, size) as (client, _proc):
        client.open(str(Path(rrd).resolve()))
        deadline = time.monotonic() + 30.0
        state = client.get_state()
        while not any(r.timelines for r in state.recordings) and time.monotonic() < deadline:
            time.sleep(0.5)
            state = client.get_state()
        if time_s is not None:
            client.set_time("mission_time", duration=float(time_s), play_state="paused")
        time.sleep(settle_s)  # the views lay out and the map settles its zoom (frames drawn)
        png = client.take_screenshot()
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(png)
        state = client.get_state()
        return {"views": [{"name": v.name, "class": v.view_class,
                           "reports": [str(r) for r in v.reports]} for v in state.views]}


# ---------------------------------------------------------------------------------------------
# headless Chromium over the DevTools protocol
# ---------------------------------------------------------------------------------------------
def chromium_executable() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    raise FileNotFoundError("chromium is not installed (Debian: apt-get install chromium)")


@contextlib.contextmanager
def chromium(size: str = "1920x1080", *, nice: int = 0
             ) -> Iterator[tuple[subprocess.Popen[bytes], int]]:
    """Headless Chromium with a fresh profile and a DevTools port: (process, port); ``nice``
    lowers the priority of it and every helper process it starts (the GPU process draws)."""
    port = free_port()
    w, h = size.split("x")
    with tempfile.TemporaryDirectory(prefix="chromium-") as profile:
        proc = subprocess.Popen(
            [chromium_executable(), *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
             f"--remote-debugging-port={port}", "--remote-allow-origins=*",
             f"--window-size={w},{h}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
            preexec_fn=(lambda: os.nice(nice)) if nice else None)
        try:
            wait_port(port, 30.0, proc)
            yield proc, port
        finally:
            if proc.poll() is None:  # its own process group: the renderer and GPU helpers too
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
            stop(proc)


class DevTools:
    """A minimal DevTools-protocol client of one page (websockets, synchronous)."""

    def __init__(self, port: int) -> None:
        from urllib.request import urlopen

        from websockets.sync.client import connect

        deadline = time.monotonic() + 20.0
        while True:
            pages = json.load(urlopen(f"http://127.0.0.1:{port}/json"))
            pages = [p for p in pages if p.get("type") == "page"]
            if pages or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=64 * 2**20)
        self._id = 0

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=60.0))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return dict(msg.get("result", {}))

    def evaluate(self, expr: str) -> Any:
        res = self.call("Runtime.evaluate", expression=expr, returnByValue=True)
        return res.get("result", {}).get("value")

    def screenshot(self, out: Path) -> None:
        data = self.call("Page.captureScreenshot", format="png")["data"]
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(base64.b64decode(data))

    def close(self) -> None:
        self.ws.close()


def browser_screenshot(url: str, out: Path, *, wait_s: float = 20.0,
                       size: str = "1920x1080") -> dict[str, Any]:
    """Open ``url`` in headless Chromium, wait, save a screenshot; returns what the page says
    about WebGL/WebGPU (to tell a page that cannot draw from one that did)."""
    with chromium(size) as (_proc, port):
        dt = DevTools(port)
        try:
            w, h = (int(v) for v in size.split("x"))
            dt.call("Emulation.setDeviceMetricsOverride", width=w, height=h,
                    deviceScaleFactor=1, mobile=False)
            dt.call("Page.enable")
            dt.call("Page.navigate", url=url)
            time.sleep(wait_s)
            info = {
                "webgl2": dt.evaluate("!!document.createElement('canvas').getContext('webgl2')"),
                "webgpu": dt.evaluate("!!navigator.gpu"),
                "title": dt.evaluate("document.title"),
            }
            dt.screenshot(out)
        finally:
            dt.close()
    return info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    v = sub.add_parser("viewer")
    v.add_argument("rrd", type=Path)
    v.add_argument("out", type=Path)
    v.add_argument("--time", type=float, default=None, metavar="S")
    v.add_argument("--size", default="1920x1080")
    b = sub.add_parser("browser")
    b.add_argument("url")
    b.add_argument("out", type=Path)
    b.add_argument("--wait", type=float, default=20.0, metavar="S")
    b.add_argument("--size", default="1920x1080")
    args = ap.parse_args()
    if args.what == "viewer":
        info = viewer_screenshot(args.rrd, args.out, time_s=args.time, size=args.size)
    else:
        info = browser_screenshot(args.url, args.out, wait_s=args.wait, size=args.size)
    print(json.dumps(info, indent=1))


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
