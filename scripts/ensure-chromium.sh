#!/usr/bin/env bash
# The page's tests (tests/service/test_page.py) drive a real headless Chromium through
# Selenium: Debian's `chromium` and `chromium-driver`. Install them when missing and we are
# root with apt-get; otherwise say why: the browser tests then fail with the same reason (or
# skip under ALLOW_SKIP=1, tests/required_components.py).
set -euo pipefail
have_chromium() {
  command -v chromium >/dev/null && command -v chromedriver >/dev/null
}
have_chromium && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "renderloop: chromium or chromedriver missing; installing chromium chromium-driver with apt-get" >&2
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null
  have_chromium && exit 0
fi
echo "renderloop: the page's browser tests need Debian's chromium and chromium-driver" \
     "('apt-get install chromium chromium-driver' as root); they will fail (ALLOW_SKIP=1 skips them)" >&2
exit 1
