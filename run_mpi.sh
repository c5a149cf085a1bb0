#!/usr/bin/env bash
# Run a pmpm case on N MPI ranks, bootstrapping the environment on first use:
#   ./run_mpi.sh [-n N] CASE [--output DIR] [--set KEY=VALUE ...] [--check] [-petsc_option value ...]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
"$root/tools/bootstrap.sh"
ranks=1
if [ "${1:-}" = "-n" ]; then ranks="$2"; shift 2; fi
flags=(--quiet)   # pmpm reports its own errors; mpirun need not repeat them
[ "$(id -u)" = 0 ] && flags+=(--allow-run-as-root)
[ "$ranks" -gt "$(nproc)" ] && flags+=(--oversubscribe)
exec mpirun "${flags[@]}" -n "$ranks" "$root/.venv/bin/python" -m pmpm "$@"
