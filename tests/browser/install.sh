#!/usr/bin/env bash
# Debian's headless Chromium + ChromeDriver for tests/browser (playwright drives
# /usr/bin/chromium; it never downloads a browser of its own). Idempotent; needs root.
set -euo pipefail
if [ -x /usr/bin/chromium ]; then
  echo "chromium present: $(/usr/bin/chromium --version 2>/dev/null || true)"
  exit 0
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -q
apt-get install -y -q chromium chromium-driver
/usr/bin/chromium --version
