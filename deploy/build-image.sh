#!/usr/bin/env bash
# Builds the pathfarm container image without a registry: `FROM scratch` with the release
# binary of this checkout and the shared libraries it loads (found with ldd, with the
# loader). One image for every role: entrypoint `pathfarm`, so `docker run IMAGE render ...`,
# `... coordinator ...` and `... worker ...` all work.
#
# Usage: deploy/build-image.sh [TAG]            (default tag: pathfarm:local)
#
# CPU baseline: the image's binary is built for x86-64-v3 (AVX2, FMA, BMI2: Intel Haswell
# 2013+, AMD Zen 1+), not for this machine's CPU (.cargo/config.toml builds the checkout's own
# binary with target-cpu=native), so the image runs on every machine of a cluster that has
# x86-64-v3. Override with PATHFARM_IMAGE_CPU=native (or any target-cpu). The farm refuses
# workers of another build, so one image gives one set of bits. Cost against native: see the
# README's deploy section.
set -euo pipefail
cd "$(dirname "$0")/.."

tag="${1:-pathfarm:local}"
cpu="${PATHFARM_IMAGE_CPU:-x86-64-v3}"
target_dir="target/image-${cpu}"

echo "build-image: building the release binary for target-cpu=${cpu} (${target_dir})" >&2
RUSTFLAGS="-C target-cpu=${cpu}" cargo build --release --locked -p pathfarm --target-dir "${target_dir}"
bin="${target_dir}/release/pathfarm"

ctx="$(mktemp -d)"
trap 'rm -rf "${ctx}"' EXIT
mkdir -p "${ctx}/root/tmp" "${ctx}/root/data" "${ctx}/root/etc"
chmod 1777 "${ctx}/root/tmp"
# the binary, without its debug information
objcopy --strip-debug "${bin}" "${ctx}/root/pathfarm"
# every shared library it loads, and the loader, at the paths it was linked against
ldd "${bin}" | awk '$2 == "=>" && $3 ~ /^\// {print $3} $1 ~ /^\/.*ld-linux/ {print $1}' | sort -u | while read -r lib; do
    mkdir -p "${ctx}/root$(dirname "${lib}")"
    cp -L "${lib}" "${ctx}/root${lib}"
done
# name resolution (docker provides /etc/hosts and /etc/resolv.conf)
printf 'hosts: files dns\n' > "${ctx}/root/etc/nsswitch.conf"
printf 'root:x:0:0:root:/:/pathfarm\nnobody:x:65534:65534:nobody:/:/pathfarm\n' > "${ctx}/root/etc/passwd"
cat > "${ctx}/Dockerfile" <<'DOCKERFILE'
FROM scratch
COPY root/ /
ENV PATH=/ RUST_LOG=info
WORKDIR /data
ENTRYPOINT ["/pathfarm"]
CMD ["--help"]
DOCKERFILE
docker build --quiet -t "${tag}" "${ctx}" >/dev/null
echo "build-image: built ${tag} ($(docker image inspect "${tag}" --format '{{.Size}}') bytes, target-cpu=${cpu})" >&2
