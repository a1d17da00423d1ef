"""`splatk view` as a separate process, for the viewer's tests: started on a port the system picks
(so two tests running side by side never meet on one port) and stopped as a user would stop it."""
from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass


@dataclass
class Viewer:
    proc: subprocess.Popen
    url: str
    printed: str = ""  # what it wrote on stderr before serving


def start_viewer(run, *options: str, timeout: float = 120.0) -> Viewer:
    """Start `splatk view RUN --port 0 OPTIONS` and return once its page answers."""
    proc = subprocess.Popen([sys.executable, "-m", "splatk_cli.main", "view", str(run), "--port", "0",
                            "--host", "127.0.0.1", *options],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env={**os.environ, "OMP_NUM_THREADS": "1"},
                            # a pytest-xdist worker ignores SIGINT and a child inherits that, so
                            # Python would not raise KeyboardInterrupt on Ctrl-C: give it the default
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    printed = b""
    deadline = time.time() + timeout
    try:
        url = None
        while url is None:  # `splatk view` prints the address it serves once the port is bound
            if time.time() > deadline:
                raise AssertionError(f"splatk view printed no address within {timeout:.0f} s: {_text(printed)}")
            if not select.select([proc.stderr], [], [], 0.5)[0]:
                continue
            # raw reads, not readline: a buffered reader could hold the address line back
            chunk = os.read(proc.stderr.fileno(), 65536)
            if not chunk:
                raise AssertionError(f"splatk view exited with {proc.wait()}: {_text(printed)}")
            printed += chunk
            match = re.search(rb"http://127\.0\.0\.1:\d+", printed)
            url = match and match.group(0).decode() + "/"
        while True:
            try:
                urllib.request.urlopen(url, timeout=2).close()
                return Viewer(proc, url, _text(printed))
            except OSError:
                if time.time() > deadline:
                    raise AssertionError(f"splatk view did not answer at {url} within {timeout:.0f} s") from None
                time.sleep(0.5)
    except BaseException:
        proc.kill()
        proc.communicate()
        raise


def stop_viewer(viewer: Viewer, signum: int = signal.SIGINT, timeout: float = 30.0) -> tuple[int | None, str]:
    """Send ``signum`` and wait for the exit: (exit code, or None when it had to be killed, and
    everything it printed on stderr)."""
    proc = viewer.proc
    if proc.poll() is None:
        proc.send_signal(signum)
    try:
        _, err = proc.communicate(timeout=timeout)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        code = None
    return code, viewer.printed + _text(err)


def _text(printed: bytes) -> str:
    return printed.decode(errors="replace")
