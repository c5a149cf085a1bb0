#!/usr/bin/env bash
# The test suite: bootstraps the environment, then runs every test on 1 rank and the tests
# marked `mpi` again on 2 ranks.   ./run_tests.sh [pytest options, e.g. -k mesh]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
"$root/tools/bootstrap.sh"
cd "$root"
flags=(--oversubscribe)
[ "$(id -u)" = 0 ] && flags+=(--allow-run-as-root)
export OMPI_MCA_rmaps_base_oversubscribe=1
echo "== 1 rank =="
.venv/bin/python -m pytest -q --with-mpi -x "$@"
echo "== 2 ranks (tests marked mpi) =="
timeout 1200 mpirun "${flags[@]}" -n 2 .venv/bin/python -m pytest -q --with-mpi -m mpi -x "$@" \
  -p no:cacheprovider
