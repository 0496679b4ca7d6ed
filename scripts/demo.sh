#!/usr/bin/env bash
# Quick start: a whole simulated station (serial + CAN boards, lamp relay, fixture) and the
# operator page on http://127.0.0.1:8080 . Extra arguments go to `station demo`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/station demo "$@"
