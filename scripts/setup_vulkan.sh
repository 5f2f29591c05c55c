#!/usr/bin/env bash
# Fetch Mesa's lavapipe (software Vulkan) from Debian bookworm-backports into .deps/vulkan,
# without touching the system's apt configuration, and write an ICD json pointing at it.
# SAPIEN needs a Vulkan device even for state-only physics; Debian 12's own Mesa 22 lavapipe is
# not enough (see docs/SETUP.md). Idempotent: does nothing when the ICD file already exists.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
dest="$root/.deps/vulkan"
icd="$dest/lvp_icd.json"
[ -f "$icd" ] && [ -f "$dest/root/usr/lib/x86_64-linux-gnu/libvulkan_lvp.so" ] && exit 0

command -v apt-get >/dev/null || { echo "setup_vulkan: apt-get not found; install Mesa >= 25 lavapipe yourself and set VK_ICD_FILENAMES" >&2; exit 1; }
work="$dest/apt"
rm -rf "$work" "$dest/root"
mkdir -p "$work/lists/partial" "$work/cache/archives/partial" "$work/sources" "$dest/root"
uri=$(grep -rhs '^URIs:.*debian' /etc/apt/sources.list.d/ /etc/apt/sources.list 2>/dev/null | grep -v security | head -1 | awk '{print $2}' || true)
[ -n "$uri" ] || uri="http://deb.debian.org/debian"
keyring=/usr/share/keyrings/debian-archive-keyring.gpg
cat > "$work/sources/backports.sources" <<SRC
Types: deb
URIs: $uri
Suites: bookworm-backports
Components: main
Signed-By: $keyring
SRC
opts=(-o Dir::Etc::SourceList=/dev/null -o "Dir::Etc::SourceParts=$work/sources"
      -o "Dir::State::Lists=$work/lists" -o "Dir::Cache=$work/cache" -o Debug::NoLocking=1)
echo "setup_vulkan: fetching mesa-vulkan-drivers from bookworm-backports (~11 MB)"
apt-get "${opts[@]}" -qq update
(cd "$work" && apt-get "${opts[@]}" -qq download mesa-vulkan-drivers/bookworm-backports)
dpkg -x "$work"/mesa-vulkan-drivers_*.deb "$dest/root"
lib="$dest/root/usr/lib/x86_64-linux-gnu/libvulkan_lvp.so"
[ -f "$lib" ] || { echo "setup_vulkan: $lib missing after extraction" >&2; exit 1; }
printf '{"file_format_version":"1.0.0","ICD":{"library_path":"%s","api_version":"1.4.305"}}\n' "$lib" > "$icd.tmp"
mv "$icd.tmp" "$icd"
rm -rf "$work"
echo "setup_vulkan: wrote $icd"
