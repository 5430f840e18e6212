#!/usr/bin/env bash
# The job-store tests start a real PostgreSQL server of their own (tests/service/postgres_server.py)
# from Debian's binaries (/usr/lib/postgresql/N/bin). Install the `postgresql` package when they
# are missing and we are root with apt; otherwise say so: those tests then fail with the reason
# (or skip under ALLOW_SKIP=1, tests/required_components.py).
set -euo pipefail
have_postgres() {
  compgen -G "/usr/lib/postgresql/*/bin/pg_ctl" >/dev/null || command -v pg_ctl >/dev/null
}
have_postgres && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "renderloop: no PostgreSQL server binaries found; installing postgresql with apt-get" >&2
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq postgresql >/dev/null
  have_postgres && exit 0
fi
echo "renderloop: PostgreSQL server binaries not found (e.g. 'apt-get install postgresql'):" \
     "the PostgreSQL job-store tests will fail (ALLOW_SKIP=1 skips them)" >&2
exit 1
