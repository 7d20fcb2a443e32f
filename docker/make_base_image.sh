#!/usr/bin/env bash
# Make a minimal Debian + Python 3 base image without any image registry:
# debootstrap a root filesystem from Debian's package mirror, then `docker import` it.
#
#   docker/make_base_image.sh [TAG]        (default TAG: neumip-base:bookworm)
#
# Needs root, debootstrap (apt-get install debootstrap) and a running Docker engine.
# Environment: SUITE (bookworm), MIRROR (http://deb.debian.org/debian).
set -euo pipefail

TAG="${1:-neumip-base:bookworm}"
SUITE="${SUITE:-bookworm}"
MIRROR="${MIRROR:-http://deb.debian.org/debian}"

if docker image inspect "$TAG" >/dev/null 2>&1; then
    echo "base image $TAG already exists"
    exit 0
fi
command -v debootstrap >/dev/null || { echo "debootstrap is missing: apt-get install -y debootstrap" >&2; exit 2; }

ROOTFS="$(mktemp -d /tmp/neumip-rootfs.XXXXXX)"
trap 'rm -rf "$ROOTFS"' EXIT

echo "debootstrap $SUITE from $MIRROR into $ROOTFS"
debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates \
    "$SUITE" "$ROOTFS" "$MIRROR"

# Slim the tree: apt caches, docs and man pages are not needed at run time.
rm -rf "$ROOTFS"/var/cache/apt/archives/*.deb "$ROOTFS"/var/lib/apt/lists/* \
       "$ROOTFS"/usr/share/doc/* "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/locale/*

tar -C "$ROOTFS" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["/bin/bash"]' \
    - "$TAG"
echo "made base image $TAG"
