"""pmpm: the Macroscopic Particle Model, MPI-parallel (README.md, ARCHITECTURE.md)."""
import os


def _on_one_node() -> bool:
    """Whether every rank of this job runs on this machine: Open MPI's mpirun says how many it
    started here and in all; without any launcher, the process is alone."""
    here, everywhere = os.environ.get("OMPI_COMM_WORLD_LOCAL_SIZE"), os.environ.get("OMPI_COMM_WORLD_SIZE")
    if here is not None and everywhere is not None:
        return here == everywhere
    return not any(name in os.environ for name in ("PMIX_RANK", "PMI_RANK", "SLURM_PROCID"))


# Open MPI, as it starts, opens the libraries of its ``cm`` layer (PSM, PSM2: interconnects
# between nodes) to see whether they serve, a large share of a short run's start-up (measured:
# README.md, "The command line"). On one node shared memory carries every message and Open MPI
# picks its ``ob1`` layer anyway, so ``cm`` is skipped there. Every rank decides alike; a job
# across nodes, one under another launcher, and a pml the user chose are left as they are. (Set
# before any module starts MPI, as importing mpi4py.MPI or petsc4py.PETSc does.)
if "OMPI_MCA_pml" not in os.environ and _on_one_node():
    os.environ["OMPI_MCA_pml"] = "^cm"
