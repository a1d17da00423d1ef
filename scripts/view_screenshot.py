"""Save a PNG of `splatk view RUN` as a headless Chromium shows it (the README's viewer picture).

Starts `splatk view` on a free port, opens it in the system Chromium through playwright, waits for
the full-size frame (the panel reports it), hides the browser's software-WebGL notice, saves the
window and stops the server::

    python scripts/view_screenshot.py runs/lego_learned --camera test/r_16.png \\
        --out docs/images/view_lego_learned.png

Needs `pip install playwright` (no `playwright install`: it uses /usr/bin/chromium, Debian's
`chromium` package).
"""
from __future__ import annotations

import argparse
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request

from playwright.sync_api import sync_playwright

from splatk.stages.view import frame_size

# WebGL through SwiftShader without a GPU; the background-networking flags keep the browser quiet
# on a closed network
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-gl=angle", "--use-angle=swiftshader",
                 "--disable-quic", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def screenshot(run: str, camera: str, out: str, width: int, height: int, max_size: int, chromium: str,
               view_args: list[str]) -> None:
    port = _free_port()
    url = f"http://127.0.0.1:{port}/"
    server = subprocess.Popen([sys.executable, "-m", "splatk_cli.main", "view", run, "--port", str(port),
                               "--camera", camera, "--max-size", str(max_size), *view_args])
    try:
        deadline = time.time() + 300
        while True:
            if server.poll() is not None or time.time() > deadline:
                sys.exit(f"splatk view did not serve {url}")
            try:
                urllib.request.urlopen(url, timeout=2).close()
                break
            except OSError:
                time.sleep(0.5)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": width, "height": height})
            page.set_default_timeout(300_000)
            page.goto(url)
            page.add_style_tag(content=".mantine-Notification-root { display: none !important }")
            # the full-size frame, which follows once the camera has rested
            full_width, full_height = frame_size(width, height, max_size)
            page.get_by_text(re.compile(rf"Frame: \d+ ms, {full_width}×{full_height}")).wait_for()
            time.sleep(1.0)  # the browser paints the frame a moment after it arrives
            page.screenshot(path=out)
            browser.close()
    finally:
        server.send_signal(signal.SIGINT)
        server.wait(timeout=30)
    print(f"wrote {out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--camera", required=True, help="train or test camera to show")
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--size", default="960x600", help="browser window, WIDTHxHEIGHT")
    ap.add_argument("--max-size", type=int, default=960, help="splatk view --max-size")
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    args, view_args = ap.parse_known_args()  # the rest goes to splatk view (e.g. --backend cpu)
    width, height = (int(v) for v in args.size.split("x"))
    screenshot(args.run, args.camera, args.out, width, height, args.max_size, args.chromium, view_args)


if __name__ == "__main__":
    main()
