#!/usr/bin/env bash
# Runs a command with a throwaway PostgreSQL cluster, then stops and deletes the cluster (also
# when the command fails or is interrupted). The command sees
#   SEPOA_TEST_POSTGRES_URL=postgresql+psycopg://sepoa@/sepoa_test?host=<socket folder>
# a database owned by the `sepoa` superuser, reachable only through a unix socket in a private
# temporary folder (no TCP port, so it cannot clash with another cluster). The queue tests
# (tests/labelqueue/conftest.py) then also run on PostgreSQL, each in a schema of its own.
#
#   bash scripts/with_postgres.sh .venv/bin/python -m pytest -q tests/labelqueue
#
# Needs Debian's postgresql package (scripts/setup.sh --for-tests installs it). PostgreSQL
# refuses to run as root: as root the cluster runs as the `postgres` user. Exits 1, saying why, when the cluster
# cannot be started; otherwise with the command's exit status.
set -euo pipefail

if [ $# -eq 0 ]; then
    echo "usage: $0 COMMAND [ARGS...]" >&2
    exit 2
fi

bindir=$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -n 1 || true)
if [ -z "$bindir" ] || [ ! -x "$bindir/initdb" ]; then
    echo "with_postgres: no PostgreSQL server found under /usr/lib/postgresql/*/bin" \
        "(apt-get install postgresql; scripts/setup.sh --for-tests does)" >&2
    exit 1
fi

pgtmp=$(mktemp -d "${TMPDIR:-/tmp}/sepoa-pg.XXXXXX")
as_owner=()
if [ "$(id -u)" -eq 0 ]; then
    if ! id postgres >/dev/null 2>&1; then
        echo "with_postgres: running as root and there is no 'postgres' user to run the" \
            "cluster as" >&2
        rm -rf "$pgtmp"
        exit 1
    fi
    chown postgres: "$pgtmp"
    as_owner=(runuser -u postgres --)
fi
# The temporary folder's own mode (0700) keeps other users off the socket and the data.
data="$pgtmp/data"
log="$pgtmp/server.log"

pg() {
    # A PostgreSQL program as the cluster's owner, from a folder that owner can read.
    (cd "$pgtmp" && "${as_owner[@]}" "$bindir/$1" "${@:2}")
}

cleanup() {
    if [ -f "$data/postmaster.pid" ]; then
        pg pg_ctl -D "$data" -m immediate -w stop >/dev/null 2>&1 || true
    fi
    rm -rf "$pgtmp"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

fail() {
    echo "with_postgres: $1" >&2
    [ -f "$log" ] && sed 's/^/    /' "$log" >&2
    exit 1
}

init_log="$pgtmp/initdb.log"
if ! pg initdb -D "$data" -U sepoa --auth=trust --encoding=UTF8 --no-locale >"$init_log" 2>&1; then
    sed 's/^/    /' "$init_log" >&2
    fail "initdb failed (output above)"
fi
# Throwaway data: no fsync; a socket in the private folder and no TCP listener.
options="-k $pgtmp -c listen_addresses= -c fsync=off -c synchronous_commit=off"
options+=" -c full_page_writes=off -c max_connections=200"
if ! pg pg_ctl -D "$data" -l "$log" -o "$options" -w -t 60 start >/dev/null 2>&1; then
    fail "the PostgreSQL server did not start (its log below)"
fi
if ! pg createdb -h "$pgtmp" -U sepoa sepoa_test >/dev/null 2>&1; then
    fail "could not create the test database"
fi

export SEPOA_TEST_POSTGRES_URL="postgresql+psycopg://sepoa@/sepoa_test?host=$pgtmp"
echo "with_postgres: PostgreSQL $("$bindir/postgres" --version | awk '{print $3}') on" \
    "$pgtmp (SEPOA_TEST_POSTGRES_URL set)"
set +e
"$@"
status=$?
set -e
exit "$status"
