#!/usr/bin/env bash
# System packages the renderer and its tests use: Mesa's software Vulkan (lavapipe) and
# GL/EGL (llvmpipe) drivers, Xvfb for the window test, iproute2 (ip, tc) for the link tests. Installs them when run as root
# and something is missing; otherwise says what to install.
set -u
need=()
ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1 || need+=(mesa-vulkan-drivers)
ldconfig -p 2>/dev/null | grep -q 'libEGL.so.1' || need+=(libegl1)
ldconfig -p 2>/dev/null | grep -q 'libGL.so.1' || need+=(libgl1)
ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa' || need+=(libegl-mesa0)
command -v Xvfb >/dev/null 2>&1 || need+=(xvfb)
# ip netns / veth / tc netem for the network-namespace link tests (tests/remote)
command -v ip >/dev/null 2>&1 || need+=(iproute2)
# a real browser for the view server's page (tests/serve; playwright drives it, executable_path)
[ -x /usr/bin/chromium ] || need+=(chromium)
[ ${#need[@]} -eq 0 ] && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing system packages: ${need[*]}" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null && apt-get install -y -qq "${need[@]}" >/dev/null
else
    echo "note: missing system packages (${need[*]}); install them with: sudo apt-get install ${need[*]}" >&2
fi
