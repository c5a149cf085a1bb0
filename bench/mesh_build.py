"""Time to build a distributed box mesh (DMPlex create + distribute + numpy arrays), and its memory.

    mpirun --allow-run-as-root -n 2 .venv/bin/python bench/mesh_build.py [N [hex|tet]]
        # default N = 100 (1e6 hexahedra); run ./run_tests.sh or ./run_mpi.sh once first to bootstrap .venv
"""
import resource
import sys
import time

import numpy as np
from mpi4py import MPI

from pmpm.mesh import Mesh


def main():
    comm = MPI.COMM_WORLD
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    cell_type = sys.argv[2] if len(sys.argv) > 2 else "hex"
    comm.Barrier()
    start = time.perf_counter()
    mesh = Mesh.from_box(comm, [0, 0, 0], [1, 1, 1], [n, n, n], cell_type)
    comm.Barrier()
    seconds = time.perf_counter() - start
    rss_mb = comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    volume = comm.allreduce(float(mesh.cell_volume[:mesh.n_owned_cells].sum()))
    if comm.rank == 0:
        print(f"mesh {n}^3 {cell_type}: {mesh.n_global_cells} cells on {comm.size} rank(s): "
              f"{seconds:.2f} s wall, peak RSS summed over ranks {rss_mb:.0f} MB "
              f"({1024 * rss_mb / mesh.n_global_cells:.2f} KB/cell), volume error {abs(volume - 1):.1e}")
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in mesh.build_stages.items())
    print(f"  rank {comm.rank}: {stages}; {mesh.n_owned_cells} owned + {mesh.n_local_cells - mesh.n_owned_cells} ghost cells, "
          f"{len(mesh.face_cells)} faces", flush=True)


if __name__ == "__main__":
    main()
