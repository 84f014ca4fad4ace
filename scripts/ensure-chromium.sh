#!/usr/bin/env bash
# Make sure Debian's headless-capable Chromium is installed at /usr/bin/chromium, which the
# report's browser test uses (tests/report/test_report_browser.py).  Installs it with apt-get
# when it is missing and we are root; otherwise says why it cannot and exits 0, so the
# test then skips with a clear reason.
set -euo pipefail
if [ -x /usr/bin/chromium ]; then
    exit 0
fi
source "$(dirname "$0")/apt-install.sh"
status=0
apt_install ensure-chromium /usr/bin/chromium chromium || status=$?
if [ "$status" -eq 2 ]; then  # cannot install here: the test skips with the reason
    exit 0
elif [ "$status" -ne 0 ]; then  # apt-get itself failed
    exit "$status"
fi
test -x /usr/bin/chromium
echo "ensure-chromium: installed $(/usr/bin/chromium --version 2>/dev/null || echo chromium)"
