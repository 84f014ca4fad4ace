#!/usr/bin/env bash
# apt_install TAG WHAT PACKAGE...: install Debian packages for a test's system needs when we
# are root and apt-get exists; else print on stderr why not (prefixed "TAG:") and return 2.
# A failing apt-get returns its own (non-zero) status.
# Sourced by the ensure-*.sh scripts, which decide what a failure means for their tests.
apt_install() {
    local tag=$1 what=$2
    shift 2
    if [ "$(id -u)" != "0" ]; then
        echo "$tag: missing $what and we are not root; install Debian's $*" >&2
        return 2
    fi
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "$tag: missing $what and apt-get is not available" >&2
        return 2
    fi
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq && apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}
