#!/usr/bin/env bash
# Docker smoke test: build the image with compose (the v2 plugin `docker compose` or the v1
# `docker-compose`, whichever exists), start it, wait for its healthcheck, send real queries (msgpack and Open Inference Protocol, compared bit for bit with the same engine in process: the kernel engine, or ONNX
# Runtime), check it runs as non-root without torch/mitsuba, then stop it and check the shutdown
# was graceful (exit status 0 after SIGTERM).
#
#   docker/smoke.sh
#
# Environment: NEUMIP_BASE_IMAGE (default neumip-base:bookworm, made by make_base_image.sh when
# missing), PYTHON (host Python with neumip[train,client,test]; default .venv/bin/python),
# NEUMIP_HOST_PORT (default: a free port), NEUMIP_COMPOSE (the compose command, e.g. "docker-compose";
# default: `docker compose` if the plugin answers, else `docker-compose`). Exit status 3: no Docker
# engine or no compose.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-$ROOT/.venv/bin/python}"
export NEUMIP_BASE_IMAGE="${NEUMIP_BASE_IMAGE:-neumip-base:bookworm}"
export NEUMIP_HOST_PORT="${NEUMIP_HOST_PORT:-$("$PY" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')}"
PROJECT="neumip-smoke-$$"

if ! docker info >/dev/null 2>&1; then
    echo "smoke: no Docker engine answers (start one: dockerd --iptables=false --bridge=none &)" >&2
    exit 3
fi
if [ -n "${NEUMIP_COMPOSE:-}" ]; then
    read -r -a COMPOSE <<< "$NEUMIP_COMPOSE"
elif docker compose version >/dev/null 2>&1; then
    COMPOSE=(docker compose)
elif command -v docker-compose >/dev/null; then
    COMPOSE=(docker-compose)
else
    echo "smoke: neither \`docker compose\` nor \`docker-compose\` is installed (apt-get install docker-compose)" >&2
    exit 3
fi
COMPOSE_NAME="${COMPOSE[*]}"
echo "smoke: $("${COMPOSE[@]}" version 2>&1 | sed -n 1p)"
docker image inspect "$NEUMIP_BASE_IMAGE" >/dev/null 2>&1 || docker/make_base_image.sh "$NEUMIP_BASE_IMAGE"
docker/wheelhouse.sh "$PY"

WORK="$(mktemp -d /tmp/neumip-smoke.XXXXXX)"
COMPOSE+=(-p "$PROJECT" -f compose.yaml)
cleanup() {
    "${COMPOSE[@]}" down --timeout 20 >/dev/null 2>&1 || true
    rm -rf "$WORK"
}
trap cleanup EXIT

# Shipped models when models/ has some; otherwise two small exported ones mounted over /app/models.
MODELS="$ROOT/models"
if ! ls models/*.onnx >/dev/null 2>&1; then
    MODELS="$WORK/models"
    "$PY" docker/smoke_check.py make-models "$MODELS"
    printf 'services:\n  server:\n    volumes:\n      - "%s:/app/models:ro"\n' "$MODELS" > "$WORK/models.yaml"
    COMPOSE+=(-f "$WORK/models.yaml")
fi

echo "smoke: ${COMPOSE[*]} up (base image $NEUMIP_BASE_IMAGE, port 127.0.0.1:$NEUMIP_HOST_PORT)"
"${COMPOSE[@]}" build
"${COMPOSE[@]}" up --detach   # no --wait: docker-compose v1 lacks it; the healthcheck is polled below
CID="$("${COMPOSE[@]}" ps -q server)"
health=starting
for _ in $(seq 120); do
    health="$(docker inspect -f '{{.State.Health.Status}}' "$CID")"
    [ "$health" = starting ] || break
    sleep 1
done
echo "smoke: container $CID is $health"
if [ "$health" != healthy ]; then
    docker logs "$CID" 2>&1 | tail -n 15 >&2
    exit 1
fi
memory="$(docker inspect -f '{{.HostConfig.Memory}}' "$CID")"
[ "$memory" -gt 0 ] || { echo "smoke: the container has no memory limit" >&2; exit 1; }

uid="$(docker exec "$CID" id -u)"
[ "$uid" != 0 ] || { echo "smoke: the server runs as root" >&2; exit 1; }
docker exec "$CID" python3 -c "import importlib.util as u, sys; bad = [m for m in ('torch', 'mitsuba') if u.find_spec(m)]; sys.exit(f'image carries {bad}' if bad else 0)"
published="$(docker port "$CID" 8000/tcp)"
case "$published" in 127.0.0.1:*) ;; *) echo "smoke: port published on $published, not loopback" >&2; exit 1;; esac

"$PY" docker/smoke_check.py check "http://127.0.0.1:$NEUMIP_HOST_PORT" "$MODELS"
echo "smoke: memory in use after the checks: $(docker stats --no-stream --format '{{.MemUsage}}' "$CID")"

"${COMPOSE[@]}" stop --timeout 20 server
code="$(docker inspect -f '{{.State.ExitCode}}' "$CID")"
graceful_logged() {  # the log driver may still be writing the last lines when `stop` returns
    for _ in 1 2 3 4 5; do
        docker logs "$CID" 2>&1 | grep -q "Application shutdown complete" && return 0
        sleep 1
    done
    return 1
}
if ! graceful_logged; then
    echo "smoke: no graceful shutdown in the logs (exit status $code); their end:" >&2
    docker logs "$CID" 2>&1 | tail -n 15 >&2
    exit 1
fi
[ "$code" = 0 ] || { echo "smoke: server exited with status $code after SIGTERM" >&2; exit 1; }
echo "smoke: OK with $COMPOSE_NAME (uid $uid, published on $published, memory limit $((memory >> 20)) MiB, graceful exit 0)"
