"""Analytic and published references used by the validation tests and benchmark scripts."""
from __future__ import annotations

import numpy as np


def stokes_velocity(x: np.ndarray, center: np.ndarray, radius: float, far_velocity: np.ndarray) -> np.ndarray:
    """Stokes (1851) creeping flow past a fixed sphere, uniform ``far_velocity`` far away (n, 3)."""
    r_vec = np.asarray(x, float) - center
    r = np.linalg.norm(r_vec, axis=1)[:, None]
    along = (r_vec @ far_velocity)[:, None]
    return (far_velocity - 0.75 * radius * (far_velocity / r + along * r_vec / r ** 3)
            - 0.25 * radius ** 3 * (far_velocity / r ** 3 - 3 * along * r_vec / r ** 5))


def stokes_drag(viscosity: float, radius: float, speed: float) -> float:
    """6 π μ a U (N)."""
    return 6 * np.pi * viscosity * radius * speed


def rotlet_torque(viscosity: float, radius: float, omega: float) -> float:
    """Torque on a sphere spinning in unbounded still fluid at low Re, 8 π μ a³ ω (N m)."""
    return 8 * np.pi * viscosity * radius ** 3 * omega


def schiller_naumann_drag_coefficient(reynolds):
    """C_D = 24/Re (1 + 0.15 Re^0.687), Re < 800."""
    reynolds = np.asarray(reynolds, float)
    return 24.0 / reynolds * (1 + 0.15 * reynolds ** 0.687)


def square_duct_wall_factor(diameter_over_side: float) -> float:
    """Creeping-flow drag factor K of a sphere on the axis of a square duct, to first order in
    λ = d / side: K = 1 / (1 − 1.903 λ) (Haberman's coefficient, as tabulated by Happel & Brenner,
    Low Reynolds Number Hydrodynamics; the circular tube's is 2.104)."""
    return 1.0 / (1.0 - 1.903 * diameter_over_side)


def terminal_velocity(particle_density, fluid_density, viscosity, diameter, gravity=9.81, wall_factor=1.0):
    """Terminal settling speed with the Schiller–Naumann drag times ``wall_factor``, by
    fixed-point iteration on Re."""
    weight = (particle_density - fluid_density) * np.pi * diameter ** 3 / 6 * gravity
    speed = abs(weight) / (3 * np.pi * viscosity * diameter * wall_factor)          # Stokes first guess
    for _ in range(200):
        reynolds = fluid_density * speed * diameter / viscosity
        cd = wall_factor * schiller_naumann_drag_coefficient(reynolds)
        speed = np.sqrt(abs(weight) / (0.5 * fluid_density * cd * np.pi * diameter ** 2 / 4))
    return speed


def di_felice_wall_factor(diameter_ratio: float, reynolds: float) -> float:
    """Settling speed in a tube over that in unbounded fluid, ((1 − λ)/(1 − 0.33 λ))^a with
    a = (3.3 + 0.085 Re)/(1 + 0.1 Re), λ = sphere over tube diameter (Di Felice 1996, fitted to
    measurements for Re from 0.01 to 200)."""
    exponent = (3.3 + 0.085 * reynolds) / (1 + 0.1 * reynolds)
    return ((1 - diameter_ratio) / (1 - 0.33 * diameter_ratio)) ** exponent


# ten Cate, Nieuwstad, Derksen & Van den Akker (2002), "Particle imaging velocimetry experiments and
# lattice-Boltzmann simulations on a single sphere settling under gravity", Phys. Fluids 14, 4012,
# Table 1: a nylon sphere (d = 15 mm, ρ = 1120 kg/m³) released from rest with its centre 127.5 mm
# above the floor of a closed box 100 × 100 × 160 mm of silicone oil. Per experiment: fluid density
# (kg/m³), viscosity (Pa s), and the measured terminal (largest) settling speed (m/s).
TEN_CATE_2002 = {
    "E1": (970.0, 0.373, 0.038),   # Re 1.5
    "E2": (965.0, 0.212, 0.060),   # Re 4.1
    "E3": (962.0, 0.113, 0.091),   # Re 11.6
    "E4": (960.0, 0.058, 0.128),   # Re 31.9
}
TEN_CATE_BOX = (0.100, 0.100, 0.160)      # m, the sphere released on the vertical axis
TEN_CATE_SPHERE = (0.015, 1120.0, 0.1275)  # diameter (m), density (kg/m³), release height of the centre (m)

# The same spheres and liquids settling through an infinite duct of ten Cate's cross-section, solved
# body-fitted by OpenFOAM v1912 (bench/openfoam_sphere_duct.sh: a held sphere, walls and inflow moving
# at U, simpleFoam on a snappyHexMesh mesh with 24 cells per diameter on the sphere; the terminal speed
# interpolated between the drags at two speeds, bench/accuracy.py --settling, 2026-11-23). Refining the
# sphere's surface to 48 cells per diameter raises the drag by 0.6 % (E1) and 0.5 % (E4), which lowers
# these by 0.6 % and 0.3 %.
# A closed box as tall as ten Cate's settles within 0.6 % of a box 2.5 times taller (pmpm, E1 and E4),
# so these are the terminal speeds of the Navier–Stokes equations in their box, to about 1 %. The
# measured speeds (TEN_CATE_2002) are 4–9 % above them.
TEN_CATE_BODY_FITTED = {"E1": 0.0351, "E2": 0.0581, "E3": 0.0881, "E4": 0.1234}   # m/s
