#!/usr/bin/env bash
# The dashboard in headless Chromium (tests/browser/dashboard_test.py). Needs Debian's
# chromium and chromium-driver and pip's selenium: skips without them, except on CI
# (CI=true), where .ci/run installs them and a skip would hide a failure.
set -euo pipefail
cd "$(dirname "$0")/../.."

missing=""
command -v chromium >/dev/null 2>&1 || missing="chromium"
command -v chromedriver >/dev/null 2>&1 || [ -x /usr/lib/chromium/chromedriver ] || missing="$missing chromium-driver"
python3 -c "import selenium" >/dev/null 2>&1 || missing="$missing selenium (pip)"
if [ -n "$missing" ]; then
    if [ "${CI:-}" = "true" ]; then
        echo "browser test: missing on CI: $missing" >&2
        exit 1
    fi
    echo "browser test: SKIPPED (missing: $missing; apt-get install chromium chromium-driver; pip install selenium)" >&2
    exit 0
fi
timeout 600 python3 tests/browser/dashboard_test.py
