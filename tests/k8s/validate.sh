#!/usr/bin/env bash
# Validates deploy/k8s against the Kubernetes API schemas, offline (PyPI's
# kubernetes-validate bundles them): every resource the kustomization lists, strictly
# (unknown fields are errors), for the oldest Kubernetes the manifests support (1.27: the
# native gRPC probe is stable from 1.27) and the newest the validator knows. Also checks that
# the kustomization lists every manifest of the directory and only existing ones.
set -euo pipefail
cd "$(dirname "$0")/../../deploy/k8s"
if ! command -v kubernetes-validate >/dev/null 2>&1; then
    python3 -m pip install --quiet --disable-pip-version-check kubernetes-validate
fi
listed="$(awk '/^resources:/{on=1; next} on && /^  - /{print $2; next} on && !/^  /{on=0}' kustomization.yaml | sort)"
present="$(ls *.yaml | grep -v '^kustomization.yaml$' | sort)"
if [ "${listed}" != "${present}" ]; then
    echo "k8s manifests: FAILED: kustomization.yaml lists [${listed//$'\n'/ }], the directory has [${present//$'\n'/ }]" >&2
    exit 1
fi
for version in 1.27.0 1.37.0; do
    # shellcheck disable=SC2086
    kubernetes-validate --strict --quiet -k "${version}" ${listed}
done
echo "k8s manifests: RAN: $(echo ${listed} | wc -w) files valid against Kubernetes 1.27 and 1.37 (strict)"
