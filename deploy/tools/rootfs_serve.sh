#!/bin/bash
# Run by check_runtime_rootfs.sh inside the Debian 12 root, in a private network namespace (the container's view):
# starts `scone serve` as uid 10001 with the image's ENV (/tmp/check/image.env) and the Kubernetes ConfigMap's
# TOML, then checks the HEALTHCHECK command, the HTTP endpoints, auth, and a clean exit on SIGTERM.
set -uo pipefail
mapfile -t image_env < /tmp/check/image.env
cd /var/lib/scone || exit 1
setpriv --reuid=10001 --regid=10001 --clear-groups env -i HOME=/var/lib/scone PATH=/usr/bin:/bin "${image_env[@]}" \
  /opt/scone/bin/scone serve --config /etc/scone/config/scone.toml > /tmp/check/server.log 2>&1 &
pid=$!
fail=0
expect() { if [ "$2" = "$3" ]; then echo "ok   $1: $3"; else echo "FAIL $1: $3, expected $2"; fail=1; fi; }
code() { curl -s -o /dev/null -w '%{http_code}' --max-time 2 "$@"; }
for _ in $(seq 1 150); do [ "$(code http://127.0.0.1:8080/healthz)" = 200 ] && break; sleep 0.2; done
export "${image_env[@]}"
# The image's HEALTHCHECK, verbatim.
# shellcheck disable=SC2016
/bin/sh -c 'curl -fsS --max-time 2 -o /dev/null http://127.0.0.1:${SCONE_SERVER__HTTP_ADDR##*:}/healthz || exit 1'
expect "HEALTHCHECK command (exit status)" 0 $?
for _ in $(seq 1 150); do [ "$(code http://127.0.0.1:8080/readyz)" = 200 ] && break; sleep 0.2; done
expect "GET /readyz" 200 "$(code http://127.0.0.1:8080/readyz)"
expect "GET /metrics without key" 200 "$(code http://127.0.0.1:8080/metrics)"
expect "GET /v1/maps without key" 401 "$(code http://127.0.0.1:8080/v1/maps)"
key="$(awk '$1 == "read" {print $2}' /etc/scone/secrets/keys)"
expect "GET /v1/maps with x-api-key" 200 "$(code -H "x-api-key: $key" http://127.0.0.1:8080/v1/maps)"
if kill -0 "$pid" 2>/dev/null; then
  kill -TERM "$pid"; wait "$pid"
  expect "exit status after SIGTERM" 0 $?
else
  wait "$pid"; echo "FAIL server exited early with status $?"; fail=1
fi
[ $fail -eq 0 ] || { echo "server log (last lines):"; tail -8 /tmp/check/server.log; }
exit $fail
