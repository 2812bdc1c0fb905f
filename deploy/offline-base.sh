#!/bin/sh
# What deploy/compose.offline.yml builds from, made on this machine without any image
# registry: a Debian base image and a wheelhouse. tests/test_compose.py runs this too.
#
#   deploy/offline-base.sh [--cache DIR] [--wheels-to DIR] [--no-import]
#
# Both are kept in the cache (default ~/.cache/hivemap-docker), keyed by what they are
# made from, so only the first run pays for them:
#   base-KEY.tar     debootstrap's Debian bookworm (minbase) with Python 3.11 and
#                    Prometheus (Debian packages cannot be installed inside an offline
#                    build, so they go in here), about 1.5 min and 550 MB
#   wheelhouse-KEY/  `pip wheel` of the project's dependencies, from this venv's pip
# Then the wheels are hard-linked into --wheels-to (default deploy/wheelhouse, which the
# Dockerfile copies) and the tar is imported as hivemap-base:bookworm into the engine
# DOCKER_HOST names, unless --no-import. debootstrap needs root; it fetches from the
# Debian mirror apt already uses (override with DEBIAN_MIRROR).
set -eu

here=$(cd "$(dirname "$0")/.." && pwd)
cache=${HOME}/.cache/hivemap-docker
wheels_to=$here/deploy/wheelhouse
import=1
while [ $# -gt 0 ]; do
    case $1 in
        --cache) cache=$2; shift 2 ;;
        --wheels-to) wheels_to=$2; shift 2 ;;
        --no-import) import=0; shift ;;
        *) echo "usage: $0 [--cache DIR] [--wheels-to DIR] [--no-import]" >&2; exit 2 ;;
    esac
done
python=${PYTHON:-$here/.venv/bin/python}
[ -x "$python" ] || python=python3
image=${HIVEMAP_BASE_IMAGE:-hivemap-base:bookworm}
suite=bookworm
packages=python3,python3-venv,ca-certificates,prometheus
mkdir -p "$cache"
# One maker at a time: a second run waits and then finds the artifacts made.
exec 9>"$cache/.lock"
flock 9

key() { printf '%s' "$*" | sha256sum | cut -c1-16; }

base=$cache/base-$(key "$suite $packages").tar
if [ ! -s "$base" ]; then
    mirror=${DEBIAN_MIRROR:-$(apt-cache policy 2>/dev/null \
        | awk -v s="$suite/main" '$3 == s && $2 ~ /^https?:/ { print $2; exit }')}
    mirror=${mirror:-http://deb.debian.org/debian}
    rootfs=$(mktemp -d "$cache/rootfs.XXXXXX")
    trap 'rm -rf "$rootfs" "$base.part"' EXIT
    echo "offline-base: debootstrap $suite from $mirror (once)" >&2
    debootstrap --variant=minbase --include="$packages" "$suite" "$rootfs" "$mirror" >&2
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    tar --numeric-owner -C "$rootfs" -cf "$base.part" .
    mv "$base.part" "$base"
    rm -rf "$rootfs"
    trap - EXIT
fi

# Debian's Python is 3.11.2, the venv's may be newer: redis needs async-timeout below
# 3.11.3, which pip on the newer one would not fetch. setuptools and wheel build the
# project itself inside the image.
extra="async-timeout setuptools wheel"
pyver=$("$python" -c 'import sys; print(sys.version.split()[0])')
wheels=$cache/wheelhouse-$(key "$pyver $extra $(cat "$here/pyproject.toml")")
if [ ! -d "$wheels" ]; then
    echo "offline-base: pip wheel of the dependencies (once per pyproject.toml)" >&2
    rm -rf "$wheels.part"
    "$python" -m pip wheel -q --wheel-dir "$wheels.part" "$here" $extra >&2
    # The project itself is built in the image from its copied sources, never from here.
    rm -f "$wheels.part"/hivemap-*.whl
    mv "$wheels.part" "$wheels"
fi
# Only the current wheelhouse is kept (each is ~170 MB; a pyproject.toml change makes one).
for old in "$cache"/wheelhouse-*; do
    [ "$old" = "$wheels" ] || rm -rf "$old"
done

mkdir -p "$wheels_to"
rm -f "$wheels_to"/*.whl
cp -l "$wheels"/*.whl "$wheels_to"/ 2>/dev/null || cp "$wheels"/*.whl "$wheels_to"/
if [ "$import" = 1 ]; then
    # Imported again only when it is another tar: a new import is a new image id, and
    # every layer built on the old one would be rebuilt.
    tag=$(basename "$base" .tar)
    have=$(docker image inspect -f '{{index .Config.Labels "org.hivemap.base"}}' "$image" \
        2>/dev/null || true)
    if [ "$have" != "$tag" ]; then
        docker import --change "LABEL org.hivemap.base=$tag" "$base" "$image" >/dev/null
    fi
fi
echo "base $base"
echo "wheelhouse $wheels"
