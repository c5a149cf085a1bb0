#!/usr/bin/env bash
# Make the environment pmpm needs, idempotently: Debian's HPC stack and a venv at .venv.
# A second call checks two marker conditions and returns in well under a second.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
packages="python3 python3-venv python3-pip python3-numpy python3-scipy python3-petsc4py
  python3-mpi4py python3-h5py-mpi python3-meshio python3-pytest python3-pytest-mpi openmpi-bin
  python3-matplotlib python3-hypothesis"
petsc_site=/usr/lib/petscdir/petsc3.18/x86_64-linux-gnu-real/lib/python3/dist-packages

missing=$(dpkg-query -W -f='${Package} ${Status}\n' $packages 2>/dev/null \
          | awk '$NF != "installed" {print $1}'; \
          for p in $packages; do dpkg-query -W "$p" >/dev/null 2>&1 || echo "$p"; done)
if [ -n "$missing" ]; then
  echo "bootstrap: installing Debian packages: $(echo $missing | tr '\n' ' ')" >&2
  sudo_cmd=""; [ "$(id -u)" = 0 ] || sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends $(echo $missing | sort -u) >&2
fi

if [ ! -f "$venv/.pmpm-ready" ] || [ "$root/pyproject.toml" -nt "$venv/.pmpm-ready" ]; then
  echo "bootstrap: making the virtual environment $venv" >&2
  /usr/bin/python3 -m venv --system-site-packages "$venv"
  site=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  echo "$petsc_site" > "$site/petsc318.pth"
  "$venv/bin/pip" install -q --no-build-isolation --no-deps -e "$root" >&2
  # numba compiles the contact engine (pmpm/collisions/); a wheel from PyPI, with numpy held at
  # Debian's version so that pip never replaces it under Debian's binary modules
  numpy_version=$("$venv/bin/python" -c 'import numpy; print(numpy.__version__)')
  "$venv/bin/pip" install -q "numba==0.68.1" "numpy==$numpy_version" >&2
  "$venv/bin/python" -c 'import petsc4py, mpi4py, h5py, meshio, scipy, numba, pmpm' 
  touch "$venv/.pmpm-ready"
fi
