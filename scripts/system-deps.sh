#!/usr/bin/env bash
# Install the Debian packages CoEx needs when they are missing (OpenJPEG for glymur; Chromium for
# the browser tests of the web console). Uses apt when it can (root or passwordless sudo);
# otherwise prints the exact command to run and exits 0 so that the rest of the install goes on.
set -u
want=()
if ! ldconfig -p 2>/dev/null | grep -q 'libopenjp2\.so\.7'; then
  want+=(libopenjp2-7)
fi
if [ "${COEX_BROWSER_TESTS:-1}" != 0 ] && ! command -v chromium >/dev/null 2>&1; then
  want+=(chromium)
fi
[ ${#want[@]} -eq 0 ] && exit 0

if ! command -v apt-get >/dev/null 2>&1; then
  echo "CoEx needs: ${want[*]} (Debian/Ubuntu package names). Install them with your package manager." >&2
  exit 0
fi
if [ "$(id -u)" = 0 ]; then
  SUDO=""
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
  SUDO="sudo"
else
  echo "CoEx needs Debian packages: run   sudo apt-get update && sudo apt-get install -y ${want[*]}" >&2
  exit 0
fi
echo "installing Debian packages: ${want[*]}"
$SUDO apt-get update -qq >/dev/null 2>&1 || true
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${want[@]}" >/dev/null \
  || echo "apt-get could not install ${want[*]}; run: sudo apt-get install -y ${want[*]}" >&2
exit 0
