#!/usr/bin/env bash
# Set up everything the tests need on a fresh machine, then run the whole suite.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v chromium >/dev/null 2>&1; then
  # Browser tests drive Debian's Chromium (no browser download at test time).
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null \
    || echo "warning: could not install chromium; browser tests will be skipped"
fi
if ! command -v pdftotext >/dev/null 2>&1 || ! command -v pdftoppm >/dev/null 2>&1; then
  # The certificate tests read the PDF back with poppler (pdftotext, pdftoppm).
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq poppler-utils >/dev/null \
    || echo "warning: could not install poppler-utils; certificate PDF tests will be skipped"
fi
bash scripts/setup.sh test
mkdir -p artifacts
# Three workers on two cores: most tests wait on simulated hardware, not on the CPU. Whole files
# go to one worker (--dist loadfile): module-scoped stations and venvs are built once.
exec .venv/bin/python -m pytest -q -p no:cacheprovider --tb=native --durations=25 -n "${TEST_WORKERS:-3}" --dist loadfile "$@"
