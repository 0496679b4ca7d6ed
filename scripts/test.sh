#!/usr/bin/env bash
# Set up everything the tests need on a fresh machine, then run the whole suite.
set -euo pipefail
cd "$(dirname "$0")/.."
# Debian packages the tests drive (no download at test time beyond these):
#   chromium                 the browser tests (no browser download)
#   poppler-utils            the certificate tests read the PDF back (pdftotext, pdftoppm)
#   gcc-arm-none-eabi, libnewlib-arm-none-eabi, qemu-system-arm
#                            the board firmware (firmware/): built for the STM32F407 Discovery and
#                            run on an emulated Cortex-M4 in the firmware tests
need=()
command -v chromium >/dev/null 2>&1 || need+=(chromium)
{ command -v pdftotext && command -v pdftoppm; } >/dev/null 2>&1 || need+=(poppler-utils)
command -v arm-none-eabi-gcc >/dev/null 2>&1 || need+=(gcc-arm-none-eabi)
[ -e /usr/lib/arm-none-eabi/newlib/thumb/v7e-m+fp/hard/libc_nano.a ] || need+=(libnewlib-arm-none-eabi)
command -v qemu-system-arm >/dev/null 2>&1 || need+=(qemu-system-arm)
# clang + libclang-rt-14-dev: the firmware's libFuzzer harness (firmware/fuzz, tests/test_firmware_fuzz.py)
command -v clang >/dev/null 2>&1 || need+=(clang)
ls /usr/lib/llvm-*/lib/clang/*/lib/linux/libclang_rt.fuzzer-x86_64.a >/dev/null 2>&1 || need+=(libclang-rt-14-dev)
# fonts-noto-cjk: the Chinese operator page (tests/test_browser_i18n.py) renders real glyphs, not boxes
fc-list :lang=zh 2>/dev/null | grep -q . || need+=(fonts-noto-cjk)
if [ "${#need[@]}" -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null \
    || echo "warning: could not install ${need[*]}; the tests that need them will fail or be skipped"
fi
# The firmware tests fail (not skip) here when their tools are missing: CI must run them.
export STATION_REQUIRE_FIRMWARE="${STATION_REQUIRE_FIRMWARE:-1}"
bash scripts/setup.sh test
# The typed seams first (pyproject.toml [tool.mypy]): a part that reads another by a name it does
# not have fails here, in seconds, not at a restart on the line.
.venv/bin/python -m mypy || { echo "type check failed (mypy, pyproject.toml [tool.mypy])"; exit 1; }
# The CFX tests (tests/test_cfx.py) talk AMQP 1.0 to the RabbitMQ on 127.0.0.1: its plugin on (idempotent).
if command -v rabbitmq-plugins >/dev/null 2>&1; then
  rabbitmq-plugins enable --quiet rabbitmq_amqp1_0 >/dev/null 2>&1 || echo "warning: could not enable rabbitmq_amqp1_0 (tests/test_cfx.py)"
fi
mkdir -p artifacts
# Three workers on two cores: most tests wait on simulated hardware, not on the CPU. Whole files
# go to one worker (--dist loadfile): module-scoped stations and venvs are built once.
exec .venv/bin/python -m pytest -q -p no:cacheprovider --tb=native --durations=25 -n "${TEST_WORKERS:-3}" --dist loadfile "$@"
