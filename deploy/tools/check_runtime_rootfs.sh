#!/usr/bin/env bash
# Stand-in for the Dockerfile's runtime stage where no Docker engine runs: a minimal Debian 12 root (debootstrap
# --variant=minbase, close to debian:12-slim) gets the same apt packages, user and files as the image, then the
# binary's libraries are resolved (the image's `ldd` check), the OpenCV path is exercised (`scone extract` on a
# committed photograph, as uid 10001) and libonnxruntime.so is loaded with dlopen. Needs root (chroot),
# debootstrap and cc, Debian's mirrors, and a release build from scripts/setup.
# The binary's RUNPATH is the setup prefix's OpenCV lib dir, so the libraries go to that path, as in the image
# (there /opt/scone-prefix/...).  Usage: sudo deploy/tools/check_runtime_rootfs.sh
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
# shellcheck disable=SC1091  # scripts/env.sh, resolved at run time
. "$repo/scripts/env.sh"
work="$SCONE_PREFIX/deploy-check"
root="$work/rootfs"
mkdir -p "$work"
if [ ! -x "$root/usr/bin/apt-get" ]; then
  debootstrap --variant=minbase bookworm "$root" http://deb.debian.org/debian > "$work/debootstrap.log"
fi
cp /etc/resolv.conf "$root/etc/resolv.conf"
# Same commands as the runtime stage of deploy/Dockerfile.
chroot "$root" /bin/bash -o pipefail -c '
  apt-get update -q >/dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends libstdc++6 curl >/dev/null
  rm -rf /var/lib/apt/lists/*
  id scone >/dev/null 2>&1 || { groupadd --gid 10001 scone \
    && useradd --uid 10001 --gid scone --home-dir /var/lib/scone --no-create-home --shell /usr/sbin/nologin scone; }
  install -d -o scone -g scone -m 0750 /var/lib/scone'
runpath="$(readelf -d "$CARGO_TARGET_DIR/release/scone" | sed -n 's/.*runpath: \[\(.*\)\]/\1/p')"
[ "$runpath" = "$SCONE_OPENCV_PREFIX/lib" ] || { echo "unexpected RUNPATH: $runpath"; exit 1; }
install -d "$root/opt/scone/bin" "$root/opt/scone/lib" "$root/opt/scone/models" "$root$runpath" "$root/tmp/check"
cp "$CARGO_TARGET_DIR/release/scone" "$root/opt/scone/bin/scone"
cp -a "$SCONE_OPENCV_PREFIX"/lib/libopencv_*.so.* "$root$runpath/"
cp -a "$SCONE_ORT_DIR"/lib/libonnxruntime.so* "$root/opt/scone/lib/"
cp "$repo"/models/scone-ring-e1-real-bits.onnx "$repo"/models/scone-ring-e1-real.onnx "$repo"/models/scone-freak-k20.onnx \
  "$root/opt/scone/models/"
cp "$repo/tests/fixtures/coffee-640x480.jpg" "$root/tmp/check/"
# Directories on the way to the RUNPATH must be traversable by uid 10001 (in the image: /opt/scone-prefix).
d="$runpath"; while [ "$d" != / ]; do chmod o+x "$root$d"; d="$(dirname "$d")"; done
cat > "$work/ortcheck.c" <<'EOF'
#include <dlfcn.h>
#include <stdio.h>
typedef struct { const void *(*GetApi)(unsigned); const char *(*GetVersionString)(void); } OrtApiBase;
int main(int argc, char **argv) {
  void *h = dlopen(argv[1], RTLD_NOW);
  if (!h) { fprintf(stderr, "dlopen: %s\n", dlerror()); return 1; }
  const OrtApiBase *(*base)(void) = (const OrtApiBase *(*)(void))dlsym(h, "OrtGetApiBase");
  if (!base) { fprintf(stderr, "no OrtGetApiBase in %s\n", argv[1]); return 1; }
  printf("onnxruntime %s loaded from %s\n", base()->GetVersionString(), argv[1]);
  return 0;
}
EOF
cc -O1 -o "$root/tmp/check/ortcheck" "$work/ortcheck.c" -ldl
echo "== ldd (the image's check)"
# shellcheck disable=SC2016  # expanded inside the chroot
chroot "$root" /bin/bash -o pipefail -c 'out="$(ldd /opt/scone/bin/scone /opt/scone/lib/libonnxruntime.so)" \
  && if grep -F "not found" <<<"$out"; then exit 1; fi; echo "all libraries resolved"'
echo "== scone extract as uid 10001"
chroot --userspec=10001:10001 "$root" /usr/bin/env -i HOME=/var/lib/scone PATH=/usr/bin:/bin \
  /opt/scone/bin/scone extract /tmp/check/coffee-640x480.jpg | grep -E '"(keypoints|constellations)"'
echo "== ONNX Runtime as uid 10001"
chroot --userspec=10001:10001 "$root" /tmp/check/ortcheck /opt/scone/lib/libonnxruntime.so
echo "== scone serve with the image's ENV, the k8s ConfigMap's TOML and a generated keys file"
install -d "$root/etc/scone/config" "$root/etc/scone/secrets"
# PyYAML from the venv deploy/validate.sh creates.
"$SCONE_PREFIX/venv-deploy/bin/python" - "$repo/deploy/Dockerfile" "$repo/deploy/k8s/configmap.yaml" "$root" <<'PY'
import pathlib, re, shlex, sys, yaml
dockerfile, configmap, root = sys.argv[1:]
runtime = open(dockerfile).read().split(" AS runtime", 1)[1]
block = re.search(r"^ENV ((?:.*\\\n)*.*)$", runtime, re.M).group(1).replace("\\\n", " ")
pathlib.Path(root, "tmp/check/image.env").write_text("\n".join(shlex.split(block)) + "\n")
pathlib.Path(root, "etc/scone/config/scone.toml").write_text(yaml.safe_load(open(configmap))["data"]["scone.toml"])
PY
printf 'write %s\nread %s\n' "$(od -An -tx1 -N16 /dev/urandom | tr -d ' \n')" \
  "$(od -An -tx1 -N16 /dev/urandom | tr -d ' \n')" > "$root/etc/scone/secrets/keys"
chmod 0444 "$root/etc/scone/secrets/keys"
sed 's/^/  /' "$root/tmp/check/image.env"
cp "$repo/deploy/tools/rootfs_serve.sh" "$root/tmp/check/serve.sh"
timeout 120 unshare -n bash -c "ip link set lo up && chroot '$root' /bin/bash /tmp/check/serve.sh"
echo "== packages"
# shellcheck disable=SC2016  # dpkg-query format
chroot "$root" dpkg-query -W -f='${Package} ${Version}\n' libc6 libgcc-s1 libstdc++6 curl
echo "runtime rootfs check passed"
