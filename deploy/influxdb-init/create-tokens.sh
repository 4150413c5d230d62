#!/bin/bash
# Run once by the influxdb:2.7 image, on its first start only (an empty data volume), after
# DOCKER_INFLUXDB_INIT_MODE=setup created the organisation, the bucket and the admin token
# (the image exports DOCKER_INFLUXDB_INIT_ORG and DOCKER_INFLUXDB_INIT_BUCKET_ID, and the
# `influx` CLI is configured with the admin token).
#
# Creates two tokens that can do only what their user needs, and writes each into the
# volume that only its user mounts (read-only there):
#   /tokens/supervisor/token  write access to the bucket    (the supervisors' spool)
#   /tokens/grafana/token     read access to the bucket     (the dashboards)
# Lost tokens (a removed token volume): create new ones with the same commands, using the
# admin token from deploy/secrets/, and put them back into the volumes.
set -euo pipefail

TOKENS_DIR=${TOKENS_DIR:-/tokens}  # the tests point it elsewhere

create() { # description, permission flag, output file
    local json token
    json=$(influx auth create --org "${DOCKER_INFLUXDB_INIT_ORG}" --description "$1" \
        "$2" "${DOCKER_INFLUXDB_INIT_BUCKET_ID}" --json)
    token=$(printf '%s\n' "${json}" | sed -n 's/^[[:space:]]*"token":[[:space:]]*"\([^"]*\)".*$/\1/p')
    if [ -z "${token}" ]; then
        echo "create-tokens: no token in the answer of influx auth create ($1)" >&2
        exit 1
    fi
    mkdir -p "$(dirname "$3")"
    # Written before it is readable; 0444 because the consumer runs as its own uid.
    umask 077
    printf '%s\n' "${token}" > "$3.tmp"
    chmod 0444 "$3.tmp"
    mv "$3.tmp" "$3"
    echo "create-tokens: $1 → $3"
}

create "bench supervisors: write ${DOCKER_INFLUXDB_INIT_BUCKET}" --write-bucket "${TOKENS_DIR}/supervisor/token"
create "grafana: read ${DOCKER_INFLUXDB_INIT_BUCKET}" --read-bucket "${TOKENS_DIR}/grafana/token"
