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


def standard_drag_coefficient(reynolds):
    """The standard drag curve of a sphere: Schiller–Naumann up to Re 800, beyond it Clift, Grace &
    Weber's (1978, Bubbles, Drops and Particles, Table 5.2) fits for 260–1500 and 1500–12000.
    Schiller–Naumann itself lies within about ±5 % of the measurements it was fitted to."""
    reynolds = np.asarray(reynolds, float)
    w = np.log10(reynolds)
    return np.where(reynolds <= 800, schiller_naumann_drag_coefficient(reynolds),
                    np.where(reynolds <= 1500, 10 ** (1.6435 - 1.1242 * w + 0.1558 * w ** 2),
                             10 ** (-2.4571 + 2.5558 * w - 0.9295 * w ** 2 + 0.1049 * w ** 3)))


def oseen_velocity(x: np.ndarray, center: np.ndarray, radius: float, far_velocity: np.ndarray,
                   kinematic_viscosity: float, drag_coefficient: float) -> np.ndarray:
    """Oseen's (1910) flow past a fixed sphere in Lamb's form (Hydrodynamics, §342), with the wake's
    strength set by ``drag_coefficient``: u = U + ∇φ + ∇χ/(2k) − χ e, k = |U|/(2ν),
    χ = B e^{k(x − r)}/r, φ = −(a³|U|/4) x/r³ − B/(2k r), B = F/(4πμ), x = r·e along the stream e.
    It is the far field of any steady flow past a body of drag F (an Oseenlet, the source that feeds
    its wake, and the potential dipole), and Stokes' far field as Re → 0 (B = 3a|U|/2). (n, 3)."""
    far_velocity = np.asarray(far_velocity, float)
    speed = float(np.linalg.norm(far_velocity))
    e = far_velocity / speed
    k = speed / (2 * kinematic_viscosity)
    strength = drag_coefficient * speed ** 2 * radius ** 2 / (8 * kinematic_viscosity)   # B
    r_vec = np.asarray(x, float) - center
    r = np.linalg.norm(r_vec, axis=1)[:, None]
    along = (r_vec @ e)[:, None]
    unit = r_vec / r
    wake = np.exp(k * (along - r))                 # ≤ 1: x ≤ r
    chi = strength * wake / r
    return (far_velocity - 0.25 * radius ** 3 * speed * (e / r ** 3 - 3 * along * r_vec / r ** 5)
            + strength * (1 - wake) / (2 * k * r ** 2) * unit - 0.5 * chi * (e + unit))


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


def beverloo_mass_rate(orifice_diameter, particle_diameter, bulk_density, gravity=9.81, c=0.58, k=1.5):
    """Beverloo's law for the steady discharge of coarse, free-flowing grains from a flat-bottomed
    bin through a circular orifice (kg/s): W = C ρ_b √g (D₀ − k d)^{5/2}, independent of the fill
    height. C = 0.58 and k = 1.5 are Beverloo, Leniger & van de Velde's (1961, Chem. Eng. Sci. 15,
    260) fit over their materials (C ranged 0.55–0.65), for D₀ ≳ 6 d. A conical hopper no steeper
    than the stagnant zone that forms over a flat bottom discharges as the flat-bottomed bin;
    a steeper one faster (Rose & Tanaka's factor, reviewed by Nedderman, Tüzün, Savage & Houlsby
    1982, Chem. Eng. Sci. 37, 1597)."""
    return c * bulk_density * np.sqrt(gravity) * (orifice_diameter - k * particle_diameter) ** 2.5
