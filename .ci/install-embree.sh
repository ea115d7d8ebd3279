#!/usr/bin/env bash
# Install Embree 3.13 (Debian's libembree-dev) for the `embree` feature of
# rebraid-cli. Idempotent: does nothing when the headers are already there.
# The embree3 crate links `-lembree3`; Debian puts libembree3.so on the
# default linker and loader paths, so no environment variable is needed.
#
#   bash .ci/install-embree.sh
#   cargo test -p rebraid-cli --features embree --test embree_baseline
set -euo pipefail

libs="$(ldconfig -p 2>/dev/null || true)"
if [ -f /usr/include/embree3/rtcore.h ] && [[ "$libs" == *"libembree3.so "* ]]; then
  echo "Embree already installed: $(grep -m1 RTC_VERSION_STRING /usr/include/embree3/rtcore_config.h)"
  exit 0
fi

export DEBIAN_FRONTEND=noninteractive
sudo=()
if [ "$(id -u)" -ne 0 ]; then
  sudo=(sudo)
fi
"${sudo[@]}" apt-get update -qq
"${sudo[@]}" apt-get install -y -qq libembree-dev
echo "Installed: $(grep -m1 RTC_VERSION_STRING /usr/include/embree3/rtcore_config.h)"
